"""A frame whose crossings are seen small is read a second time, larger (``Detector.zoom``,
:class:`rebar_data.perception.inference.detector.Zoom`): the first reading's box sides decide, and the
crossings come back in the frame's own pixels."""

from __future__ import annotations

import numpy as np
import pytest

from rebar_data.perception.evaluation.metrics import Truth, pixel_metrics
from rebar_data.perception.inference import detector as infer
from rebar_data.perception.inference.detector import Detector, Zoom
from rebar_data.perception.inference.image import resample


def test_the_zoom_reads_again_only_where_the_crossings_are_seen_small():
    z = Zoom(below_px=24.0, to_px=32.0, at_most=1.6, min_detections=3, above_px=None)
    assert z.factor(None) == 1.0  # no size output
    assert z.factor(np.array([10.0, 10.0])) == 1.0  # too few to judge a frame by
    assert z.factor(np.array([30.0, 24.0, 40.0])) == 1.0  # seen as the first stage learnt them
    assert z.factor(np.array([20.0, 22.0, 26.0])) == pytest.approx(32.0 / 22.0)
    assert z.factor(np.array([10.0, 12.0, 15.0, 90.0])) == 1.6  # at most this much larger
    assert z.factor(np.array([80.0, 90.0, 100.0])) == 1.0  # shrinking is off without above_px
    big = Zoom(above_px=60.0, shrink_to_px=45.0, at_least=0.5)
    assert big.factor(np.array([70.0, 75.0, 90.0])) == pytest.approx(45.0 / 75.0)
    assert big.factor(np.array([100.0, 110.0, 120.0])) == 0.5  # at least this large
    assert big.factor(np.array([40.0, 50.0, 60.0])) == 1.0


def test_a_frame_of_small_crossings_is_read_again_larger_and_answered_in_its_own_pixels(rendered_frame):
    """The rendered frame shrunk to half its size and tiled 2 x 2 into a 640x480 frame of the same focal
    length: its crossings are seen at half the size the first stage learnt, as from twice as far. Read again
    1.6 times larger (the second reading 1024x768), more of them are found within 2 px than from the one
    reading, and they come back in the frame's own pixels."""
    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    det = Detector.load(threads=1, runtime="onnxruntime")
    rgb, truth, box, camera = rendered_frame
    assert rgb.shape[:2] == (480, 640)
    small = resample(rgb, (240, 320))
    tiled = np.vstack([np.hstack([small] * 2)] * 2)
    offsets = np.array([[0, 0], [320, 0], [0, 240], [320, 240]], float)
    truth_tiled = Truth(np.vstack([truth / 2.0 + o for o in offsets]), np.tile(box / 2.0, 4))
    shapes: list[tuple[int, int]] = []
    run = det._run
    det._run = lambda image, rays: shapes.append(image.shape[:2]) or run(image, rays)
    zoomed = det.detect(tiled, camera=camera)
    assert set(shapes) == {(480, 640), (768, 1024)}, shapes
    shapes.clear()
    det.zoom = None
    once = det.detect(tiled, camera=camera)
    assert set(shapes) == {(480, 640)}
    with_zoom = pixel_metrics([truth_tiled], [zoomed])
    without = pixel_metrics([truth_tiled], [once])
    assert with_zoom.pck[2.0] > without.pck[2.0], (with_zoom.pck, without.pck)
    assert with_zoom.precision >= 0.9, with_zoom.precision
