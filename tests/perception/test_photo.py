"""A photograph's camera from its EXIF (``rebar_data.perception.photo``): the intrinsics `rebar detect IMAGES`
reads a photograph with when ``--camera`` gives none."""

from __future__ import annotations

import math

import numpy as np
import pytest
from PIL import Image

from rebar_data.perception.evaluation.data import read_image
from rebar_data.perception.evaluation.metrics import Truth, pixel_metrics
from rebar_data.perception.inference import detector as infer
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.inference.image import resample
from rebar_data.perception.photo import EXIF_IFD, FOCAL_LENGTH_35MM, focal_35mm, photo_camera

ORIENTATION = 0x0112


def _save(path, rgb: np.ndarray, *, f35: int | None = None, orientation: int | None = None) -> None:
    """``rgb`` as a JPEG (or PNG, by the suffix) carrying the EXIF tags given."""
    exif = Image.Exif()
    if f35 is not None:
        exif.get_ifd(EXIF_IFD)[FOCAL_LENGTH_35MM] = f35
    if orientation is not None:
        exif[ORIENTATION] = orientation
    kw = {"quality": 95} if str(path).endswith(".jpg") else {}
    Image.fromarray(rgb).save(path, exif=exif, **kw)


def test_the_35mm_equivalent_gives_the_focal_length_across_the_diagonal(tmp_path):
    path = tmp_path / "p.jpg"
    _save(path, np.zeros((960, 1280, 3), np.uint8), f35=28)
    assert focal_35mm(path) == 28.0
    found = photo_camera(path, 960, 1280)
    f = 28.0 * 1600.0 / math.hypot(36.0, 24.0)  # 1035.4 px: a 1280x960 frame's diagonal is 1600 px
    assert found.focal_35mm == 28.0
    np.testing.assert_allclose(found.camera, (f, f, 640.0, 480.0))
    # the training camera (525 px across 640) is a 28 mm equivalent
    assert 525.0 * math.hypot(36.0, 24.0) / 800.0 == pytest.approx(28.4, abs=0.05)


def test_a_file_without_the_focal_length_gives_none(tmp_path):
    rgb = np.zeros((48, 64, 3), np.uint8)
    _save(tmp_path / "plain.jpg", rgb)
    _save(tmp_path / "unknown.jpg", rgb, f35=0)  # 0: "unknown" in the standard
    _save(tmp_path / "corrupt.jpg", rgb, f35=29122)  # no lens has it
    _save(tmp_path / "plain.png", rgb)
    (tmp_path / "text.jpg").write_text("not an image")
    for name in ("plain.jpg", "unknown.jpg", "corrupt.jpg", "plain.png", "text.jpg", "missing.jpg"):
        assert focal_35mm(tmp_path / name) is None, name
        assert photo_camera(tmp_path / name, 48, 64) is None, name


def test_a_turned_photograph_gets_the_centre_of_the_image_as_read(tmp_path):
    """EXIF orientation 6 (turned a quarter): OpenCV turns the image as it reads it, and the intrinsics
    are those of the turned image."""
    path = tmp_path / "turned.jpg"
    _save(path, np.zeros((480, 640, 3), np.uint8), f35=28, orientation=6)
    rgb = read_image(path)
    assert rgb.shape[:2] == (640, 480)
    found = photo_camera(path, *rgb.shape[:2])
    assert found.camera[2:] == (240.0, 320.0)
    assert found.camera[0] == pytest.approx(28.0 * 800.0 / math.hypot(36.0, 24.0))


def test_detect_reads_a_photographs_focal_length_from_its_exif(rendered_frame, tmp_path, capsys, monkeypatch):
    """A rendered frame enlarged twice and cut to its central 960x720 (its focal length 1050 px, where the
    field-of-view guess gives 787): saved as a JPEG with a 38 mm equivalent, `rebar detect` reads it with
    that focal length (1054 px) and finds its crossings in its own pixels; ``--no-exif`` and ``--camera``
    read it as they say."""
    import pyarrow.parquet as pq

    from rebar_data.cli import main

    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    rgb, truth, box, camera = rendered_frame
    assert camera == (525.0, 525.0, 320.0, 240.0)
    photo = resample(rgb, (960, 1280))[120:840, 160:1120]
    path = tmp_path / "photo.jpg"
    _save(path, np.ascontiguousarray(photo), f35=round(1050.0 * math.hypot(36.0, 24.0) / 1200.0))
    cameras: list = []
    detect = Detector.detect
    monkeypatch.setattr(
        Detector, "detect", lambda self, rgb, **kw: cameras.append(kw["camera"]) or detect(self, rgb, **kw)
    )

    assert main(["detect", str(path), "--out", str(tmp_path / "exif"), "--threads", "1"]) == 0
    fx = 38.0 * 1200.0 / math.hypot(36.0, 24.0)
    np.testing.assert_allclose(cameras[-1], (fx, fx, 480.0, 360.0))
    assert "camera: EXIF 38 mm equivalent, fx 1054 px" in capsys.readouterr().err
    found = pq.read_table(tmp_path / "exif/detections.parquet").to_pandas()[["u", "v", "score"]].to_numpy()
    uv = truth * 2.0 - [160.0, 120.0]
    inside = (uv[:, 0] >= 0) & (uv[:, 0] < 960) & (uv[:, 1] >= 0) & (uv[:, 1] < 720)
    px = pixel_metrics([Truth(uv[inside], box[inside] * 2.0)], [found])
    assert inside.sum() >= 10 and px.recall >= 0.9 and px.pck[5.0] >= 0.9, (inside.sum(), px.recall, px.pck)

    import json

    read_with = json.loads((tmp_path / "exif/cameras.json").read_text())["photo"]
    assert read_with["fx"] == pytest.approx(fx) and (read_with["width"], read_with["height"]) == (960, 720)
    assert read_with["from"] == "EXIF 38 mm equivalent, fx 1054 px"
    assert main(["detect", str(path), "--out", str(tmp_path / "fov"), "--threads", "1", "--no-exif"]) == 0
    guess = json.loads((tmp_path / "fov/cameras.json").read_text())["photo"]
    assert guess["fx"] == pytest.approx(525.0 / 640.0 * 960.0) and guess["cx"] == 480.0
    assert (
        cameras[-1] is None
        and "camera: the training camera's field of view, --no-exif" in capsys.readouterr().err
    )
    given = "1050,1050,480,360"
    assert (
        main(["detect", str(path), "--out", str(tmp_path / "given"), "--threads", "1", "--camera", given])
        == 0
    )
    assert cameras[-1] == (1050.0, 1050.0, 480.0, 360.0) and "camera: --camera" in capsys.readouterr().err


def test_no_exif_beside_a_dataset_is_refused(drawn_dataset, tmp_path, capsys):
    """A dataset's frames carry their own intrinsics: `rebar score` takes no --no-exif."""
    from rebar_data.cli import main

    out = tmp_path / "p.parquet"
    with pytest.raises(SystemExit) as e:
        main(["score", str(drawn_dataset), "--out", str(out), "--no-exif"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and "unrecognized arguments: --no-exif" in err[-1], err
    assert not out.exists()
