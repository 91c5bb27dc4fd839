from __future__ import annotations

import pytest

from rebar_data.config import ConfigError
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.training.card import CARD_NAME
from rebar_data.perception.training.ship import ship


def test_ship_copies_the_best_model_and_writes_its_card(trained_run, tmp_path):
    model = ship(trained_run.out_dir, models_dir=tmp_path, gate=False)
    assert model.name == "rebar_keypoint.onnx" and model.stat().st_size < 5 * 2**20
    assert (tmp_path / "rebar_keypoint.refine.onnx").is_file()  # the second stage travels with it
    card = (tmp_path / CARD_NAME).read_text()
    assert "OKS sigma 0.04" in card and "| drawn test | with depth |" in card and "make train" in card
    assert "| drawn test | first stage alone |" in card and "`rebar_keypoint.refine.onnx`" in card
    # where the test split's errors lie: the frames' inside (the drawn set has no lower-mat column)
    assert (
        "| drawn test | with depth; crossings >= 8 px inside the frame |" in card
        and "lower mat |" not in card
    )
    # the test split again with its depth images and what lies behind flattened, and what that row means
    assert "| drawn test | with depth; what lies behind flattened (`--flatten-behind`) |" in card
    assert "- `what lies behind flattened (`--flatten-behind`)`: every pixel more than" in card
    # how the stages' scores combine: the depth check only lowers
    assert "- Score: sigmoid(first-stage logit + b + 1 log p + 0.5 s^2 min(0, d + 2))." in card
    assert "The depth check only lowers a score" in card and "| second stage, int8 copy |" in card
    # latency is timed on rendered frames like the training data's, not on the drawn worst case
    assert "over 8 rendered paper-tunnel frames" in card and "candidates" in card
    # its figures read each image as Detector.load does by default: the mirrored reading
    assert "- Reading: the figures on this card read each image mirrored;" in card
    det = Detector.load(model)
    assert det.meta["dataset"]["name"] == "drawn" and det.refiner is not None
    # training stores the focal length its frames had, and the card says frames of another are resampled
    assert det.focal_px and f"trained on frames of focal length {det.focal_px:g} px" in card


def test_the_card_has_the_hubs_form_and_its_figures(trained_run, tmp_path):
    """The card is a Hugging Face model card: a YAML header the Hub reads (license, library, task, the
    model index with each held-out set's figures), the sections in the template's order and one evaluation
    table; its PNGs (training curves, a PR figure per held-out set, a frame with its detections) lie in
    ``card/`` beside it, small, decodable, and linked from the card."""
    import cv2
    import numpy as np
    import yaml

    from rebar_data.perception.evaluation.plots import MAX_FIGURE_BYTES
    from rebar_data.perception.training.card import FIGURES_DIR

    (tmp_path / FIGURES_DIR).mkdir()
    (tmp_path / FIGURES_DIR / "pr-stale.png").write_bytes(b"stale")  # a figure of an earlier card goes
    ship(trained_run.out_dir, models_dir=tmp_path, gate=False)
    card = (tmp_path / CARD_NAME).read_text()
    assert card.startswith("---\n")
    meta = yaml.safe_load(card.split("---\n")[1])
    assert meta["pipeline_tag"] == "keypoint-detection" and meta["library_name"] == "onnx"
    assert meta["license"] == "other" and meta["datasets"] == ["drawn"]
    results = meta["model-index"][0]["results"]
    sets = {r["dataset"]["name"]: r for r in results}
    # the held-out test split in both input modes; no val, no part of a set, no first stage alone
    assert set(sets) == {"drawn test, with depth", "drawn test, without depth (the RGB stages alone)"}
    ap = {m["type"]: m["value"] for m in sets["drawn test, with depth"]["metrics"]}
    assert set(ap) - {"median_px"} == {"oks_ap50", "oks_ap", "pck2", "recall_at_p99"}  # median: NaN, no match
    assert "| drawn test | with depth | " in card and f"| {ap['oks_ap50']:.4f} |" in card
    assert sets["drawn test, with depth"]["dataset"]["split"] == "test"
    headings = [line for line in card.splitlines() if line.startswith("## ")]
    assert headings == [
        "## Model details",
        "## Intended use and limits",
        "## Training data",
        "## Evaluation",
        "## How to use",
        "## Latency",
    ]
    assert card.count("| held-out set | input |") == 1  # one evaluation table
    assert "(../../../docs/detector/design.md)" in card and "(../../../docs/detector/experiments.md)" in card
    assert "from rebar_data.perception import Detector" in card and "rebar detect" in card
    pngs = sorted((tmp_path / FIGURES_DIR).glob("*.png"))
    assert [p.name for p in pngs] == ["frame.png", "pr-drawn-test.png", "training.png"]
    for p in pngs:
        assert p.stat().st_size <= MAX_FIGURE_BYTES
        img = cv2.imread(str(p))
        assert img is not None and min(img.shape[:2]) >= 100 and img.std() > 5  # drawn, not blank
        assert f"]({FIGURES_DIR}/{p.name})" in card
    # the frame is the test image with the most visible crossings, with its detections counted in the caption
    assert "drawn test, image `" in card and "visible crossings (green circles" in card
    # every row of the table has all thirteen columns
    table = [line for line in card.splitlines() if line.startswith("| drawn ")]
    assert table and all(line.count("|") == 14 for line in table)
    assert np.isfinite([m["value"] for r in results for m in r["metrics"]]).all()


def test_ship_refuses_an_unfinished_run(tmp_path):
    with pytest.raises(ConfigError, match="finished"):
        ship(tmp_path, models_dir=tmp_path / "models", gate=False)


def test_a_set_from_another_renderer_is_scored_from_rgb_against_both_truths(trained_run, tmp_path):
    """A dataset whose info.json names another engine gets RGB-only rows, against the labels and against
    the projected 3D crossing points; one from the project's renderer keeps its single row."""
    import json
    import shutil
    from unittest import mock

    from rebar_data.dataset.build import build_dataset
    from rebar_data.perception.evaluation import evaluate
    from rebar_data.perception.evaluation.card_rows import evaluation_rows
    from rebar_data.resume import Steps
    from tests.dataset.conftest import TINY, write_config

    own = build_dataset(write_config(tmp_path, {**TINY, "name": "own"}), tmp_path / "data", workers=1)
    other = tmp_path / "other" / "v0.0.1"
    shutil.copytree(own, other)
    info = json.loads((other / "meta/info.json").read_text())
    info.update(name="other", renderer={"engine": "cycles"})
    (other / "meta/info.json").write_text(json.dumps(info))
    det = Detector.load(trained_run.out_dir)
    held_out = {}
    steps = Steps(tmp_path / "steps.json")
    rows = evaluation_rows(
        det, trained_run.out_dir, evaluate_on=[own, other], random_split=False, held_out=held_out, steps=steps
    )
    assert "own v0.0.1 (all splits)" in rows
    # each set's scoring is a step: a ship run again after a kill takes it from the record, detecting nothing
    again = {}
    with mock.patch.object(evaluate, "predict", side_effect=AssertionError("detected again")):
        kept = evaluation_rows(
            det,
            trained_run.out_dir,
            evaluate_on=[own, other],
            random_split=False,
            held_out=again,
            steps=Steps(tmp_path / "steps.json"),
        )
    assert json.dumps(kept, sort_keys=True) == json.dumps(rows, sort_keys=True)
    assert {k: sorted(h.modes) for k, h in again.items()} == {k: sorted(h.modes) for k, h in held_out.items()}
    # each held-out set's detections per input mode, for its PR figure: one figure a set
    assert {k: sorted(h.modes) for k, h in held_out.items()} == {
        "drawn test": ["RGB only", "with depth"],
        "own v0.0.1 (all splits)": ["with depth"],
        "other v0.0.1, cycles renderer": ["RGB only", "with depth"],
    }
    assert all(len(p) == len(h.samples) for h in held_out.values() for p in h.modes.values())
    from rebar_data.perception.training.card import FIGURES_DIR, write_figures

    figures = write_figures(trained_run.out_dir, tmp_path / "models", held_out, frame_from="drawn test")
    assert sorted(figures["pr"].values()) == [
        f"{FIGURES_DIR}/pr-drawn-test.png",
        f"{FIGURES_DIR}/pr-other-v0-0-1-cycles-renderer.png",
        f"{FIGURES_DIR}/pr-own-v0-0-1.png",
    ]
    assert all((tmp_path / "models" / link).is_file() for link in figures["pr"].values())
    rgb = rows["other v0.0.1, cycles renderer, RGB only"]
    vs_3d = rows["other v0.0.1, cycles renderer, RGB only, vs 3D crossing points"]
    assert rgb["n_gt"] == vs_3d["n_gt"] == rows["own v0.0.1 (all splits)"]["n_gt"] > 0
    assert rgb["mean_px"] != vs_3d["mean_px"]
    # and with its depth images, as they come and with what lies behind flattened: the same crossings
    from rebar_data.perception.evaluation.card_rows import FLATTENED

    with_depth = rows["other v0.0.1, cycles renderer, with depth"]
    flat = rows[f"other v0.0.1, cycles renderer, with depth, {FLATTENED}"]
    assert with_depth["n_gt"] == flat["n_gt"] == rgb["n_gt"]
    assert det.flatten_behind is False  # the scoring leaves the detector's setting as it was
    # a run trained on a dataset that records the lower mat: its test split also from RGB alone, by scene
    run = tmp_path / "run"
    run.mkdir()
    res = json.loads((trained_run.out_dir / "results.json").read_text())
    res["dataset"] = {**res["dataset"], "name": "own", "path": str(own)}
    (run / "results.json").write_text(json.dumps(res))
    own_rows = evaluation_rows(det, run, random_split=False)
    by_scene = {k: m for k, m in own_rows.items() if k.startswith("own test, without depth, scenes")}
    assert (
        by_scene and sum(m["n_gt"] for m in by_scene.values()) == own_rows[f"own test, {FLATTENED}"]["n_gt"]
    )
    # split by the lower mat, as the test split's breakdown is: together they hold every crossing
    split = {k: m for k, m in rows.items() if k.startswith("other v0.0.1, cycles renderer, RGB only, scenes")}
    assert sum(m["n_gt"] for m in split.values()) == rgb["n_gt"] and split
    assert not any(k.startswith("own v0.0.1") and "scenes" in k for k in rows)
    # and where its confident false detections lie, which the card lists under its table
    from rebar_data.perception.evaluation.false_detections import PLACES

    census = rgb["false_detections"]
    assert census["recall"] == 0.97 and census["false"] == sum(census[k] for k in PLACES)
    assert not any(
        "false_detections" in m for k, m in rows.items() if k != "other v0.0.1, cycles renderer, RGB only"
    )
    from rebar_data.perception.evaluation.bench import DetectorLatency
    from rebar_data.perception.evaluation.false_detections import format_census
    from rebar_data.perception.training.card import write_model_card

    card = write_model_card(
        trained_run.out_dir,
        tmp_path / "card.md",
        model=det.path,
        detector=det,
        rows=rows,
        figures=figures,
        latency=DetectorLatency(10.0, 12.0, 1, 40.0, 30.0),
        latency_source="one frame",
        latency_runtime="ONNX Runtime, float32",
    ).read_text()
    assert f"  - `other v0.0.1, cycles renderer, RGB only`: {format_census(census)}.\n" in card
    assert "| other v0.0.1 | cycles renderer, RGB only, vs 3D crossing points |" in card
    assert "- `cycles renderer`: sets rendered by Blender Cycles" in card


def test_the_card_names_every_renderer_that_drew_training_images():
    """The Training data counts the frames another renderer drew (a dataset that names no renderer was built
    by Open3D, before datasets recorded it)."""
    from rebar_data.perception.training.card import renderers

    own = {"renderer": "open3d", "supplements": [{"name": "lower", "images": 720}]}
    assert renderers(own) == ("Open3D", "", 0)
    cycles = [
        {"name": "a", "images": 36, "renderer": "cycles"},
        {"name": "b", "images": 48},
    ]
    # the lower-mat supplement is Open3D's own, as is the one that names no renderer
    assert renderers({**own, "refine_supplements": cycles}) == ("Open3D", "Blender Cycles", 36)


def test_the_shipped_card_has_the_hubs_form_and_its_figures_ship_with_it():
    """The card in the package: a YAML header with the model index, the sections in order, and every figure
    it links present, a decodable PNG under the size limit, and named by the package data."""
    import re
    import tomllib
    from fnmatch import fnmatch
    from pathlib import Path

    import cv2
    import yaml

    from rebar_data.perception.evaluation.plots import MAX_FIGURE_BYTES
    from rebar_data.perception.inference.detector import MODELS_DIR

    card = (MODELS_DIR / CARD_NAME).read_text()
    meta = yaml.safe_load(card.split("---\n")[1])
    assert meta["pipeline_tag"] == "keypoint-detection"
    results = meta["model-index"][0]["results"]
    assert any(r["dataset"]["name"].startswith("paper-tunnel test") for r in results)
    assert all(m["value"] <= 1 or m["type"] == "median_px" for r in results for m in r["metrics"])
    headings = [line for line in card.splitlines() if line.startswith("## ")]
    assert headings[:5] == [
        "## Model details",
        "## Intended use and limits",
        "## Training data",
        "## Evaluation",
        "## How to use",
    ]
    links = re.findall(r"\]\((card/[^)]+\.png)\)", card)
    assert "card/frame.png" in links and any(link.startswith("card/pr-") for link in links)
    pyproject = tomllib.loads((Path(__file__).parents[3] / "pyproject.toml").read_text())
    globs = pyproject["tool"]["setuptools"]["package-data"]["rebar_data.perception"]
    for link in links:
        path = MODELS_DIR / link
        assert path.stat().st_size <= MAX_FIGURE_BYTES and cv2.imread(str(path)) is not None
        assert any(fnmatch(f"models/{link}", g) for g in globs)
    assert sorted(p.name for p in (MODELS_DIR / "card").glob("*.png")) == sorted(Path(x).name for x in links)
