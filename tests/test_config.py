from __future__ import annotations

import copy
import os

import pytest
import yaml

from rebar_data.cli import main

GOOD = {
    "name": "t",
    "version": "0.1.0",
    "seed": 1,
    "mesh": {"kind": "planar", "width_m": 1.0, "height_m": 0.6},
    "camera": {"intrinsics": "square_640"},
}


def _with(path: str, value):
    cfg = copy.deepcopy(GOOD)
    node = cfg
    keys = path.split(".")
    for k in keys[:-1]:
        node = node.setdefault(k, {})
    node[keys[-1]] = value
    return cfg


BAD = [
    # (config, words the message must contain)
    (_with("mesh.spacing_x_m", -0.1), ["mesh.spacing_x_m", "-0.1", "greater than 0"]),
    (_with("mesh.width_m", "wide"), ["mesh.width_m", "'wide'", "number"]),
    (_with("mesh.spacing_y_m", 2.0), ["spacing_y_m = 2.0", "larger than the mesh", "at most"]),
    (_with("mesh.colour", "red"), ["unknown key", "mesh.colour", "accepted at mesh:", "spacing_x_m"]),
    (_with("mesh.widht_m", 2.0), ["unknown key 'mesh.widht_m'", "did you mean 'width_m'?"]),
    (_with("mesh.layers", [{"facee": "top"}]), ["mesh.layers.0.facee", "did you mean 'face'?"]),
    (_with("sede", 3), ["unknown key 'sede'", "did you mean 'seed'?", "accepted at the top level:"]),
    (_with("mesh.kind", "hexagonal"), ["mesh", "hexagonal", "planar", "tunnel_segment"]),
    (_with("seed", -4), ["seed", "-4", "greater than or equal to 0"]),
    (_with("realism.missing_fraction", 1.5), ["realism.missing_fraction", "1.5", "less than 1"]),
    (_with("realism.tie_wire_fraction", "some"), ["realism.tie_wire_fraction", "'some'"]),
    (_with("mesh.layers", []), ["mesh.layers", "at least 1"]),
    (_with("mesh.layers", [{"face": "side"}]), ["mesh.layers.0.face", "'side'", "'top' or 'bottom'"]),
    (_with("mesh.bar_diameter_m", 0), ["mesh.bar_diameter_m", "0", "greater than 0"]),
    (_with("mesh.cover_m", 0.24), ["layers[0]", "thickness_m"]),
    (
        {
            **GOOD,
            "mesh": {"kind": "tunnel_segment", "intrados_arc_m": 2.5, "extrados_arc_m": 2.3, "width_m": 3},
        },
        ["extrados_arc_m", "longer than intrados_arc_m"],
    ),
    (_with("pose.rotation_deg", [0, 0]), ["pose.rotation_deg", "[0, 0]"]),
    ({k: v for k, v in GOOD.items() if k != "mesh"}, ["'mesh' is required"]),
]


@pytest.mark.parametrize(("cfg", "words"), BAD, ids=[w[0] for _, w in BAD])
def test_bad_config_is_one_clear_message_and_writes_nothing(cfg, words, tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(cfg))
    out = tmp_path / "out"
    assert main(["mesh", str(path), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err  # one line
    assert "Traceback" not in err
    for w in words:
        assert w in err, (w, err)
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["bad.yaml"]


def test_missing_file_not_yaml_and_not_a_mapping(tmp_path, capsys):
    assert main(["mesh", str(tmp_path / "nope.yaml"), "--out", str(tmp_path / "o")]) == 2
    assert "no such config file" in capsys.readouterr().err
    bad = tmp_path / "broken.yaml"
    bad.write_text("mesh: [unclosed\n")
    assert main(["mesh", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "not valid YAML at line" in capsys.readouterr().err
    bad.write_text("- just\n- a list\n")
    assert main(["mesh", str(bad), "--out", str(tmp_path / "o")]) == 2
    assert "accepted: a mapping" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_good_config_builds_and_prints_the_folder_last(tmp_path, capsys):
    path = tmp_path / "good.yaml"
    path.write_text(yaml.safe_dump(GOOD))
    assert main(["mesh", str(path), "--out", str(tmp_path / "m"), "--rrd", str(tmp_path / "m.rrd")]) == 0
    assert capsys.readouterr().out.strip().splitlines()[-1] == str(tmp_path / "m")
    for f in ("mesh.glb", "mesh.ply", "bars.parquet", "crossings.parquet"):
        assert (tmp_path / "m" / f).stat().st_size > 0
    assert (tmp_path / "m.rrd").stat().st_size > 0


# --- bounded YAML, short excerpts, inputs read once -------------------------------------------------------

LAUGHS = 'a: &a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]\n' + "".join(
    f"{n}: &{n} [{','.join([f'*{p}'] * 9)}]\n" for p, n in zip("abcdefgh", "bcdefghi", strict=True)
)


def test_nested_aliases_are_refused_before_they_expand(tmp_path, capsys):
    import tracemalloc

    from rebar_data.config import ConfigError, read_yaml

    p = tmp_path / "laughs.yaml"
    p.write_text(LAUGHS)  # 9**9 strings, from 500 bytes
    assert main(["mesh", str(p), "--out", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "aliases" in err and "200,000" in err and str(p) in err, err
    tracemalloc.start()
    with pytest.raises(ConfigError):
        read_yaml(p)
    peak = tracemalloc.get_traced_memory()[1]
    tracemalloc.stop()
    assert peak < 50e6, peak  # what the document is, not what it would expand to
    (tmp_path / "self.yaml").write_text("a: &a [1, *a]\n")
    assert main(["mesh", str(tmp_path / "self.yaml"), "--out", str(tmp_path / "m")]) == 2
    assert "its own value" in capsys.readouterr().err
    assert not (tmp_path / "m").exists()


def test_a_bad_value_is_shown_as_a_short_excerpt(write_yaml, tmp_path, capsys):
    big = _with("seed", ["x" * 50] * 40)
    assert main(["mesh", str(write_yaml(big)), "--out", str(tmp_path / "m")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "seed = " in err and "..." in err and len(err) < 400, err


def test_a_pipeline_given_as_a_pipe_is_read_once(root, tmp_path):
    from rebar_data.dataset.build import check_paths
    from rebar_data.pipeline import load_pipeline

    r, w = os.pipe()  # what bash's <(cat pipelines/smoke.yaml) hands over: /dev/fd/N, readable once
    os.write(w, (root / "pipelines" / "smoke.yaml").read_bytes())
    os.close(w)
    try:
        path = check_paths(f"/dev/fd/{r}", tmp_path)
        assert load_pipeline(path).name == "smoke"
    finally:
        os.close(r)
