"""How the detector reads an image (``rebar_data.perception.inference.detector``): the mirrored reading, in which the
first stage reads the image and its mirror image and the second stage reads its int8 copy, and the single
one."""

from __future__ import annotations

import numpy as np
import pytest

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.evaluate import first_stage_only
from rebar_data.perception.evaluation.metrics import match
from rebar_data.perception.inference import detector as infer
from rebar_data.perception.inference.detector import READINGS, Detector
from rebar_data.perception.inference.refine import Refiner
from tests.perception.conftest import refined


def _shipped(**kw) -> Detector:
    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    return Detector.load(threads=1, runtime="onnxruntime", **kw)


def test_a_reading_is_one_of_the_accepted_names():
    assert READINGS == ("mirrored", "single")
    with pytest.raises(
        ConfigError, match="reading = 'twice' is not accepted; accepted: one of mirrored, single"
    ):
        Detector.load(reading="twice")


def test_the_mirrored_reading_of_a_mirror_image_is_the_mirrored_reading_turned_back():
    """The two readings swap roles for the mirror image: its output is the image's own, cell for cell
    turned left for right, the column offsets pointing the other way (to rounding: the same two network
    calls, added in the other order)."""
    from tests.perception.synthetic import drawn_frame

    det = _shipped()
    rgb, _ = drawn_frame()
    rgb = np.ascontiguousarray(rgb[:, :624])  # a whole number of the network's 16 px blocks
    h, w = rgb.shape[:2]
    camera, mirrored_camera = (520.0, 520.0, 301.5, 247.0), (520.0, 520.0, w - 301.5, 247.0)
    out = det.raw(rgb, camera=camera)
    turned = det.raw(np.ascontiguousarray(rgb[:, ::-1]), camera=mirrored_camera)
    np.testing.assert_allclose(turned[0], out[0][:, ::-1], atol=1e-5)
    np.testing.assert_allclose(turned[1], -out[1][:, ::-1], atol=1e-5)
    np.testing.assert_allclose(turned[2], out[2][:, ::-1], atol=1e-5)
    det.reading = "single"  # not so for one reading: the network is not mirror-symmetric
    single = det.raw(rgb, camera=camera)
    assert np.abs(det.raw(rgb[:, ::-1].copy(), camera=mirrored_camera)[0] - single[0][:, ::-1]).max() > 0.05


@pytest.mark.parametrize("width, height", [(640, 480), (627, 470), (625, 461)])
def test_the_mirror_image_lands_on_the_cells_of_the_image_at_any_size(width, height):
    """The image is padded to whole blocks before it is mirrored, so the mirror's cells fall on the image's
    own: the first stage's peaks in the two readings lie where each other's do (a cell off would move every
    one by half a cell, 2 px, one way)."""
    from tests.perception.synthetic import drawn_frame

    det = _shipped()
    rgb = np.ascontiguousarray(drawn_frame()[0][:height, :width])
    with first_stage_only(det):
        det.reading = "single"
        single = det.detect(rgb, threshold=0.5)
        det.reading = "mirrored"
        mirrored = det.detect(rgb, threshold=0.5)
    p, g, dist = match(single[:, :2], mirrored[:, :2], 3.0)
    assert len(dist) >= 0.9 * len(single) > 50, (len(dist), len(single))
    shift = (mirrored[p, :2] - single[g, :2]).mean(axis=0)
    assert np.abs(shift).max() < 0.25 and np.median(dist) < 0.75, (shift, np.median(dist))


def test_the_mirrored_reading_reads_every_second_stage_pass_in_the_int8_copy_and_the_later_in_one_view():
    calls: list[tuple[str, int]] = []

    def network(name: str, offset: float):
        def run(x: np.ndarray) -> np.ndarray:
            calls.append((name, len(x)))
            out = np.zeros((len(x), 4), np.float32)
            out[:, 0], out[:, 2] = offset, 1.0
            return out

        return run

    refiner = Refiner(
        network("float", 0.0), patch_px=16, iterations=2, verifies=True, views=2, first_pass_views=1,
        int8_run=network("int8", 0.0),
    )  # fmt: skip
    image = np.zeros((64, 64, 3), np.uint8)
    points = np.array([[20.0, 30.0], [40.0, 33.0]])
    refined(refiner, image, points)
    assert calls == [("float", 2), ("int8", 4)]  # the single reading: two views of two patches later
    calls.clear()
    refined(refiner, image, points, mirrored=True)
    assert calls == [("int8", 2), ("int8", 2)]
    calls.clear()
    refiner.int8_run = None  # a model without the copy reads the float file throughout
    refined(refiner, image, points, mirrored=True)
    assert calls == [("float", 2), ("float", 2)]


def test_the_shipped_detector_reads_mirrored_by_default_and_finds_the_crossings_either_way():
    from tests.perception.synthetic import drawn_frame

    det = _shipped()
    assert det.reading == "mirrored" and _shipped(reading="single").reading == "single"
    rgb, _ = drawn_frame()
    mirrored = det.detect(rgb)
    det.reading = "single"
    single = det.detect(rgb)
    p, g, dist = match(single[:, :2], mirrored[:, :2], 3.0)
    # the confident crossings are the same ones, placed within a fraction of a pixel of each other
    assert len(dist) >= 0.9 * max(len(single), len(mirrored)) > 30, (len(dist), len(single), len(mirrored))
    assert np.median(dist) < 0.3, np.median(dist)
