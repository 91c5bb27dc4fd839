from __future__ import annotations

import json
import math
import shutil

import numpy as np
import pytest
import torch

from rebar_data.config import ConfigError
from rebar_data.perception.evaluation.data import load_split, read_info
from rebar_data.perception.evaluation.plots import read_history
from rebar_data.perception.inference.detector import Detector
from rebar_data.perception.networks import eager
from rebar_data.perception.networks.keypoint_net import KeypointNet
from rebar_data.perception.training.config import TrainConfig
from rebar_data.perception.training.epochs import TrainingImages, make_batch
from rebar_data.perception.training.loss import detection_loss
from rebar_data.perception.training.train import train
from tests.perception.conftest import TINY_TRAIN


def test_loss_falls_when_a_tiny_model_trains_a_few_steps(drawn_dataset):
    cfg = TrainConfig.model_validate({**TINY_TRAIN, "crop_px": 96})
    data = TrainingImages(load_split(drawn_dataset, "train"), cache=True, occluded="ignore")
    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    net = KeypointNet(cfg.model)
    opt = torch.optim.AdamW(net.parameters(), lr=5e-3)
    batches = [make_batch(data, rng, cfg, mosaic=False) for _ in range(2)]
    losses = []
    for step in range(60):  # 30 left it near half with some augmentation draws; 60: about a quarter
        x, rays, *targets = batches[step % 2]
        loss = detection_loss(net(x, rays), *targets)[0]
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert np.mean(losses[-4:]) < 0.5 * np.mean(losses[:2])


def test_a_batch_holds_crops_rays_and_targets(drawn_dataset):
    cfg = TrainConfig.model_validate(TINY_TRAIN)
    data = TrainingImages(load_split(drawn_dataset, "train"), cache=False, occluded="ignore")
    x, rays, heat, hw, off, ow = make_batch(data, np.random.default_rng(1), cfg, mosaic=True)
    assert x.shape == (4, 3, 64, 64) and rays.shape == (4, 2, 16, 16)
    assert heat.shape == hw.shape == ow.shape == (4, 16, 16) and off.shape == (4, 2, 16, 16)
    assert (heat == 1).sum() > 0 and x.min() >= 0 and x.max() <= 255


def test_training_writes_the_run_and_its_model_detects(trained_run, drawn_dataset):
    out = trained_run.out_dir
    for f in (
        "config.json",
        "last.pt",
        "best.pt",
        "best.onnx",
        "metrics.csv",
        "results.json",
        "curves.png",
        "pr_curve.png",
        "predictions.png",
    ):
        assert (out / f).is_file(), f
    history = read_history(out / "metrics.csv")
    assert [int(h["epoch"]) for h in history] == [1, 2]
    assert all(np.isfinite(h["train_loss"]) for h in history)
    assert {"val_oks_ap", "val_pck2", "val_recall_at_p99", "lr"} <= set(history[0])
    results = json.loads((out / "results.json").read_text())
    assert set(results["results"]) == {"val", "test"}
    det = Detector.load(out)
    assert det.path.name == "best.onnx" and det.meta["oks_sigma"] == results["oks_sigma"]
    sample = load_split(drawn_dataset, "test")[0]
    from rebar_data.perception.evaluation.data import read_image

    assert det.detect(read_image(sample.path), threshold=0.01).shape[1] == 3


def test_training_resumes_where_it_stopped(drawn_dataset, tmp_path):
    cfg = {**TINY_TRAIN, "epochs": 1}
    first = train(drawn_dataset, tmp_path / "run", config=cfg, progress=False)
    row1 = read_history(tmp_path / "run/metrics.csv")[0]
    again = train(drawn_dataset, tmp_path / "run", config=cfg, epochs=2, progress=False)
    history = read_history(tmp_path / "run/metrics.csv")
    assert first.epochs_run == 1 and again.epochs_run == 2
    assert [int(h["epoch"]) for h in history] == [1, 2]
    assert history[0]["train_loss"] == row1["train_loss"]
    with pytest.raises(ConfigError, match="crop_px"):
        train(drawn_dataset, tmp_path / "run", config={**cfg, "crop_px": 96}, epochs=3, progress=False)
    fresh = train(drawn_dataset, tmp_path / "run", config=cfg, resume=False, progress=False)
    assert fresh.epochs_run == 1


def test_bad_settings_and_datasets_are_one_clear_error(drawn_dataset, tmp_path):
    with pytest.raises(ConfigError, match="crop_px"):
        train(drawn_dataset, tmp_path / "r", config={"crop_px": 100})
    with pytest.raises(ConfigError, match="no such dataset folder"):
        train(tmp_path / "nowhere", tmp_path / "r")
    (tmp_path / "empty").mkdir()
    with pytest.raises(ConfigError, match="tables/samples.parquet"):
        train(tmp_path / "empty", tmp_path / "r")
    # a dataset without its depth images fails before training, and says how to train without them
    no_depth = tmp_path / "no_depth"
    shutil.copytree(drawn_dataset, no_depth)
    shutil.rmtree(no_depth / "depth")
    with pytest.raises(ConfigError, match=r"no depth image.*depth_check: \{enabled: false\}"):
        train(no_depth, tmp_path / "r")
    assert not (tmp_path / "r" / "last.pt").exists()


def test_batches_are_the_same_with_or_without_a_loader_process(drawn_dataset):
    from rebar_data.perception.training.epochs import batch_stream

    samples = load_split(drawn_dataset, "train")
    here = TrainConfig.model_validate({**TINY_TRAIN, "loader_workers": 0})
    there = TrainConfig.model_validate({**TINY_TRAIN, "loader_workers": 1})
    a = list(batch_stream(samples, here, first=3, last=4, steps=2))
    b = list(batch_stream(samples, there, first=3, last=4, steps=2))
    assert len(a) == len(b) == 4
    for x, y in zip(a, b, strict=True):
        for s, t in zip(x, y, strict=True):
            torch.testing.assert_close(s, t)
    resumed = list(batch_stream(samples, here, first=4, last=4, steps=2))  # epoch 4 alone, as after a resume
    torch.testing.assert_close(resumed[0][0], a[2][0])
    assert not torch.equal(a[0][0], a[2][0])


def test_a_supplement_adds_its_images_to_training_and_is_recorded(drawn_dataset, tmp_path):
    from tests.perception.synthetic import SyntheticSpec, write_synthetic_dataset

    spec = SyntheticSpec(width=192, height=144, focal_px=157.5, trajectories=3, frames=2)
    extra = write_synthetic_dataset(tmp_path / "data", spec, seed=5, name="drawn-extra")
    cfg = {**TINY_TRAIN, "epochs": 1, "refine": {**TINY_TRAIN["refine"], "enabled": False}}
    alone = train(drawn_dataset, tmp_path / "alone", config=cfg, progress=False)
    both = train(drawn_dataset, tmp_path / "both", config=cfg, supplements=[extra], progress=False)
    n_train, n_extra = len(load_split(drawn_dataset, "train")), 6
    steps_alone = math.ceil(n_train / cfg["batch_size"])
    steps_both = math.ceil((n_train + n_extra) / cfg["batch_size"])
    assert steps_both > steps_alone
    assert alone.history[0]["steps"] == steps_alone and both.history[0]["steps"] == steps_both
    recorded = json.loads((tmp_path / "both/results.json").read_text())["dataset"]["supplements"]
    assert [(d["name"], d["images"]) for d in recorded] == [("drawn-extra", n_extra)]
    assert set(both.results) == {"val", "test"}  # scored on the first dataset's splits alone
    from rebar_data.perception.training.card import CARD_NAME
    from rebar_data.perception.training.ship import ship

    ship(tmp_path / "both", models_dir=tmp_path / "models", gate=False)
    assert "`drawn-extra` v0.0.0 (6 images)" in (tmp_path / "models" / CARD_NAME).read_text()
    with pytest.raises(ConfigError, match="supplements"):  # a run resumes only with the supplements it had
        train(drawn_dataset, tmp_path / "both", config=cfg, epochs=2, progress=False)
    with pytest.raises(ConfigError, match="another pipeline"):  # its own val and test scenes would leak in
        train(drawn_dataset, tmp_path / "r", config=cfg, supplements=[drawn_dataset], progress=False)


def test_a_second_stage_supplement_trains_the_second_stage_alone(trained_run, drawn_dataset, tmp_path):
    """A finished run resumed with a second-stage supplement keeps its first stage and trains the second
    again on its images and the supplement's (each repeated), and the card says so; resumed again with the
    same supplement, nothing trains."""
    from rebar_data.perception.networks.files import load_checkpoint
    from rebar_data.perception.training.card import CARD_NAME
    from rebar_data.perception.training.refine import load as load_refiner
    from rebar_data.perception.training.ship import ship
    from tests.perception.synthetic import SyntheticSpec, write_synthetic_dataset

    spec = SyntheticSpec(width=192, height=144, focal_px=157.5, trajectories=3, frames=2)
    extra = write_synthetic_dataset(tmp_path / "data", spec, seed=6, name="drawn-second")
    run = tmp_path / "run"
    shutil.copytree(trained_run.out_dir, run)
    first_before, _, _ = load_checkpoint(run / "best.pt")
    refine_before = load_refiner(run / "refine_last.pt")[2]
    cfg = {
        **TINY_TRAIN,
        "epochs": 2,
        "adapt": {"epochs": 0},  # no adapt epochs: the first stage stays as it is
        # the repeats are a second-stage setting: a resumed run may change them with the supplement; how
        # the file ships is an export setting: the later passes' int8 copy beside the float file
        "refine": {**TINY_TRAIN["refine"], "supplement_repeats": 3, "quantize": "later"},
    }
    again = train(drawn_dataset, run, config=cfg, refine_supplements=[extra], progress=False)
    assert again.epochs_run == trained_run.epochs_run
    assert [h["train_loss"] for h in again.history] == [h["train_loss"] for h in trained_run.history]
    first_after, _, _ = load_checkpoint(run / "best.pt")
    for k, v in first_before.state_dict().items():
        torch.testing.assert_close(first_after.state_dict()[k], v)
    _, _, refine_after = load_refiner(run / "refine_last.pt")
    assert refine_before["data"] == [f"first stage: epoch {trained_run.best_epoch}"]
    assert refine_after["data"] == ["drawn-second v0.0.0", f"first stage: epoch {trained_run.best_epoch}"]
    assert not (run / "adapted.pt").exists()
    n_train = len(load_split(drawn_dataset, "train"))
    assert len(refine_after["negatives"]) == n_train + 3 * 6  # its own images, then the 6 extra three times
    assert any(
        not torch.equal(refine_after["state_dict"][k], v) for k, v in refine_before["state_dict"].items()
    )
    recorded = json.loads((run / "results.json").read_text())["dataset"]
    assert recorded["supplements"] == [] and [d["name"] for d in recorded["refine_supplements"]] == [
        "drawn-second"
    ]
    train(drawn_dataset, run, config=cfg, refine_supplements=[extra], progress=False)
    kept = load_refiner(run / "refine_last.pt")[2]
    for k, v in refine_after["state_dict"].items():
        assert torch.equal(kept["state_dict"][k], v)  # a finished stage on the same data is kept
    ship(run, models_dir=tmp_path / "models", gate=False)
    card = (tmp_path / "models" / CARD_NAME).read_text()
    assert "`drawn-second` v0.0.0 (6 images)" in card and "; the second supplements 3 times |" in card
    shipped = Detector.load(tmp_path / "models" / "rebar_keypoint.onnx")
    assert shipped.refiner.int8_run is not None
    name = read_info(drawn_dataset)["name"]
    assert shipped.meta["refiner"]["int8_calibrated_on"]["data"] == [f"{name} train"]
    assert "`rebar_keypoint.refine.int8.onnx`" in card
    with pytest.raises(ConfigError, match="another pipeline"):  # its val and test scenes would leak in
        train(drawn_dataset, run, config=cfg, refine_supplements=[drawn_dataset], progress=False)


def test_adapt_epochs_train_the_first_stage_on_the_supplement_and_ship_it(
    trained_run, drawn_dataset, tmp_path
):
    """With a second-stage supplement the first stage trains its adapt epochs from its best epoch (kept in
    best.pt) on its images and the supplement's; the adapted weights ship in best.onnx and the later stages
    train beside them; resumed again nothing trains, and with no adapt epochs the best epoch ships again."""
    from rebar_data.perception.networks.files import load_checkpoint
    from rebar_data.perception.training.adapt import ADAPT_LAST, ADAPTED
    from rebar_data.perception.training.card import CARD_NAME
    from rebar_data.perception.training.refine import load as load_refiner
    from rebar_data.perception.training.ship import ship
    from tests.perception.synthetic import SyntheticSpec, write_synthetic_dataset

    spec = SyntheticSpec(width=192, height=144, focal_px=157.5, trajectories=3, frames=2)
    extra = write_synthetic_dataset(tmp_path / "data", spec, seed=7, name="drawn-other")
    run = tmp_path / "run"
    shutil.copytree(trained_run.out_dir, run)
    best_before, _, _ = load_checkpoint(run / "best.pt")
    cfg = {**TINY_TRAIN, "epochs": 2, "adapt": {"epochs": 2, "supplement_repeats": 3}}
    again = train(drawn_dataset, run, config=cfg, refine_supplements=[extra], progress=False)
    assert again.epochs_run == trained_run.epochs_run  # the first epochs are not run again
    best_after, _, _ = load_checkpoint(run / "best.pt")
    adapted, meta, _ = load_checkpoint(run / ADAPTED)
    for k, v in best_before.state_dict().items():
        torch.testing.assert_close(best_after.state_dict()[k], v)
    assert any(not torch.equal(adapted.state_dict()[k], v) for k, v in best_before.state_dict().items())
    # the batch norms' statistics stayed the best epoch's
    for k, v in best_before.state_dict().items():
        if k.endswith(("running_mean", "running_var")):
            torch.testing.assert_close(adapted.state_dict()[k], v)
    results = json.loads((run / "results.json").read_text())
    n_train = len(load_split(drawn_dataset, "train"))
    steps = math.ceil((n_train + 3 * 6) / cfg["batch_size"])  # its own images, then the 6 extra three times
    assert results["adapt_epochs"] == 2 and [h["steps"] for h in results["adapt_history"]] == [steps, steps]
    # the adapted file carries the results (NaN where the tiny model found nothing: compared as text)
    assert json.dumps(meta["results"], sort_keys=True) == json.dumps(results["results"], sort_keys=True)
    # best.onnx is the adapted first stage
    image = np.random.default_rng(0).integers(0, 255, (144, 192, 3), dtype=np.uint8)
    # float32, as trained, read once, as a network in memory reads
    shipped = Detector.load(run / "best.onnx", runtime="onnxruntime", reading="single").raw(image)
    np.testing.assert_allclose(shipped, eager.detector(adapted).raw(image), atol=1e-3)
    assert not np.allclose(shipped, eager.detector(best_after).raw(image), atol=1e-3)
    refine = load_refiner(run / "refine_last.pt")[2]
    assert refine["data"][0] == "drawn-other v0.0.0" and refine["data"][-1].startswith("adapted:")
    from rebar_data.perception.training.depth_check import load as load_depth_check

    depth_data = load_depth_check(run / "depth_last.pt")[2]["data"]
    assert depth_data[-3].startswith("adapted:") and depth_data[-2] == "its own lower-mat negatives: 16"
    assert depth_data[-1] == "sensor depth"  # what it read: each image's sensor depth
    ship(run, models_dir=tmp_path / "models", gate=False)
    card = (tmp_path / "models" / CARD_NAME).read_text()
    assert "| adapt epochs | 2 |" in card and "second supplements 3 times; batch norms frozen" in card
    assert "the second ones" not in card  # the first epochs did not see them
    assert '"lower_mat_negatives": 16' in card  # the depth check's, in the settings
    # the latency names what ran it (the default runtime), the figures the runtime training fits on
    from rebar_data.perception.evaluation.bench import runtime_description

    assert f"2 CPU threads, {runtime_description('auto')}, end to end" in card
    assert "The figures are ONNX Runtime's in float32" in card
    stamp = (run / ADAPT_LAST).stat().st_mtime_ns
    train(drawn_dataset, run, config=cfg, refine_supplements=[extra], progress=False)
    assert (run / ADAPT_LAST).stat().st_mtime_ns == stamp  # finished on the same data: kept
    # no adapt epochs: the best epoch ships again, and the later stages train beside it
    train(
        drawn_dataset, run, config={**cfg, "adapt": {"epochs": 0}}, refine_supplements=[extra], progress=False
    )
    assert not (run / ADAPTED).exists() and not (run / ADAPT_LAST).exists()
    np.testing.assert_allclose(
        Detector.load(run / "best.onnx", runtime="onnxruntime", reading="single").raw(image),
        eager.detector(best_after).raw(image),
        atol=1e-3,
    )
    assert load_refiner(run / "refine_last.pt")[2]["data"][-1].startswith("first stage: epoch")


def test_other_renderer_repeats_put_the_second_stage_supplements_in_the_first_epochs(drawn_dataset, tmp_path):
    """With ``other_renderer_repeats`` the second-stage supplements' images join the first epochs that many
    times (their steps count them), the card says so, and a resumed run must keep those supplements."""
    from rebar_data.perception.training.card import CARD_NAME
    from rebar_data.perception.training.ship import ship
    from tests.perception.synthetic import SyntheticSpec, write_synthetic_dataset

    spec = SyntheticSpec(width=192, height=144, focal_px=157.5, trajectories=3, frames=2)
    extra = write_synthetic_dataset(tmp_path / "data", spec, seed=8, name="drawn-early")
    other = write_synthetic_dataset(tmp_path / "data", spec, seed=9, name="drawn-late")
    cfg = {
        **TINY_TRAIN,
        "epochs": 1,
        "other_renderer_repeats": 2,
        "adapt": {"epochs": 0},
        "depth_check": {**TINY_TRAIN["depth_check"], "enabled": False},
        "crossing_point": {**TINY_TRAIN["crossing_point"], "enabled": False},
    }
    run = tmp_path / "run"
    result = train(drawn_dataset, run, config=cfg, refine_supplements=[extra], progress=False)
    n_train = len(load_split(drawn_dataset, "train"))
    assert [h["steps"] for h in result.history] == [math.ceil((n_train + 2 * 6) / cfg["batch_size"])]
    ship(run, models_dir=tmp_path / "models", gate=False)
    card = (tmp_path / "models" / CARD_NAME).read_text()
    assert "the train split, the second ones 2 times |" in card  # in the first stage's epochs
    with pytest.raises(ConfigError, match="drawn-late"):  # they trained the first epochs: kept to resume
        train(drawn_dataset, run, config=cfg, refine_supplements=[other], progress=False)
    plain = train(
        drawn_dataset,
        tmp_path / "plain",
        config={**cfg, "other_renderer_repeats": 0},
        refine_supplements=[extra],
        progress=False,
    )
    assert [h["steps"] for h in plain.history] == [math.ceil(n_train / cfg["batch_size"])]


def test_interrupted_adapt_epochs_resume_after_their_last_epoch(
    trained_run, drawn_dataset, tmp_path, monkeypatch
):
    """Adapt epochs stopped during the second go on from the first's checkpoint to the same weights as
    epochs that were not stopped."""
    from rebar_data.perception.networks.files import load_checkpoint
    from rebar_data.perception.training import adapt as adapt_train
    from tests.perception.synthetic import SyntheticSpec, write_synthetic_dataset

    spec = SyntheticSpec(width=192, height=144, focal_px=157.5, trajectories=2, frames=2)
    extra = load_split(write_synthetic_dataset(tmp_path / "data", spec, seed=8, name="drawn-x"), "train")
    samples = load_split(drawn_dataset, "train")
    cfg = TrainConfig.model_validate({**TINY_TRAIN, "adapt": {"epochs": 2}})
    whole, stopped = tmp_path / "whole", tmp_path / "stopped"
    for run in (whole, stopped):
        shutil.copytree(trained_run.out_dir, run)
    path, history = adapt_train.adapt_first_stage(whole, cfg, samples, extra, base_epoch=1, data=["x"])
    assert path == whole / adapt_train.ADAPTED and len(history) == 2
    epoch = adapt_train.train_epoch

    def stop_in_the_second(*args, **kwargs):
        if kwargs["epoch"] == 2:
            raise KeyboardInterrupt
        return epoch(*args, **kwargs)

    monkeypatch.setattr(adapt_train, "train_epoch", stop_in_the_second)
    with pytest.raises(KeyboardInterrupt):
        adapt_train.adapt_first_stage(stopped, cfg, samples, extra, base_epoch=1, data=["x"])
    assert not (stopped / adapt_train.ADAPTED).exists()
    monkeypatch.setattr(adapt_train, "train_epoch", epoch)
    path, history = adapt_train.adapt_first_stage(stopped, cfg, samples, extra, base_epoch=1, data=["x"])
    assert len(history) == 2
    a, b = load_checkpoint(whole / adapt_train.ADAPTED)[0], load_checkpoint(path)[0]
    for k, v in a.state_dict().items():
        torch.testing.assert_close(b.state_dict()[k], v)


def test_a_run_from_before_other_renderer_repeats_resumes_only_without_them(tmp_path):
    from rebar_data.perception.training.train import _check_resumable

    saved = TrainConfig().model_dump(mode="json")
    del saved["other_renderer_repeats"]  # a run folder written before the setting existed
    _check_resumable(saved, TrainConfig(other_renderer_repeats=0), tmp_path / "last.pt")
    with pytest.raises(ConfigError, match="other_renderer_repeats = 0, not 2"):
        _check_resumable(saved, TrainConfig(), tmp_path / "last.pt")  # the default


def test_the_training_device_is_the_gpu_where_there_is_one_and_a_bad_one_is_refused():
    from rebar_data.perception.training.epochs import training_device

    assert training_device("cpu").type == "cpu"
    assert training_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ConfigError, match="accepted: one of auto, cpu, cuda"):
        training_device("tpu")
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="sees no GPU"):
            training_device("cuda")
