"""The pipeline files the project ships, and the Makefile's lists of them.

`make train` trains on paper-tunnel and the supplements the Makefile lists, and scores on the cross-renderer
sets it lists: each must be a whole, valid pipeline, the training supplements must put every image in the
train split, and no training pipeline may share a seed with a held-out set (same seed, same scenes).
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from rebar_data.dataset.config import load_pipeline

ROOT = Path(__file__).resolve().parents[1]
PIPELINES = sorted((ROOT / "pipelines").glob("*.yaml"))


def _make_list(name: str) -> list[str]:
    m = re.search(rf"^{name} := (.+)$", (ROOT / "Makefile").read_text(), re.MULTILINE)
    assert m, f"Makefile defines no {name}"
    return m.group(1).split()


@pytest.mark.parametrize("path", PIPELINES, ids=[p.stem for p in PIPELINES])
def test_every_shipped_pipeline_is_whole_and_named_as_its_file(path: Path):
    cfg = load_pipeline(path)
    assert cfg.name == path.stem


def test_training_supplements_train_only_and_share_no_seed_with_held_out_sets():
    supplements = _make_list("SUPPLEMENTS")
    crossval = _make_list("CROSSVAL")
    assert "paper-tunnel-lower-mat" in supplements and len(supplements) > 1
    training = [load_pipeline(ROOT / f"pipelines/{p}.yaml") for p in ["paper-tunnel", *supplements]]
    for cfg in training[1:]:
        assert cfg.dataset.split.train == 1.0, f"{cfg.name}: a supplement trains on every image"
    held_out = [load_pipeline(ROOT / f"pipelines/{p}.yaml") for p in [*crossval, "planar-slab", "smoke"]]
    for cfg in held_out:
        assert cfg.render.engine == "cycles" or cfg.name in ("planar-slab", "smoke")
    seeds = [c.seed for c in training + held_out]
    assert len(set(seeds)) == len(seeds), "two pipelines with one seed draw the same scenes"
    for cfg in training:  # the cross-renderer sets test another renderer: none of them is trained on
        assert cfg.render.engine == "open3d"
