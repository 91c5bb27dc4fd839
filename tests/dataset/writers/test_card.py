"""The dataset card's code runs as written, where only the packages it names are installed."""

from __future__ import annotations

import json
import re
import shutil

import pytest

from tests.fresh_env import named_packages, python_blocks, run_in_fresh_environment


def perfect_results(annotations: dict) -> list[dict]:
    """The labels of a COCO keypoints file as COCO results of score 1."""
    keys = ("image_id", "category_id", "keypoints")
    return [{k: a[k] for k in keys} | {"score": 1.0} for a in annotations["annotations"]]


def test_every_snippet_of_the_dataset_card_names_its_packages_and_runs_with_them_alone(
    tiny_dataset, tmp_path
):
    blocks = python_blocks((tiny_dataset / "README.md").read_text())
    assert blocks
    for i, block in enumerate(blocks):
        assert named_packages(block), f"snippet {i} has no `# pip install ...` first line:\n{block}"
        work = tmp_path / f"snippet{i}"
        shutil.copytree(tiny_dataset, work)  # DATASET = "." in the snippet: this folder
        if "COCOeval" in block:
            gt = json.loads((work / "annotations/val.json").read_text())
            (work / "predictions.json").write_text(json.dumps(perfect_results(gt)))
        run = run_in_fresh_environment(block, work)
        assert run.returncode == 0, (block, run.stderr[-2000:])
        if "COCOeval" in block:
            ap, ap50 = (float(x) for x in re.search(r"AP ([0-9.]+) .*AP@0.5 ([0-9.]+)", run.stdout).groups())
            assert ap == pytest.approx(1.0) and ap50 == pytest.approx(1.0), run.stdout
