"""The release bundle's card: its code runs as written, where only the packages it names are installed."""

from __future__ import annotations

import json
import os
import re
import shutil

import pytest

from tests.dataset.writers.test_card import perfect_results
from tests.fresh_env import named_packages, python_blocks, run_in_fresh_environment


def _offline(tmp_path) -> dict:
    """This environment with the Hugging Face caches under ``tmp_path`` and the Hub out of reach."""
    return {**os.environ, "HF_HOME": str(tmp_path / "hf"), "HF_HUB_OFFLINE": "1", "HF_DATASETS_OFFLINE": "1"}


def test_every_snippet_of_the_bundle_card_names_its_packages_and_runs_with_them_alone(bundle, tmp_path):
    blocks = python_blocks((bundle / "README.md").read_text())
    assert any("load_dataset" in b for b in blocks) and any("COCOeval" in b for b in blocks)
    for i, block in enumerate(blocks):
        assert named_packages(block), f"snippet {i} has no `# pip install ...` first line:\n{block}"
        work = tmp_path / f"snippet{i}"
        shutil.copytree(bundle, work)  # the snippets run from the bundle's folder
        if "COCOeval" in block:
            gt = json.loads((work / "annotations/val.json").read_text())
            (work / "predictions.json").write_text(json.dumps(perfect_results(gt)))
        run = run_in_fresh_environment(block, work, env=_offline(tmp_path / f"env{i}"))
        assert run.returncode == 0, (block, run.stderr[-2000:])
        if "COCOeval" in block:
            ap = float(re.search(r"AP ([0-9.]+)", run.stdout).group(1))
            assert ap == pytest.approx(1.0), run.stdout


def test_the_datasets_snippet_needs_the_pillow_it_names(bundle, tmp_path):
    """Without Pillow (`pip install datasets` alone) the snippet's image does not decode: the name matters."""
    block = next(b for b in python_blocks((bundle / "README.md").read_text()) if "load_dataset" in b)
    names = named_packages(block)
    assert "pillow" in [n.lower() for n in names], names
    shutil.copytree(bundle, tmp_path / "bundle")
    without = [n for n in names if n.lower() != "pillow"]
    run = run_in_fresh_environment(block, tmp_path / "bundle", names=without, env=_offline(tmp_path))
    assert run.returncode != 0 and "install 'Pillow'" in run.stderr, run.stderr[-2000:]
