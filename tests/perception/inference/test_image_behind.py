from __future__ import annotations

import numpy as np
import pytest

from rebar_data.perception.inference import detector as infer
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.inference.image import GAP_M, behind_mask, flatten_behind, front_depth

H, W = 240, 320


def _scene():
    """A steeply tilted top mat (0.5 m at the left edge to 0.9 m at the right: 1.25 mm a pixel, 75 mm over
    one window), its bars every 40 px both ways and 8 px wide, the outermost 16 px from the frame's edges; a lower mat 0.15 m behind it, bars 6 px wide
    half way between; the ground 1.5 m away. Colour: top bars grey, lower bars red, ground sand."""
    u = np.arange(W)[None, :].repeat(H, 0)
    v = np.arange(H)[:, None].repeat(W, 1)
    plane = (0.5 + 0.4 * u / (W - 1)).astype(np.float32)
    top = ((u - 16) % 40 < 8) | ((v - 16) % 40 < 8)
    lower = ~top & (((u + 4) % 40 < 6) | ((v + 4) % 40 < 6))
    depth = np.where(top, plane, np.where(lower, plane + 0.15, 1.5)).astype(np.float32)
    rgb = np.empty((H, W, 3), np.uint8)
    rgb[:] = (200, 180, 120)
    rgb[lower] = (180, 40, 30)
    rgb[top] = (120, 120, 120)
    return rgb, depth, top, lower


def test_the_lower_mat_and_ground_lie_behind_and_a_tilted_top_mat_does_not():
    rgb, depth, top, lower = _scene()
    behind = behind_mask(depth)
    assert not behind[top].any()  # the far side of the tilted mat keeps its bars
    assert behind[lower].all() and behind[~top & ~lower].all()
    # the front follows the tilt: at the bars, never behind them, and away from the frame's edges (where a
    # window is clipped) within a cell's tilt of their own depth
    front = front_depth(depth)
    assert (front[top] <= depth[top] + 0.006).all()
    inner = top.copy()
    inner[:, :30] = inner[:, -30:] = False
    np.testing.assert_allclose(front[inner], depth[inner], atol=0.006)
    # a plain minimum over the same window would have taken the near side's depth for the far side's front
    assert (depth[top] - np.min(depth[top])).max() > GAP_M


def test_flatten_keeps_the_front_and_fills_what_lies_behind_with_its_surroundings():
    rgb, depth, top, lower = _scene()
    out = flatten_behind(rgb, depth)
    np.testing.assert_array_equal(out[top], rgb[top])  # the bars in front to the bit
    # the lower bars are gone: their pixels now take the colour around them, mostly the ground's
    red = out[lower].astype(float)
    assert (red[:, 0] - red[:, 1]).mean() < 0.5 * (180 - 40)
    assert np.abs(out[~top & ~lower].astype(float) - rgb[~top & ~lower]).mean() < 40
    assert flatten_behind(rgb, depth) is not rgb and (rgb[lower] == (180, 40, 30)).all()  # input untouched


def test_no_measurement_leaves_the_image_as_it_is():
    rgb, depth, _, _ = _scene()
    np.testing.assert_array_equal(flatten_behind(rgb, np.zeros_like(depth)), rgb)
    holes = depth.copy()
    holes[:, ::3] = 0.0  # pixels without a measurement are kept, and the rest still read
    out = flatten_behind(rgb, holes)
    np.testing.assert_array_equal(out[:, ::3], rgb[:, ::3])
    assert not np.array_equal(out, rgb)


def test_the_shipped_model_reads_a_rendered_frame_with_depth_through_it(
    rendered_frame, rendered_depth, monkeypatch
):
    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    from rebar_data.perception.evaluation.metrics import Truth, pixel_metrics

    rgb, truth, box, camera = rendered_frame
    assert behind_mask(rendered_depth).mean() > 0.2  # the frame shows the ground between the bars
    det = Detector.load(threads=1)
    assert not det.flatten_behind  # off unless asked for (registration, the servo: the module text)
    det.flatten_behind = True
    seen = []
    monkeypatch.setattr(
        infer, "flatten_behind", lambda image, depth_m: seen.append(1) or flatten_behind(image, depth_m)
    )
    found = det.detect(rgb, camera=camera, depth=rendered_depth)
    assert seen == [1]
    px = pixel_metrics([Truth(truth, box)], [found])
    assert px.recall >= 0.95 and px.precision >= 0.95, (px.recall, px.precision)
    assert px.pck[2.0] >= 0.9 and px.median_px < 1.0, (px.pck, px.median_px)
    # the crossing-point stage reads the frame as it comes, as it trained
    read = []
    points = det.crossing_point.points
    monkeypatch.setattr(
        det.crossing_point, "points", lambda image, *a: read.append(image) or points(image, *a)
    )
    det.detect(rgb, camera=camera, depth=rendered_depth, point="crossing")
    assert seen == [1, 1] and len(read) == 1 and np.array_equal(read[0], rgb)
    # switched off, the colour image is read as it comes
    det.flatten_behind = False
    det.detect(rgb, camera=camera, depth=rendered_depth)
    assert seen == [1, 1]


def test_score_flattens_a_datasets_frames_when_asked_and_refuses_it_without_depth(
    drawn_dataset, tmp_path, capsys, monkeypatch
):
    from rebar_data.cli import main

    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    seen = []
    monkeypatch.setattr(infer, "flatten_behind", lambda image, depth_m: seen.append(depth_m.shape) or image)
    args = ["score", str(drawn_dataset), "--split", "test", "--threads", "1"]
    assert main([*args, "--out", str(tmp_path / "plain.parquet")]) == 0 and not seen
    assert main([*args, "--out", str(tmp_path / "flat.parquet"), "--flatten-behind"]) == 0
    assert len(seen) == 2  # each test frame, with its depth image
    capsys.readouterr()
    out = tmp_path / "refused"
    assert main(["score", str(drawn_dataset), "--out", str(out), "--flatten-behind", "--no-depth"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "which --no-depth leaves out" in err[0], err
    # images given as files have no depth: `rebar detect` takes no --flatten-behind
    image = str(next((drawn_dataset / "images").rglob("*.png")))
    with pytest.raises(SystemExit) as e:
        main(["detect", image, "--out", str(out), "--flatten-behind"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and "unrecognized arguments: --flatten-behind" in err[-1], err
    assert not out.exists()
