"""The fault battery: the CLI tried as a new user and a careless one would, each case judged clean or not.

Not part of ``make test`` (it builds a dataset and loads the detector many times: about 15 minutes on 2
cores). Run it from the project root::

    .venv/bin/python tests/fault_battery.py [--work DIR] [--only SUBSTRING] [--skip SUBSTRING]

A case is clean when the command does what was asked, or refuses in one line (``error: ...``, or argparse's
usage and error line) with a non-zero exit, with no traceback, with no ``error:`` on a success, and with every
file the user had left as it was (hashed before and after). It prints one line a case and a count.

The cases of a full disk and of a read-only dataset mount a small tmpfs and a read-only bind mount (as
root, where ``mount`` works); elsewhere they are left out, and the count says how many.
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
REBAR = str(ROOT / ".venv" / "bin" / "rebar")
PY = str(ROOT / ".venv" / "bin" / "python")
ENV = {**os.environ, "EGL_PLATFORM": "surfaceless"}


@dataclass
class Result:
    rc: int
    out: str
    err: str


@dataclass
class Case:
    name: str
    run: Callable[[Path], Result]
    expect: str  # "ok", "refused" or "partial" (a batch that goes on and exits non-zero)
    protect: Callable[[Path], list[Path]] = field(
        default=lambda w: []
    )  # makes the user's files, returns them
    check: Callable[[Path, Result], str | None] = field(default=lambda w, r: None)


def rebar(*argv: str, cwd: Path | None = None, timeout: float = 600) -> Result:
    p = subprocess.run(
        [REBAR, *argv], capture_output=True, text=True, env=ENV, cwd=cwd or ROOT, timeout=timeout
    )
    return Result(p.returncode, p.stdout, p.stderr)


def snapshot(paths: list[Path]) -> dict[str, str]:
    """Every file under ``paths`` with its SHA-256 (folders walked)."""
    files: dict[str, str] = {}
    for p in paths:
        for f in [p] if p.is_file() else sorted(x for x in p.rglob("*") if x.is_file()) if p.exists() else []:
            files[str(f)] = hashlib.sha256(f.read_bytes()).hexdigest()
    return files


def judge(case: Case, r: Result, before: dict, after: dict) -> str | None:
    """Why the case is not clean, or None."""
    if "Traceback" in r.err or "Traceback" in r.out:
        return "traceback"
    if before != after:
        lost = sorted(set(before) - set(after))
        changed = sorted(k for k in set(before) & set(after) if before[k] != after[k])
        return f"user files lost ({len(lost)}) or changed ({len(changed)})"
    lines = [x for x in r.err.splitlines() if x.strip()]
    errors = [x for x in lines if "error:" in x]
    if case.expect == "ok":
        if r.rc != 0:
            return f"exit {r.rc}: {lines[-1] if lines else ''}"
        if errors:
            return f"`error:` on success: {errors[0][:100]}"
    elif case.expect == "refused":
        if r.rc == 0:
            return "accepted"
        if len(errors) != 1:
            return f"{len(errors)} error lines: {' | '.join(lines[-3:])[:200]}"
    elif case.expect == "partial" and r.rc == 0:
        return "exit 0 although items failed"
    return case.check(case_work(case), r)


_WORK: Path = Path()


def case_work(case: Case) -> Path:
    return _WORK / case.name.replace(" ", "_").replace("/", "_")


def write_binary(p: Path) -> Path:
    p.write_bytes(bytes(range(256)) * 64)
    return p


def user_folder(p: Path, n: int = 5) -> Path:
    p.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        (p / f"notes-{i}.txt").write_text(f"the user's own file {i}\n")
    return p


def sh(script: str, timeout: float = 600) -> Result:
    """A bash command line (for what only a shell makes, such as ``<(...)``)."""
    p = subprocess.run(
        ["bash", "-c", script], capture_output=True, text=True, env=ENV, cwd=ROOT, timeout=timeout
    )
    return Result(p.returncode, p.stdout, p.stderr)


def _mount(*argv: str) -> bool:
    return subprocess.run(["mount", *argv], capture_output=True).returncode == 0


def can_mount() -> bool:
    """Whether this process may mount a tmpfs (root, and a kernel and container that allow it)."""
    if os.geteuid() != 0 or shutil.which("mount") is None:
        return False
    probe = Path(tempfile.mkdtemp(prefix="rebar-battery-mount-"))
    try:
        ok = _mount("-t", "tmpfs", "-o", "size=64k", "tmpfs", str(probe))
        if ok:
            subprocess.run(["umount", str(probe)], check=True)
        return ok
    finally:
        probe.rmdir()


class Mounted:
    """A mount for one case's command: a tmpfs of ``size`` or ``source`` bound read-only; unmounted after."""

    def __init__(self, at: Path, *, size: str | None = None, source: Path | None = None):
        self.at, self.size, self.source = at, size, source

    def __enter__(self) -> Path:
        self.at.mkdir(parents=True, exist_ok=True)
        if self.size:
            assert _mount("-t", "tmpfs", "-o", f"size={self.size}", "tmpfs", str(self.at))
        else:
            assert _mount("--bind", str(self.source), str(self.at))
            assert _mount("-o", "remount,ro,bind", str(self.at))
        return self.at

    def __exit__(self, *exc: object) -> None:
        subprocess.run(["umount", str(self.at)], check=True)


def cases(smoke: Path, images: Path, *, mounts: bool = True) -> list[Case]:
    """The battery. ``smoke`` is a built smoke dataset, ``images`` a folder of a few PNG frames."""
    c: list[Case] = []

    def add(name, run, expect, protect=None, check=None):
        c.append(Case(name, run, expect, protect or (lambda w: []), check or (lambda w, r: None)))

    pipe = str(ROOT / "pipelines" / "smoke.yaml")
    # --- configs ---
    add("pipeline missing", lambda w: rebar("mesh", str(w / "none.yaml"), "--out", str(w / "m")), "refused")
    add("pipeline is a folder", lambda w: rebar("mesh", str(w), "--out", str(w / "m")), "refused")
    add(
        "pipeline binary",
        lambda w: rebar("dataset", "build", str(write_binary(w / "b.yaml")), "--out", str(w / "d")),
        "refused",
    )

    def yaml_case(text: str):
        def run(w: Path) -> Result:
            (w / "p.yaml").write_text(text)
            return rebar("mesh", str(w / "p.yaml"), "--out", str(w / "m"))

        return run

    add("pipeline empty", yaml_case(""), "refused")
    add("pipeline a list", yaml_case("- 1\n- 2\n"), "refused")
    add("pipeline bad yaml", yaml_case("name: [unclosed\n"), "refused")
    smoke_text = (ROOT / "pipelines" / "smoke.yaml").read_text()
    add("pipeline unknown key", yaml_case(smoke_text + "colour: red\n"), "refused")
    add("pipeline bad value", yaml_case(smoke_text.replace("seed: 7", "seed: -3")), "refused")
    add("pipeline bad version", yaml_case(smoke_text.replace("version: 0.3.0", "version: 1.0")), "refused")
    add(
        "suite binary",
        lambda w: rebar("servo", "run", str(write_binary(w / "s.yaml")), "--out", str(w / "r")),
        "refused",
    )
    add(
        "suite missing",
        lambda w: rebar("servo", "run", str(w / "none.yaml"), "--out", str(w / "r")),
        "refused",
    )

    def fake_run(w: Path) -> Path:
        r = w / "run"
        r.mkdir()
        return r

    add(
        "thresholds binary",
        lambda w: rebar("servo", "check", str(fake_run(w)), "--thresholds", str(write_binary(w / "t.yaml"))),
        "refused",
    )
    add("servo check not a run", lambda w: rebar("servo", "check", str(user_folder(w / "x"))), "refused")
    add("servo check missing", lambda w: rebar("servo", "check", str(w / "none")), "refused")
    add(
        "train config binary",
        lambda w: rebar(
            "train", str(smoke), "--config", str(write_binary(w / "c.yaml")), "--out", str(w / "t")
        ),
        "refused",
    )
    # --- dataset build ---
    add(
        "build --workers -1",
        lambda w: rebar("dataset", "build", pipe, "--out", str(w), "--workers", "-1"),
        "refused",
    )
    add(
        "build --workers 1000",
        lambda w: rebar("dataset", "build", pipe, "--out", str(w), "--workers", "1000"),
        "refused",
    )

    def out_is_file(w: Path) -> Path:
        f = w / "out.txt"
        f.write_text("the user's file\n")
        return f

    add(
        "build --out a file",
        lambda w: rebar("dataset", "build", pipe, "--out", str(out_is_file(w))),
        "refused",
        protect=lambda w: [out_is_file(w)],
    )
    add(
        "build existing without --force",
        lambda w: rebar("dataset", "build", pipe, "--out", str(smoke.parents[1])),
        "refused",
        protect=lambda w: [smoke],
    )

    def force_over_user(w: Path) -> Result:
        user_folder(w / "smoke" / "v0.3.0")
        return rebar("dataset", "build", pipe, "--out", str(w), "--force")

    add(
        "build --force over a user folder",
        force_over_user,
        "refused",
        protect=lambda w: [user_folder(w / "smoke" / "v0.3.0")],
    )
    add(
        "build --address without ray",
        lambda w: rebar("dataset", "build", pipe, "--out", str(w), "--address", "auto"),
        "refused",
    )

    def concurrent(second: tuple[str, ...]) -> Callable[[Path], Result]:
        def run(w: Path) -> Result:
            first = subprocess.Popen(
                [REBAR, "dataset", "build", pipe, "--out", str(w), "--workers", "1"],
                env=ENV,
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            try:
                time.sleep(6)
                return rebar("dataset", "build", pipe, "--out", str(w), "--workers", "1", *second, timeout=30)
            finally:
                first.send_signal(signal.SIGINT)
                first.wait(60)

        return run

    add("build twice at once", concurrent(()), "refused")
    add("build --resume while live", concurrent(("--resume",)), "refused")
    add("build --force while live", concurrent(("--force",)), "refused")

    def ctrl_c(w: Path) -> Result:
        p = subprocess.Popen(
            [REBAR, "dataset", "build", pipe, "--out", str(w), "--workers", "2"],
            env=ENV,
            stdout=subprocess.PIPE,
            stderr=subprocess.PIPE,
            text=True,
            start_new_session=True,
        )
        deadline = time.time() + 180
        while time.time() < deadline and not list(w.glob("smoke/.v0.3.0.partial/records/*.pkl")):
            time.sleep(0.5)
        os.killpg(p.pid, signal.SIGINT)  # as a terminal's Ctrl-C reaches the whole process group
        out, err = p.communicate(timeout=120)
        return Result(p.returncode, out, err)

    def resumable(w: Path, r: Result) -> str | None:
        lines = [x for x in r.err.splitlines() if x.strip() and "%" not in x]
        if len(lines) > 2:
            return f"{len(lines)} lines after Ctrl-C"
        if r.rc == 0:
            return "exit 0 after Ctrl-C"
        done = rebar("dataset", "build", pipe, "--out", str(w), "--resume")
        return None if done.rc == 0 else f"--resume failed: {done.err[-200:]}"

    add("build Ctrl-C then --resume", ctrl_c, "partial", check=resumable)
    # --- validate, audit ---
    add("validate missing", lambda w: rebar("dataset", "validate", str(w / "none")), "refused")
    add(
        "validate a user folder", lambda w: rebar("dataset", "validate", str(user_folder(w / "x"))), "refused"
    )
    add("validate a file", lambda w: rebar("dataset", "validate", str(out_is_file(w))), "refused")
    add("audit a user folder", lambda w: rebar("dataset", "audit", str(user_folder(w / "x"))), "refused")

    def damaged(kind: str) -> Callable[[Path], Result]:
        def run(w: Path) -> Result:
            d = w / "ds"
            shutil.copytree(smoke, d)
            shutil.rmtree(d / "audit", ignore_errors=True)
            if kind == "image":
                img = next((d / "images" / "train").glob("*.png"))
                img.write_bytes(img.read_bytes()[:200])
            elif kind == "nan":
                import pyarrow.parquet as pq

                t = pq.read_table(d / "tables" / "keypoints.parquet")
                col = t.column("depth_m").to_pylist()
                col[0] = float("nan")
                import pyarrow as pa

                t = t.set_column(t.schema.get_field_index("depth_m"), "depth_m", pa.array(col, pa.float64()))
                pq.write_table(t, d / "tables" / "keypoints.parquet")
            elif kind == "category":
                import json

                p = d / "annotations" / "train.json"
                coco = json.loads(p.read_text())
                coco["annotations"][0]["category_id"] = 99
                p.write_text(json.dumps(coco))
            subprocess.run(
                [
                    PY,
                    "-c",
                    f"from rebar_data.dataset.writers.manifest import write_manifest; from pathlib import Path; write_manifest(Path({str(d)!r}))",
                ],
                check=True,
                env=ENV,
            )
            return rebar("dataset", "validate", str(d))

        return run

    def names(word: str) -> Callable[[Path, Result], str | None]:
        return lambda w, r: None if word in (r.out + r.err).lower() else f"no line names the {word}"

    add("validate undecodable image", damaged("image"), "partial", check=names("decode"))
    add("validate NaN in a table", damaged("nan"), "partial", check=names("finite"))
    add("validate unknown COCO category", damaged("category"), "partial", check=names("category"))

    def ultralytics_cache(w: Path) -> Result:
        d = w / "ds"
        shutil.copytree(smoke, d)
        (d / "labels" / "train.cache").write_bytes(b"\x80\x04cache")
        return rebar("dataset", "validate", str(d))

    add("validate with Ultralytics' cache", ultralytics_cache, "ok")
    # --- detect, score ---
    add(
        "detect IMAGES --out IMAGES",
        lambda w: rebar("detect", str(images), "--out", str(images)),
        "refused",
        protect=lambda w: [images],
    )

    def bad_image_in_batch(w: Path) -> Result:
        f = w / "imgs"
        shutil.copytree(images, f)
        (f / "000-broken.png").write_bytes(b"not a png")
        return rebar("detect", str(f), "--out", str(w / "o"))

    def wrote_rest(w: Path, r: Result) -> str | None:
        return (
            None if (w / "o" / "detections.parquet").exists() else "no detections.parquet for the good images"
        )

    add("detect a folder with a bad image", bad_image_in_batch, "partial", check=wrote_rest)
    add("detect missing input", lambda w: rebar("detect", str(w / "none"), "--out", str(w / "o")), "refused")
    add(
        "detect --out a file (images)",
        lambda w: rebar("detect", str(images), "--out", str(out_is_file(w))),
        "refused",
        protect=lambda w: [out_is_file(w)],
    )
    add(
        "detect --out a user folder",
        lambda w: rebar("detect", str(images), "--out", str(user_folder(w / "u"))),
        "refused",
        protect=lambda w: [user_folder(w / "u")],
    )

    def user_parquet(w: Path) -> Path:
        f = w / "mine.parquet"
        f.write_bytes(b"PAR1 the user's own table PAR1")
        return f

    add(
        "score dataset --out a user's parquet",
        lambda w: rebar("score", str(smoke), "--split", "test", "--out", str(user_parquet(w))),
        "refused",
        protect=lambda w: [user_parquet(w)],
    )
    add(
        "score dataset --out a folder",
        lambda w: rebar("score", str(smoke), "--split", "test", "--out", str(w)),
        "refused",
    )
    add(
        "detect --threads 0",
        lambda w: rebar("detect", str(images), "--out", str(w / "o"), "--threads", "0"),
        "refused",
    )
    add(
        "detect --camera malformed",
        lambda w: rebar("detect", str(images), "--out", str(w / "o"), "--camera", "1,2"),
        "refused",
    )
    add("detect images", lambda w: rebar("detect", str(images), "--out", str(w / "o")), "ok")

    def detect_twice(w: Path) -> Result:
        rebar("detect", str(images), "--out", str(w / "o"))
        return rebar("detect", str(images), "--out", str(w / "o"))

    add("detect again into its own output", detect_twice, "ok")
    # --- servo ---
    add(
        "servo run --out a user folder",
        lambda w: rebar("servo", "run", str(ROOT / "eval" / "ci.yaml"), "--out", str(user_folder(w / "u"))),
        "refused",
        protect=lambda w: [user_folder(w / "u")],
    )
    add(
        "servo run --out a dataset",
        lambda w: rebar("servo", "run", str(ROOT / "eval" / "ci.yaml"), "--out", str(smoke)),
        "refused",
        protect=lambda w: [smoke],
    )
    add(
        "servo run --episodes 0",
        lambda w: rebar(
            "servo", "run", str(ROOT / "eval" / "ci.yaml"), "--out", str(w / "r"), "--episodes", "0"
        ),
        "refused",
    )
    add(
        "servo run --episodes -1",
        lambda w: rebar(
            "servo", "run", str(ROOT / "eval" / "ci.yaml"), "--out", str(w / "r"), "--episodes", "-1"
        ),
        "refused",
    )
    add(
        "servo run --out a file",
        lambda w: rebar("servo", "run", str(ROOT / "eval" / "ci.yaml"), "--out", str(out_is_file(w))),
        "refused",
        protect=lambda w: [out_is_file(w)],
    )
    # --- publish, train, diff, bench ---
    add(
        "publish --out a file",
        lambda w: rebar("dataset", "publish", str(smoke), "--out", str(out_is_file(w))),
        "refused",
        protect=lambda w: [out_is_file(w)],
    )
    add(
        "publish --force over a user folder",
        lambda w: rebar("dataset", "publish", str(smoke), "--out", str(user_folder(w / "u")), "--force"),
        "refused",
        protect=lambda w: [user_folder(w / "u")],
    )
    add(
        "publish --out inside the dataset",
        lambda w: rebar("dataset", "publish", str(smoke), "--out", str(smoke / "bundle")),
        "refused",
        protect=lambda w: [smoke],
    )
    add(
        "publish a user folder",
        lambda w: rebar("dataset", "publish", str(user_folder(w / "x")), "--out", str(w / "b")),
        "refused",
    )
    add(
        "train --out a user folder",
        lambda w: rebar("train", str(smoke), "--out", str(user_folder(w / "u")), "--epochs", "1"),
        "refused",
        protect=lambda w: [user_folder(w / "u")],
    )
    add(
        "train on a user folder",
        lambda w: rebar("train", str(user_folder(w / "x")), "--out", str(w / "t")),
        "refused",
    )
    add(
        "train --epochs 0",
        lambda w: rebar("train", str(smoke), "--out", str(w / "t"), "--epochs", "0"),
        "refused",
    )
    add(
        "diff two user folders",
        lambda w: rebar("dataset", "diff", str(user_folder(w / "a")), str(user_folder(w / "b"))),
        "refused",
    )
    add("bench --only unknown", lambda w: rebar("bench", "--only", "nothing"), "refused")
    add(
        "mesh --out a file",
        lambda w: rebar("mesh", pipe, "--out", str(out_is_file(w))),
        "refused",
        protect=lambda w: [out_is_file(w)],
    )

    # --- symbolic links, bundles, read-only inputs, full disks (issue 58) ---
    def linked(w: Path) -> Path:
        (w / "target").mkdir(exist_ok=True)
        (w / "target" / "theirs.txt").write_text("the user's file\n")
        if not (w / "link").is_symlink():
            (w / "link").symlink_to(w / "target")
        return w / "link"

    def still_a_link(w: Path, r: Result) -> str | None:
        if not (w / "link").is_symlink():
            return "the link was replaced"
        return None if "symbolic link" in r.err else "no line says it is a symbolic link"

    add(
        "mesh --out a symbolic link",
        lambda w: rebar("mesh", pipe, "--out", str(linked(w))),
        "refused",
        protect=lambda w: [linked(w).parent / "target"],
        check=still_a_link,
    )
    add(
        "detect --out a symbolic link",
        lambda w: rebar("detect", str(images), "--out", str(linked(w))),
        "refused",
        protect=lambda w: [linked(w).parent / "target"],
        check=still_a_link,
    )

    def after_a_link(w: Path) -> Result:
        (w / "empty").mkdir()
        (w / "link").symlink_to(w / "empty")
        rebar("mesh", pipe, "--out", str(w / "link"))  # refused: the link kept
        return rebar("mesh", pipe, "--out", str(w / "empty"))  # where it points: written

    add(
        "mesh into a symbolic link's folder after its refusal",
        after_a_link,
        "ok",
        check=lambda w, r: None if (w / "link").is_symlink() else "the link was replaced",
    )

    def edit_bundle(w: Path) -> Result:
        r = rebar("dataset", "publish", str(smoke), "--out", str(w / "b"))
        if r.rc != 0:
            return r
        img = next((w / "b" / "images" / "train").glob("*.png"))
        img.write_bytes(img.read_bytes()[:100])  # re-saved badly in the bundle
        return rebar("dataset", "validate", str(smoke))

    add("publish, edit a bundle image, validate the dataset", edit_bundle, "ok")

    def killed_publish(w: Path) -> Result:
        stale = w / ".b.partial-k1ll3d"
        stale.mkdir()
        (stale / "README.md").write_text("half a bundle\n")
        return rebar("dataset", "publish", str(smoke), "--out", str(w / "b"))

    add(
        "publish after a killed publish",
        killed_publish,
        "ok",
        check=lambda w, r: (
            None if not list(w.glob(".b.partial-*")) else "the killed publish's folder is left"
        ),
    )

    def truncated(w: Path) -> Path:
        d = w / "ds"
        if not d.exists():
            shutil.copytree(smoke, d)
            info = d / "meta" / "info.json"
            info.write_bytes(info.read_bytes()[:300])
        return d

    names_info = names("info.json")
    for argv in (("audit",), ("diff", str(smoke)), ("publish",)):

        def run(w: Path, argv=argv) -> Result:
            extra = ["--out", str(w / "b")] if argv[0] == "publish" else []
            return rebar("dataset", argv[0], *argv[1:], str(truncated(w)), *extra)

        add(
            f"{argv[0]} a truncated info.json",
            run,
            "refused",
            protect=lambda w: [truncated(w)],
            check=names_info,
        )

    def wrong_depth(w: Path) -> Path:
        d = w / "ds"
        if not d.exists():
            shutil.copytree(smoke, d)
            import cv2
            import numpy as np

            for kind in ("depth", "sensor_depth"):
                for f in sorted((d / kind / "test").glob("*.png"))[:1]:
                    cv2.imwrite(str(f), np.full((48, 64), 1000, np.uint16))
        return d

    add(
        "score a dataset with a depth image of the wrong size",
        lambda w: rebar("score", str(wrong_depth(w)), "--split", "test", "--out", str(w / "o.parquet")),
        "refused",
        check=lambda w, r: None if "depth image of 64x48" in r.err else "no line names the depth file's size",
    )
    lol = '&a ["lol","lol","lol","lol","lol","lol","lol","lol","lol"]'
    nested = [lol] + [
        f"&{n} [{','.join([f'*{p}'] * 9)}]" for p, n in zip("abcdefgh", "bcdefghi", strict=True)
    ]
    add(  # a "billion laughs": 9**9 strings from 1.2 kB, as the value of a field
        "pipeline of nested aliases",
        yaml_case(smoke_text.replace("seed: 7", f"seed: [{', '.join(nested)}]")),
        "refused",
    )
    add(
        "pipeline with a long bad value",
        yaml_case(smoke_text.replace("seed: 7", "seed: [" + ", ".join(["abcdefghij"] * 2000) + "]")),
        "refused",
        check=lambda w, r: None if len(r.err) < 400 else f"a message of {len(r.err)} characters",
    )
    tiny = (
        "name: tiny\nversion: 0.0.1\nseed: 5\nmesh: {kind: planar, width_m: 0.8, height_m: 0.6}\ncamera:\n"
        "  intrinsics: {width: 160, height: 120, fx: 150.0, fy: 150.0, cx: 80.0, cy: 60.0}\n"
        "  trajectories: [{kind: orbit_arc, count: 2, frames: 2, edge_margin_m: 0.1}]\n"
    )
    add(
        "build a pipeline given as a pipe",  # bash's <(...): /dev/fd/N, readable once
        lambda w: sh(
            f"{REBAR} dataset build <(printf '%s' {shlex.quote(tiny)}) --out {shlex.quote(str(w / 'data'))} "
            "--workers 1"
        ),
        "ok",
    )

    def texture_cache(w: Path) -> Result:
        cfg = w / "p.yaml"
        cfg.write_text(tiny + f"render: {{cache_dir: {w / 'cache'}}}\n")
        first = rebar("render", str(cfg), "--out", str(w / "r1"), "--frames", "1")
        if first.rc != 0:
            return first
        for i, f in enumerate(sorted((w / "cache").rglob("*.npz"))):  # a power cut: empty or half-written
            f.write_bytes(b"" if i % 2 else f.read_bytes()[: f.stat().st_size // 2])
        return rebar("render", str(cfg), "--out", str(w / "r2"), "--frames", "1")

    def healed(w: Path, r: Result) -> str | None:
        import numpy as np

        for f in (w / "cache").rglob("*.npz"):
            try:
                with np.load(f) as z:
                    [z[k] for k in z.files]
            except Exception:  # noqa: BLE001
                return f"{f.name} is still damaged"
        return None

    add("render with a damaged texture cache", texture_cache, "ok", check=healed)

    def own_tmp(w: Path) -> Result:
        (w / "tmp").mkdir()
        p = subprocess.run(
            [REBAR, "render", pipe, "--out", str(w / "r"), "--frames", "1"],
            capture_output=True,
            text=True,
            env={**{k: v for k, v in ENV.items() if k != "XDG_RUNTIME_DIR"}, "TMPDIR": str(w / "tmp")},
        )
        return Result(p.returncode, p.stdout, p.stderr)

    add(
        "render leaves no temporary folder",
        own_tmp,
        "ok",
        check=lambda w, r: (
            None if not any((w / "tmp").iterdir()) else f"left {[p.name for p in (w / 'tmp').iterdir()]}"
        ),
    )
    if not mounts:
        return c

    def read_only(w: Path) -> Path:
        d = w / "ds"
        if not d.exists():
            shutil.copytree(smoke, d)
            shutil.rmtree(d / "audit", ignore_errors=True)
        return d

    def on_read_only(*argv: str, out: bool = False) -> Callable[[Path], Result]:
        def run(w: Path) -> Result:
            with Mounted(w / "ro", source=read_only(w)) as ro:
                args = [a.replace("{ro}", str(ro)) for a in argv]
                return rebar(*args, *(["--out", str(w / "o")] if out else []))

        return run

    def says_out(w: Path, r: Result) -> str | None:
        return None if "--out" in r.err and "read-only" in r.err else "no line says where the audit can write"

    protect_ro = lambda w: [read_only(w)]  # noqa: E731
    add("validate a read-only dataset", on_read_only("dataset", "validate", "{ro}"), "ok", protect=protect_ro)
    add(
        "audit a read-only dataset",
        on_read_only("dataset", "audit", "{ro}"),
        "refused",
        protect=protect_ro,
        check=says_out,
    )
    add(
        "audit a read-only dataset --out",
        on_read_only("dataset", "audit", "{ro}", out=True),
        "ok",
        protect=protect_ro,
    )
    add(
        "publish a read-only dataset",
        on_read_only("dataset", "publish", "{ro}", out=True),
        "ok",
        protect=protect_ro,
    )
    add(
        "diff a read-only dataset",
        on_read_only("dataset", "diff", str(smoke), "{ro}"),
        "ok",
        protect=protect_ro,
    )

    def full_disk(*argv: str, size: str) -> Callable[[Path], Result]:
        def run(w: Path) -> Result:
            with Mounted(w / "full", size=size) as full:
                r = rebar(*[a.replace("{full}", str(full)) for a in argv])
                left = [p.name for p in full.rglob("*") if ".tmp" in p.name or ".partial-" in p.name]
                return Result(r.rc, r.out, r.err + (f"\nhalf-written: {left}" if left else ""))

        return run

    def space_line(w: Path, r: Result) -> str | None:
        if "half-written:" in r.err:
            return r.err.splitlines()[-1]
        return (
            None if "no space left" in r.err and "needs about" in r.err else "no line names the space needed"
        )

    add(
        "build on a full disk",
        full_disk("dataset", "build", pipe, "--out", "{full}", "--workers", "1", size="2m"),
        "refused",
        check=space_line,
    )
    add(
        "publish on a full disk",
        full_disk("dataset", "publish", str(smoke), "--out", "{full}/b", size="2m"),
        "refused",
        check=space_line,
    )
    return c


def main() -> int:
    global _WORK
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=None, help="scratch folder (default: a new temporary one)")
    ap.add_argument("--only", default=None, help="run the cases whose name holds this text")
    ap.add_argument(
        "--skip", action="append", default=[], help="leave out the cases whose name holds this text"
    )
    args = ap.parse_args()
    _WORK = Path(args.work or tempfile.mkdtemp(prefix="rebar-battery-"))
    _WORK.mkdir(parents=True, exist_ok=True)
    smoke = _WORK / "_data" / "smoke" / "v0.3.0"
    if not smoke.exists():
        r = rebar("dataset", "build", str(ROOT / "pipelines" / "smoke.yaml"), "--out", str(_WORK / "_data"))
        if r.rc != 0:
            print(r.err, file=sys.stderr)
            return 1
    images = _WORK / "_images"
    if not images.exists():
        images.mkdir()
        for f in sorted((smoke / "images" / "test").glob("*.png"))[:2]:
            shutil.copy(f, images / f.name)
    mounts = can_mount()
    every = cases(smoke, images, mounts=mounts)
    selected = [
        x for x in every if (not args.only or args.only in x.name) and not any(k in x.name for k in args.skip)
    ]
    if not mounts:
        print(
            f"note: no mount here (not root, or not allowed): {len(cases(smoke, images)) - len(every)} cases left out"
        )
    clean = 0
    for case in selected:
        w = case_work(case)
        shutil.rmtree(w, ignore_errors=True)
        w.mkdir(parents=True)
        keep = [smoke, images, *case.protect(w)]
        before = snapshot(keep)
        t0 = time.perf_counter()
        try:
            r = case.run(w)
        except subprocess.TimeoutExpired:
            r = Result(-1, "", "Traceback: timed out")
        keep = [smoke, images, *case.protect(w)]
        why = judge(case, r, before, snapshot(keep))
        clean += why is None
        print(
            f"{'clean' if why is None else 'NOT  '}  {case.name} ({time.perf_counter() - t0:.0f} s){'' if why is None else ': ' + why}",
            flush=True,
        )
    print(f"{clean} of {len(selected)} cases handled cleanly")
    return 0 if clean == len(selected) else 1


if __name__ == "__main__":
    sys.exit(main())
