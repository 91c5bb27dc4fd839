"""``rebar train`` interrupted in each of its steps resumes at that step, and the run completes as one that
was never stopped."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import yaml
from tqdm import tqdm

from rebar_data.perception.training.train import train
from tests.perception.conftest import TINY_TRAIN

# two epochs a stage, so that an interruption after the first leaves a checkpoint to resume
TWO = {
    **TINY_TRAIN,
    "epochs": 2,
    **{k: {**TINY_TRAIN[k], "epochs": 2} for k in ("refine", "depth_check", "crossing_point")},
    "refine": {**TINY_TRAIN["refine"], "epochs": 2, "quantize": "later", "calibration_patches": 64},
}
# the line each step writes as it starts or finishes an epoch, in the order they run
STEP_LINES = (
    "epoch 1/2: loss",  # the first stage
    "refiner epoch 1/2",
    "depth check epoch 1/2",
    "crossing point epoch 1/2",
    "int8 copy ...",
    "operating point ...",
    "line check ...",
    "scores ...",
)


class Interrupted(BaseException):
    """What the test raises where a user's Ctrl-C or a kill would land."""


def test_a_run_stopped_in_each_step_resumes_there_and_ends_as_an_unstopped_one(
    drawn_dataset, tmp_path, monkeypatch
):
    whole = train(drawn_dataset, tmp_path / "whole", config=TWO, progress=False)
    out = tmp_path / "stopped"
    write = tqdm.write
    said: list[str] = []
    for k, line in enumerate(STEP_LINES):
        said.clear()

        def stop_at(msg, *args, line=line, **kwargs):
            said.append(msg)
            if msg.startswith(line):
                raise Interrupted(line)

        monkeypatch.setattr(tqdm, "write", stop_at)
        with pytest.raises(Interrupted):
            train(drawn_dataset, out, config=TWO, progress=True)
        # the step the last call stopped in is done again (stopped before its first epoch was kept); the
        # steps before it were finished and are not
        done = STEP_LINES[: max(0, k - 1)]
        assert not any(m.startswith(done) for m in said), (line, [m for m in said if m.startswith(done)])
    monkeypatch.setattr(tqdm, "write", write)
    resumed = train(drawn_dataset, out, config=TWO, progress=False)
    # NaN where the tiny model finds nothing: compared as text
    assert json.dumps(resumed.results, sort_keys=True) == json.dumps(whole.results, sort_keys=True)
    assert [r["train_loss"] for r in resumed.history] == [r["train_loss"] for r in whole.history]
    a, b = (json.loads((d / "results.json").read_text()) for d in (tmp_path / "whole", out))
    for key in ("refine_history", "depth_check_history", "crossing_point_history"):
        assert [r["loss" if "point" not in key else "loss_px"] for r in a[key]] == [
            r["loss" if "point" not in key else "loss_px"] for r in b[key]
        ], key


def test_a_killed_training_process_resumes_when_run_again(drawn_dataset, tmp_path):
    """A real kill (SIGKILL, as the out-of-memory killer or a lost machine stops it) in the later stages: run
    again, the command picks up after the first stage's epochs and completes."""
    config = tmp_path / "train.yaml"
    config.write_text(yaml.safe_dump(json.loads(json.dumps(TWO))))
    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "rebar_data.cli", "train", str(drawn_dataset), "--out", str(out)]
    cmd += ["--config", str(config)]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    proc = subprocess.Popen(cmd, stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env)
    deadline = time.monotonic() + 300
    for text in proc.stderr:
        if "depth check epoch 1/2" in text or time.monotonic() > deadline:
            break
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert (out / "depth_last.pt").exists() or (out / "refine_last.pt").exists()
    again = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=600)
    assert again.returncode == 0, again.stderr[-2000:]
    # the first stage's epochs were kept: none is trained again (the later stages' lines start with their name)
    assert "resuming" in again.stderr and not re.search(r"^epoch \d/2: loss", again.stderr, re.MULTILINE)
    assert Path(again.stdout.strip().splitlines()[-1]) == out
    assert json.loads((out / "results.json").read_text())["results"]
