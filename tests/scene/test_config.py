from __future__ import annotations

import numpy as np
import pytest

from rebar_data.config import ConfigError, validate
from rebar_data.scene.config import CameraConfig, RenderConfig, SceneConfig


def test_defaults_are_the_papers_dataset():
    cam = CameraConfig()
    kinds = [t.kind for t in cam.trajectories]
    assert kinds == ["orbit_arc", "straight_pass", "approach"]
    assert sum(t.count * t.frames for t in cam.trajectories) == 1200
    scene = SceneConfig()
    assert scene.lighting.sun.probability == 1.0 and scene.lighting.lamps.count == (2, 2)  # three lights
    assert RenderConfig().shadows


BAD = [
    # (model, data, words the message must contain)
    (CameraConfig, {"intrinsics": "kinect2"}, ["intrinsics", "'kinect2'", "kinect_v1", "square_640"]),
    (CameraConfig, {"intrinsics": {"width": 640}}, ["intrinsics", "height", "required"]),
    (
        CameraConfig,
        {"intrinsics": {"width": 64, "height": 48, "fx": -1, "fy": 1, "cx": 1, "cy": 1}},
        ["intrinsics", "fx = -1", "greater than 0"],
    ),
    (CameraConfig, {"trajectories": [{"kind": "spiral"}]}, ["trajectories.0", "'spiral'", "orbit_arc"]),
    (
        CameraConfig,
        {"trajectories": [{"kind": "orbit_arc", "standoff_m": [0.8, 0.4]}]},
        ["standoff_m", "[0.8, 0.4]", "min > max"],
    ),
    (CameraConfig, {"trajectories": [{"kind": "approach", "tilt_deg": [0, 90]}]}, ["tilt_deg", "85"]),
    (
        CameraConfig,
        {"trajectories": [{"kind": "straight_pass", "frames": 0}]},
        ["frames", "0", "greater than"],
    ),
    (CameraConfig, {"trajectories": []}, ["trajectories", "at least 1"]),
    (
        SceneConfig,
        {"lighting": {"lamps": {"kinds": {"laser": 1}}}},
        ["lighting.lamps.kinds", "'laser'", "spot"],
    ),
    (SceneConfig, {"lighting": {"ambient": {"environments": ["moon"]}}}, ["environments", "'moon'", "park"]),
    (SceneConfig, {"lighting": {"sun": {"elevation_deg": [10, 95]}}}, ["elevation_deg", "90"]),
    (SceneConfig, {"sensor": {"jpeg_quality": [101, 50]}}, ["jpeg_quality", "101"]),
    (SceneConfig, {"materials": {"rebar": {"rust": [0.5, 1.5]}}}, ["materials.rebar.rust", "1.5"]),
    (
        SceneConfig,
        {"surroundings": {"ground": {"kinds": {"lava": 1.0}}}},
        ["ground.kinds", "'lava'", "gravel"],
    ),
    (SceneConfig, {"lighting": {"sun": {"colour": "red"}}}, ["unknown key", "lighting.sun.colour"]),
    (RenderConfig, {"texture_size_px": 300}, ["texture_size_px", "300", "1024"]),
]


@pytest.mark.parametrize(("model", "data", "words"), BAD)
def test_bad_values_name_the_field(model, data, words):
    with pytest.raises(ConfigError) as e:
        validate(model, data, "p.yaml")
    msg = str(e.value)
    assert msg.startswith("p.yaml: ")
    for w in words:
        assert w in msg, (w, msg)


def test_texture_folder_must_exist_and_hold_maps(tmp_path):
    missing = tmp_path / "nowhere"
    with pytest.raises(ConfigError, match=r"materials\.rebar\.texture_dirs\.0.*does not exist"):
        validate(SceneConfig, {"materials": {"rebar": {"texture_dirs": [str(missing)]}}}, "p.yaml")
    empty = tmp_path / "empty"
    empty.mkdir()
    (empty / "notes.txt").write_text("no maps here")
    with pytest.raises(ConfigError, match=r"ground\.texture_dirs\.0.*holds no texture maps"):
        validate(SceneConfig, {"surroundings": {"ground": {"texture_dirs": [str(empty)]}}}, "p.yaml")


def test_texture_folder_with_maps_is_accepted(tmp_path):
    import cv2

    cv2.imwrite(str(tmp_path / "rust_diff_1k.png"), np.full((8, 8, 3), 90, np.uint8))
    cfg = validate(SceneConfig, {"materials": {"rebar": {"texture_dirs": [str(tmp_path)]}}}, "p.yaml")
    assert cfg.materials.rebar.texture_dirs == [tmp_path]
