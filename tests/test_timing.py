"""The machine line every benchmark figure is printed under."""

from __future__ import annotations

import os

from rebar_data.timing import machine_description

CORES = f"{os.cpu_count() or 1} cores"


def test_names_the_model_and_the_widest_extensions_present():
    info = (
        "processor\t: 0\nmodel name\t: Some CPU\nflags\t\t: fpu sse2 avx fma avx2 avx512f avx512_vnni\n\n"
        "processor\t: 1\nmodel name\t: Other\nflags\t\t: fpu\n"
    )
    assert machine_description(info) == f"{CORES}, Some CPU, AVX, FMA, AVX2, AVX-512 and VNNI"


def test_says_the_narrowest_extension_missing():
    info = "model name : Old CPU\nflags : sse2 avx fma\n"
    assert machine_description(info) == f"{CORES}, Old CPU, AVX and FMA, no AVX2"
    assert machine_description("model name : Older\nflags : sse2\n") == f"{CORES}, Older, no AVX"


def test_without_flags_gives_what_it_has():
    assert machine_description("model name : Some CPU\n") == f"{CORES}, Some CPU"
    assert machine_description("") == CORES


def test_reads_this_machine():
    assert machine_description().startswith(CORES)
