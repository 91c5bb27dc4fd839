"""Seconds spent in named stages, summed over calls: how the benches break a frame's time down."""

from __future__ import annotations

import time
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager


class StageTimer:
    """Sums wall-clock seconds per stage name; one clock read at each end of a stage, so it stays on."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        t0 = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] += time.perf_counter() - t0
            self.calls[name] += 1

    def totals(self) -> dict[str, tuple[float, int]]:
        """``{stage: (seconds, calls)}``, a plain dict that pickles across processes."""
        return {k: (self.seconds[k], self.calls[k]) for k in self.seconds}


# the vector extensions ONNX Runtime's CPU kernels choose by, widest last (int8 convolutions run fast
# only with VNNI): a latency figure means little without them
VECTOR_EXTENSIONS = (("avx", "AVX"), ("fma", "FMA"), ("avx2", "AVX2"), ("avx512f", "AVX-512"))
_VNNI = ("avx512_vnni", "avx_vnni")


def machine_description(cpuinfo: str | None = None) -> str:
    """The CPU a timing ran on, as a bench line states it: its model, cores and vector extensions, e.g.
    "2 cores, AMD EPYC, AVX and FMA, no AVX2". ``cpuinfo`` is /proc/cpuinfo's text (read when None;
    where there is none, as off Linux, only the core count)."""
    import os

    cores = f"{os.cpu_count() or 1} cores"
    if cpuinfo is None:
        try:
            with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
                cpuinfo = f.read()
        except OSError:
            return cores
    fields: dict[str, str] = {}
    for line in cpuinfo.splitlines():
        key, sep, value = line.partition(":")
        if sep and key.strip() not in fields:  # the first processor's entry speaks for all
            fields[key.strip()] = value.strip()
    parts = [cores] + ([fields["model name"]] if "model name" in fields else [])
    if "flags" in fields:
        flags = set(fields["flags"].split())
        have = [name for flag, name in VECTOR_EXTENSIONS if flag in flags]
        have += ["VNNI"] if flags & set(_VNNI) else []
        lacking = [name for flag, name in VECTOR_EXTENSIONS if flag not in flags]
        parts.append(f"{', '.join(have[:-1])} and {have[-1]}" if len(have) > 1 else (have or ["no AVX"])[0])
        if lacking and have:
            parts.append(f"no {lacking[0]}")  # the narrowest missing one says where the machine stops
    return ", ".join(parts)
