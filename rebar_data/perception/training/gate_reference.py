"""The regression gate's reference (``gate.json``): a model measured on the gate set
(:func:`~rebar_data.perception.evaluation.gate.reference`) and written beside it. Shipping a model writes it;
``python -m rebar_data.perception.training.gate_reference`` writes it again for the model shipped."""

from __future__ import annotations

import argparse
import json
import tempfile
from collections.abc import Sequence
from pathlib import Path

from rebar_data.outputs import replace_file
from rebar_data.perception.evaluation.gate import (
    BOOTSTRAP_REPLICATES,
    FIGURES,
    GATE_NAME,
    RUNTIME,
    build_gate_set,
    read_reference,
    reference,
)
from rebar_data.perception.inference.detector import SHIPPED_MODEL, Detector


def write_reference(
    model: str | Path | None = None,
    *,
    out: str | Path | None = None,
    data_root: str | Path | None = None,
    replicates: int = BOOTSTRAP_REPLICATES,
) -> Path:
    """Measure ``model`` (None: the shipped one) on the gate set, found or built in ``data_root`` (None: a
    temporary folder), and write :func:`reference` to ``out`` (None: ``gate.json`` beside the model)."""
    detector = Detector.load(model, runtime=RUNTIME)
    out = Path(out) if out is not None else detector.path.with_name(GATE_NAME)
    with tempfile.TemporaryDirectory(prefix="rebar-gate-") as tmp:
        root = build_gate_set(data_root if data_root is not None else tmp)
        ref = reference(detector, root, replicates=replicates)
    return replace_file(out, lambda tmp: tmp.write_text(json.dumps(ref, indent=1, sort_keys=True) + "\n"))


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        prog="python -m rebar_data.perception.training.gate_reference",
        description="Measure a model on the regression gate's set and write its reference (gate.json).",
    )
    parser.add_argument("--model", help="model file (default: the shipped model)")
    parser.add_argument("--out", help="JSON to write (default: gate.json beside the model)")
    parser.add_argument("--data", help="folder the gate set is built in, or found (default: a temporary one)")
    args = parser.parse_args(argv)
    path = write_reference(args.model or SHIPPED_MODEL, out=args.out, data_root=args.data)
    ref = read_reference(path)
    for mode, entry in ref["modes"].items():
        parts = [f"{f} {entry['figures'][f]:.4f} (margin {entry['margin'][f]:.4f})" for f in FIGURES]
        print(f"{mode}: " + ", ".join(parts))
    print(path)


if __name__ == "__main__":
    main()
