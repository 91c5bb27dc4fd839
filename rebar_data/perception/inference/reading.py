"""How the detector's stages read an image: ``Detector.reading`` (``Detector.load(..., reading=)``,
``rebar detect --reading``, a servo suite's ``detector_reading``).

- ``"mirrored"`` (``Detector.load``'s default): the first stage reads the image and its mirror image (turned
  left for right, the camera's principal point mirrored with it, so each cell's viewing ray turns too) and
  each output cell is the mean of the two readings; the second stage then reads every pass in its int8
  copy (where the model has one) and its later passes in :data:`MIRRORED_LATER_VIEWS` view.
- ``"single"``: the first stage reads the image once; the second stage's first pass reads the float file and
  its later passes the int8 copy in the file's ``views``: the reading before there was a choice, and what a
  network in memory (training) reads.

Why: the first stage's readings of a frame and of its mirror err apart, and their mean ranks the crossings
above the places where a top bar passes in front of a lower mat's bar more often. Measured on the shipped
model, RGB only (recall at precision 0.99, single / mirrored): crossval-planar 0.916 / 0.940, crossval-tunnel
0.870 / 0.915, cycles-train-planar-e 0.849 / 0.877, cycles-train-tunnel-e 0.876 / 0.894, paper-tunnel test
0.959 / 0.970 (the README's detector section has every figure). The second reading costs the first stage's
time again; the int8 first pass and the later passes' single view pay for most of it (alone, each cost
accuracy in the single reading: the int8 first pass recall at precision 0.99 0.876 to 0.853 on
cycles-train-tunnel-e; with the mirror they moved every figure by under 0.01).
"""

from __future__ import annotations

from typing import Literal, get_args

import numpy as np

from rebar_data.errors import ConfigError

Reading = Literal["mirrored", "single"]
READINGS: tuple[str, ...] = get_args(Reading)
# the views the second stage's later passes read in the mirrored reading (the single one: the file's)
MIRRORED_LATER_VIEWS = 1


def check_reading(reading: str) -> str:
    """``reading`` if it names one of :data:`READINGS`; ConfigError otherwise."""
    if reading not in READINGS:
        raise ConfigError(f"reading = {reading!r} is not accepted; accepted: one of {', '.join(READINGS)}")
    return reading


def mirrored_camera(
    camera: tuple[float, float, float, float], width: int
) -> tuple[float, float, float, float]:
    """The intrinsics of an image ``width`` pixels wide turned left for right: the principal point mirrored
    (COCO corner origin: u becomes ``width`` - u)."""
    fx, fy, cx, cy = camera
    return fx, fy, width - cx, cy


def mean_with_mirror(out: np.ndarray, mirrored: np.ndarray) -> np.ndarray:
    """The mean of the first stage's output ``out`` (3, H, W: heatmap logit, column and row offsets) and its
    output for the mirror image ``mirrored``, already turned back cell for cell: a column offset read in the
    mirror image points the other way."""
    mean = 0.5 * (out + mirrored)
    mean[1] = 0.5 * (out[1] - mirrored[1])
    return mean
