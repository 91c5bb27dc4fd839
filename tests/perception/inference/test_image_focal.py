"""A frame from a camera with another focal length is read at the one the detector trained at
(``rebar_data.perception.inference.image``): resized to it, every stage run there, positions returned in the
caller's pixels."""

from __future__ import annotations

import numpy as np
import pytest

from rebar_data.camera import Intrinsics
from rebar_data.errors import ConfigError
from rebar_data.perception.evaluation.metrics import Truth, match, pixel_metrics
from rebar_data.perception.inference import detector as infer
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.inference.image import TOLERANCE, focal_scale, resample

CAMERA = (525.0, 525.0, 320.0, 240.0)


def _twice(camera: tuple[float, float, float, float]) -> Intrinsics:
    """The intrinsics (fx, fy, cx, cy) of a 640x480 frame, for that frame enlarged to 1280x960."""
    return Intrinsics(640, 480, *camera).resized(1280, 960)


def _camera(fx: float, fy: float) -> Intrinsics:
    return Intrinsics(1280, 960, fx, fy, 640.0, 480.0)


def _shipped() -> Detector:
    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    return Detector.load(threads=1, runtime="onnxruntime")


def _frame() -> tuple[np.ndarray, np.ndarray, Truth]:
    """The bench's drawn 640x480 frame (focal length 525 px), its depth and its visible crossings."""
    from tests.perception.synthetic import drawn_frame_labelled

    rgb, records, depth = drawn_frame_labelled()
    vis = [r for r in records if r["visibility"] == 2]
    return (
        rgb,
        depth,
        Truth(np.array([[r["u"], r["v"]] for r in vis]), np.array([r["box_size_px"] for r in vis])),
    )


def test_the_scale_brings_the_focal_length_to_the_trained_one():
    assert focal_scale(525.0, _camera(1050.0, 1050.0)) == 0.5
    assert focal_scale(525.0, _camera(1000.0, 1100.0)) == 0.5  # the mean of fx and fy
    assert focal_scale(525.0, _camera(525.0 * (1 + TOLERANCE / 2), 525.0)) == 1.0  # near enough
    assert focal_scale(525.0, _camera(589.4, 589.4)) == 1.0  # the servo suites' Kinect: as it comes
    assert focal_scale(525.0, _camera(700.0, 700.0)) == 0.75
    assert focal_scale(None, _camera(1050.0, 1050.0)) == 1.0  # a file that does not say
    resized = Intrinsics(640, 480, 600.0, 610.0, 320.0, 240.0).resized(320, 120)
    assert resized == Intrinsics(320, 120, 300.0, 152.5, 160.0, 60.0)
    depth = np.array([[1.0, 0.0], [0.0, 2.0]], np.float32)
    assert set(np.unique(resample(depth, (4, 4), nearest=True))) == {0.0, 1.0, 2.0}  # no blend across edges


def test_a_frame_twice_as_large_is_read_at_the_trained_scale_and_answered_in_its_own_pixels(rendered_frame):
    """The rendered frame enlarged to 1280x960 with its intrinsics: the first stage reads it at 640x480
    (the trained focal length), and the crossings come back in the large frame's pixels, found as on the
    frame itself. Read as it comes, the first stage reads 1280x960."""
    det = _shipped()
    rgb, truth, box, camera = rendered_frame
    assert det.focal_px == 525.0 and camera[0] == 525.0
    shapes: list[tuple[int, int]] = []
    run = det._run
    det._run = lambda image, rays: shapes.append(image.shape[:2]) or run(image, rays)
    large = resample(rgb, (960, 1280))
    found = det.detect(large, camera=_twice(camera))
    assert set(shapes) == {(480, 640)}  # the frame and its mirror image, at the trained scale
    px = pixel_metrics([Truth(truth * 2.0, box * 2.0)], [found])  # the large frame's pixels
    assert px.recall >= 0.95 and px.precision >= 0.95, (px.recall, px.precision)
    assert px.pck[5.0] >= 0.95 and px.median_px < 2.0, (px.pck, px.median_px)
    shapes.clear()
    det.resample = False
    det.detect(large, camera=_twice(camera))
    assert set(shapes) == {(960, 1280)}


def test_a_frame_at_the_trained_focal_length_is_read_as_it_comes(monkeypatch):
    det = _shipped()
    rgb, depth, _ = _frame()
    expected = det.detect(rgb, camera=CAMERA)

    def refuse(*args, **kwargs):
        raise AssertionError("resampled a frame at the trained focal length")

    monkeypatch.setattr(infer, "resample", refuse)
    near = (525.0 * (1 + TOLERANCE / 2),) * 2 + CAMERA[2:]
    assert len(det.detect(rgb, camera=near, depth=depth))
    np.testing.assert_array_equal(det.detect(rgb, camera=CAMERA), expected)
    det.focal_px = None  # a file written before the focal length was stored: read as it comes
    assert len(det.detect(rgb, camera=(1050.0, 1050.0, 640.0, 480.0)))
    with pytest.raises(ConfigError, match="camera: intrinsics of a 1280x960 image for a 640x480 one"):
        det.detect(rgb, camera=_twice(CAMERA))


def test_the_depth_image_is_resampled_with_the_frame(monkeypatch):
    """With depth, the drawn frame enlarged twice gives the crossings the frame itself gives: the depth image
    is resized with it (nearest pixel), so the depth check reads the same depth image at the same points."""
    det = _shipped()
    rgb, depth, _ = _frame()
    read = []  # what the depth check is given: (depth image, points)
    veto = det.depth_check.veto
    monkeypatch.setattr(det.depth_check, "veto", lambda d, uv: read.append((d, uv.copy())) or veto(d, uv))
    at_scale = det.detect(rgb, camera=CAMERA, depth=depth)
    large, large_depth = resample(rgb, (960, 1280)), resample(depth, (960, 1280), nearest=True)
    resampled = det.detect(large, camera=_twice(CAMERA), depth=large_depth)
    p, g, _ = match(at_scale[:, :2], resampled[:, :2] / 2.0, 1.5)
    assert len(at_scale) >= 20 and len(p) >= 0.9 * max(len(at_scale), len(resampled)), (
        len(at_scale),
        len(resampled),
        len(p),
    )
    (first, first_uv), (second, second_uv) = read
    assert second.shape == depth.shape and np.array_equal(first, second)
    near = np.linalg.norm(first_uv[:, None] - second_uv[None], axis=2).min(axis=1)
    assert np.mean(near < 1.5) >= 0.9  # the points it reads lie in the trained frame's pixels


def test_detect_on_images_takes_the_camera_and_answers_in_the_images_pixels(rendered_frame, tmp_path, capsys):
    """`rebar detect IMAGE --camera FX,FY,CX,CY`: the rendered frame saved at 1280x960 with its intrinsics
    gives its crossings in its own pixels; a malformed camera is refused in one line with nothing written."""
    import cv2
    import pyarrow.parquet as pq

    from rebar_data.cli import main

    _shipped()
    rgb, truth, box, camera = rendered_frame
    image = tmp_path / "frame.png"
    cv2.imwrite(str(image), cv2.cvtColor(resample(rgb, (960, 1280)), cv2.COLOR_RGB2BGR))
    k = _twice(camera)
    text = ",".join(f"{c:g}" for c in (k.fx, k.fy, k.cx, k.cy))
    assert main(["detect", str(image), "--out", str(tmp_path / "out"), "--camera", text]) == 0
    rows = pq.read_table(tmp_path / "out/detections.parquet").to_pandas()
    found = rows[["u", "v", "score"]].to_numpy()
    px = pixel_metrics([Truth(truth * 2.0, box * 2.0)], [found])
    assert px.recall >= 0.95 and px.pck[5.0] >= 0.95, (px.recall, px.pck)
    capsys.readouterr()
    for bad in ("1050,1050,640", "0,1050,640,480", "a,b,c,d"):
        assert main(["detect", str(image), "--out", str(tmp_path / "bad"), "--camera", bad]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "accepted: FX,FY,CX,CY" in err[0], err
    assert not (tmp_path / "bad").exists()


def test_a_camera_beside_a_dataset_is_refused(drawn_dataset, tmp_path, capsys):
    """A dataset's frames carry their own intrinsics: `rebar score` takes no --camera."""
    from rebar_data.cli import main

    out = tmp_path / "p.parquet"
    with pytest.raises(SystemExit) as e:
        main(["score", str(drawn_dataset), "--out", str(out), "--camera", "525,525,320,240"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and "unrecognized arguments: --camera" in err[-1] and not out.exists(), err
