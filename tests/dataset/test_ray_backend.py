from __future__ import annotations

import os
import socket
import sys

import pyarrow.parquet as pq
import pytest
import yaml

from rebar_data.cli import main
from rebar_data.dataset.validate import validate_dataset
from rebar_data.dataset.worker import FrameWorker

LABEL_PREFIXES = ("labels/", "annotations/", "tables/")


def _hashes(ds, prefixes=LABEL_PREFIXES) -> dict[str, str]:
    man = pq.read_table(ds / "meta/manifest.parquet").to_pydict()
    return {p: h for p, h in zip(man["path"], man["sha256"], strict=True) if p.startswith(prefixes)}


@pytest.fixture(scope="module")
def ray_cluster():
    """One local two-CPU Ray cluster for the module, shut down at its end."""
    ray = pytest.importorskip("ray")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False)
    yield ray
    ray.shutdown()


def test_without_ray_the_backend_is_one_clear_message(tiny_config, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # import ray raises ImportError
    code = main(["dataset", "build", str(tiny_config), "--out", str(tmp_path), "--backend", "ray"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "pip install" in err[0] and ".[ray]" in err[0]
    assert not (tmp_path / "tiny").exists()


def test_a_broken_pipeline_is_reported_before_ray_is_looked_for(tiny_config, tmp_path, monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "ray", None)  # without Ray, the pipeline's own error still comes first
    data = yaml.safe_load(tiny_config.read_text())
    data["camera"]["trajectories"][0]["count"] = "not-a-number"
    broken = tmp_path / "broken.yaml"
    broken.write_text(yaml.safe_dump(data))
    out = tmp_path / "out"
    code = main(["dataset", "build", str(broken), "--out", str(out), "--backend", "ray", "--address", "auto"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert "camera.trajectories.0.count = 'not-a-number'" in err[0] and "pip install" not in err[0]
    assert not out.exists()


def test_address_without_the_ray_backend_is_refused(tiny_config, tmp_path, capsys):
    code = main(["dataset", "build", str(tiny_config), "--out", str(tmp_path), "--address", "auto"])
    assert code == 2 and "--backend ray" in capsys.readouterr().err


def test_an_address_where_no_cluster_answers_is_one_clear_error(tiny_config, tmp_path, capsys):
    pytest.importorskip("ray")
    with socket.socket() as s:  # a loopback port that nothing listens on once closed
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    args = ["--out", str(tmp_path), "--backend", "ray", "--address", f"127.0.0.1:{port}"]
    assert main(["dataset", "build", str(tiny_config), *args]) == 2
    assert "no Ray cluster answers" in capsys.readouterr().err
    assert not (tmp_path / "tiny").exists()


def test_ray_build_is_byte_identical_to_the_local_build(
    ray_cluster, tiny_config, tiny_dataset, tmp_path, capsys
):
    code = main(["dataset", "build", str(tiny_config), "--out", str(tmp_path), "--backend", "ray"])
    out = capsys.readouterr()
    assert code == 0
    ds = tmp_path / "tiny" / "v0.0.1"
    assert out.out.strip().splitlines()[-1] == str(ds.resolve())
    assert "2 Ray actors" in out.err
    assert _hashes(ds) == _hashes(tiny_dataset)
    assert _hashes(ds, ("images/",)) == _hashes(tiny_dataset, ("images/",))
    assert validate_dataset(ds) == []
    assert ray_cluster.is_initialized()  # a cluster the caller started is left running for the caller


def crash_once_worker(marker: str) -> type[FrameWorker]:
    """A FrameWorker that renders the first frame of its first shard and then kills its own process, once
    (while ``marker`` does not exist). Defined in a function so that Ray pickles it by value."""

    class CrashOnce(FrameWorker):
        def run(self, scene, samples):
            if not os.path.exists(marker):
                self.renderer.set_scene(scene)
                self._one(samples[0])  # a file of the shard is written before the process dies
                open(marker, "w").close()
                os._exit(1)
            return super().run(scene, samples)

    return CrashOnce


def test_a_worker_dying_mid_shard_is_retried_without_duplicates_or_losses(
    ray_cluster, tiny_config, tiny_dataset, tmp_path
):
    from rebar_data.dataset.build import build_dataset
    from rebar_data.dataset.ray_backend import RayRunner

    marker = tmp_path / "crashed"
    runner = RayRunner(worker_cls=crash_once_worker(str(marker)), max_task_retries=2)
    ds = build_dataset(tiny_config, tmp_path / "out", runner=runner)
    assert marker.exists()  # the crash happened
    assert _hashes(ds) == _hashes(tiny_dataset)
    assert _hashes(ds, ("images/",)) == _hashes(tiny_dataset, ("images/",))
    samples = pq.read_table(ds / "tables/samples.parquet").column("image_id").to_pylist()
    assert len(samples) == len(set(samples)) == 12
    assert validate_dataset(ds) == []
    assert not list(ds.rglob("*.tmp"))
