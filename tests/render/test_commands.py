from __future__ import annotations

import cv2

from rebar_data.cli import main
from tests.scene.conftest import TUNNEL


def test_render_command_writes_frames_and_a_contact_sheet(write_yaml, tmp_path, capsys):
    cfg = {
        "name": "preview",
        "version": "0.1.0",
        **TUNNEL,
        "camera": {
            "intrinsics": {"width": 320, "height": 240, "fx": 260, "fy": 260, "cx": 160, "cy": 120},
            "trajectories": [{"kind": "approach", "count": 1, "frames": 2}],
        },
        "render": {"texture_size_px": 256, "cache_dir": str(tmp_path / "cache")},
    }
    out = tmp_path / "preview"
    assert main(["render", str(write_yaml(cfg)), "--out", str(out), "--frames", "2"]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == str(out)
    frames = sorted(out.glob("frame_*.png"))
    assert [f.name for f in frames] == ["frame_000_approach.png", "frame_001_approach.png"]
    assert cv2.imread(str(frames[0])).shape == (240, 320, 3)
    assert cv2.imread(str(out / "contact_sheet.png")) is not None


def test_render_command_bad_config_is_one_line(write_yaml, tmp_path, capsys):
    cfg = {"name": "preview", "version": "0.1.0", **TUNNEL, "camera": {"intrinsics": "kinect2"}}
    assert main(["render", str(write_yaml(cfg)), "--out", str(tmp_path / "x")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "camera.intrinsics" in err and len(err.splitlines()) == 1
