"""The pipeline files the project ships, and the Makefile's lists of them.

`make train` trains on paper-tunnel and the supplements the Makefile lists, and scores on the cross-renderer
sets it lists: each must be a whole, valid pipeline, the training supplements must put every image in the
train split, and no training pipeline may share a seed with a held-out set (same seed, same scenes).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from rebar_data.pipeline import load_pipeline

ROOT = Path(__file__).resolve().parents[1]
PIPELINES = sorted((ROOT / "pipelines").glob("*.yaml"))


def _make_list(name: str) -> list[str]:
    text = (ROOT / "Makefile").read_text().replace("\\\n", " ")  # continuation lines join theirs
    m = re.search(rf"^{name} := (.+)$", text, re.MULTILINE)
    assert m, f"Makefile defines no {name}"
    return m.group(1).split()


@pytest.mark.parametrize("path", PIPELINES, ids=[p.stem for p in PIPELINES])
def test_every_shipped_pipeline_is_whole_and_named_as_its_file(path: Path):
    cfg = load_pipeline(path)
    assert cfg.name == path.stem


def test_training_supplements_train_only_and_share_no_seed_with_held_out_sets():
    supplements = _make_list("SUPPLEMENTS")
    refine_supplements = _make_list("REFINE_SUPPLEMENTS")
    crossval = _make_list("CROSSVAL")
    assert "paper-tunnel-lower-mat" in supplements and len(supplements) > 1
    training = [load_pipeline(ROOT / f"pipelines/{p}.yaml") for p in ["paper-tunnel", *supplements]]
    second_stage = [load_pipeline(ROOT / f"pipelines/{p}.yaml") for p in refine_supplements]
    for cfg in training[1:] + second_stage:
        assert cfg.dataset.split.train == 1.0, f"{cfg.name}: a supplement trains on every image"
    held_out = [load_pipeline(ROOT / f"pipelines/{p}.yaml") for p in [*crossval, "planar-slab", "smoke"]]
    for cfg in held_out:
        assert cfg.render.engine == "cycles" or cfg.name in ("planar-slab", "smoke")
    seeds = [c.seed for c in training + second_stage + held_out]
    assert len(set(seeds)) == len(seeds), "two pipelines with one seed draw the same scenes"
    for cfg in training:  # the Open3D supplements; the Cycles frames come in as REFINE_SUPPLEMENTS
        assert cfg.render.engine == "open3d"


def test_no_two_shipped_pipelines_share_a_seed():
    """Also those not (yet) in the Makefile's lists: two pipelines with one seed draw the same scenes."""
    seeds = {p.stem: load_pipeline(p).seed for p in PIPELINES}
    assert len(set(seeds.values())) == len(seeds), seeds


def test_cycles_frames_train_the_late_stages_on_meshes_the_cross_renderer_sets_do_not_have():
    """The Cycles supplements (the first stage's epochs and adapt epochs, and the second stage) are of the
    cross-renderer sets' kinds of mesh (curved and planar) but with other spacings, each its own, so the
    sets' grids stay unseen as well as their scenes."""
    second_stage = [load_pipeline(ROOT / f"pipelines/{p}.yaml") for p in _make_list("REFINE_SUPPLEMENTS")]
    crossval = [load_pipeline(ROOT / f"pipelines/{p}.yaml") for p in _make_list("CROSSVAL")]
    assert second_stage and all(c.render.engine == "cycles" for c in second_stage)
    assert {c.mesh.kind for c in second_stage} == {c.mesh.kind for c in crossval}

    def grid(cfg) -> tuple:
        m = cfg.mesh
        if m.kind == "tunnel_segment":
            return (m.kind, m.spacing_axial_m, m.spacing_arc_m)
        return (m.kind, m.spacing_x_m, m.spacing_y_m)

    assert not {grid(c) for c in second_stage} & {grid(c) for c in crossval}
    assert len({grid(c) for c in second_stage}) == len(second_stage)
