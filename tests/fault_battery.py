"""The fault battery: the CLI tried as a new user and a careless one would, each case judged clean or not.

Not part of ``make test`` (it builds a dataset and loads the detector many times: about 10 minutes on 2
cores). Run it from the project root::

    .venv/bin/python tests/fault_battery.py [--work DIR] [--only SUBSTRING]

A case is clean when the command does what was asked, or refuses in one line (``error: ...``, or argparse's
usage and error line) with a non-zero exit, with no traceback, with no ``error:`` on a success, and with every
file the user had left as it was (hashed before and after). It prints one line a case and a count.
"""

from __future__ import annotations

import argparse
import hashlib
import os
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


def cases(smoke: Path, images: Path) -> list[Case]:
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
    # --- detect ---
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
        "detect dataset --out a user's parquet",
        lambda w: rebar("detect", str(smoke), "--split", "test", "--out", str(user_parquet(w))),
        "refused",
        protect=lambda w: [user_parquet(w)],
    )
    add(
        "detect dataset --out a folder",
        lambda w: rebar("detect", str(smoke), "--split", "test", "--out", str(w)),
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
    return c


def main() -> int:
    global _WORK
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--work", default=None, help="scratch folder (default: a new temporary one)")
    ap.add_argument("--only", default=None, help="run the cases whose name holds this text")
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
    selected = [x for x in cases(smoke, images) if not args.only or args.only in x.name]
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
