"""A photograph's camera, read from its file's EXIF: the intrinsics `rebar detect IMAGES` reads a photograph
with when ``--camera`` gives none.

A camera records its lens's focal length as the 35 mm film equivalent (EXIF ``FocalLengthIn35mmFilm``, tag
0xA405): the focal length that gives a 36 x 24 mm frame (diagonal 43.27 mm) the same field of view across
the diagonal (CIPA DC-008). So fx = fy = f35 x the image's diagonal in pixels / 43.27 mm, whatever the
image's size or the sensor's, and the principal point is taken at the image's centre. A file without the
tag, with 0 there (the standard's "unknown") or with a value no lens has (:data:`PLAUSIBLE_35MM`), gives
None: the detector then assumes the training camera's field of view (``Detector.default_camera``).

Why it matters: the detector reads a frame at the focal length it trained at and gives each output cell
its viewing ray (:mod:`~rebar_data.perception.inference.image`). The training camera (525 px across 640, the Kinect v1)
is a 28 mm equivalent. A phone's main camera (24-26 mm) lies within the 15% the detector reads as it
comes, but its ultra-wide (13 mm) shows a bar at half the size the field-of-view guess expects and a
telephoto (70-77 mm) at 2.5 times. Bars twice the trained size (the cross-renderer sets enlarged twice,
read without resampling) kept 0.727 and 0.470 of their crossings at precision 0.99, against 0.925 and
0.889 brought to the trained scale (the focal module's figures). The EXIF tag stores whole millimetres,
so the focal length it gives is within about 2% at 25 mm and better above.

OpenCV's ``imread`` turns an image by its EXIF orientation as it reads it (``read_image``); the diagonal
and the centre are those of the image as read, so the intrinsics fit the turned image. A photograph resized
after it was taken keeps the tag's meaning (the diagonal shrinks with the focal length in pixels); one
cropped keeps the tag but not the field of view it describes, and needs its intrinsics given.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

# the diagonal of a 36 x 24 mm frame, which the 35 mm equivalent focal length refers to
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
EXIF_IFD = 0x8769  # the Exif sub-IFD, where the camera settings are
FOCAL_LENGTH_35MM = 0xA405
# 35 mm equivalents a camera lens has (a phone's ultra-wide 13 mm, the longest telephotos 2000 mm); a value
# outside is a corrupt tag, and reading a photograph with it would find nothing
PLAUSIBLE_35MM = (4.0, 3000.0)


@dataclass(frozen=True)
class PhotoCamera:
    """The intrinsics a photograph's EXIF implies: ``camera`` (fx, fy, cx, cy) in pixels, COCO corner origin,
    from its 35 mm equivalent focal length ``focal_35mm``."""

    camera: tuple[float, float, float, float]
    focal_35mm: float


def focal_35mm(path: str | Path) -> float | None:
    """The 35 mm equivalent focal length (mm) a photograph's EXIF records; None where it records none (or
    0), one outside :data:`PLAUSIBLE_35MM`, or the file cannot be opened as an image."""
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:  # reads the header and metadata, not the pixels
            value = im.getexif().get_ifd(EXIF_IFD).get(FOCAL_LENGTH_35MM)
    except (OSError, UnidentifiedImageError, ValueError):
        return None
    try:
        mm = float(value)
    except (TypeError, ValueError):
        return None
    return mm if PLAUSIBLE_35MM[0] <= mm <= PLAUSIBLE_35MM[1] else None


def photo_camera(path: str | Path, height: int, width: int) -> PhotoCamera | None:
    """The intrinsics of the photograph at ``path``, read as a ``height`` x ``width`` image, from its EXIF
    35 mm equivalent focal length (the module's text); None where the file records none."""
    mm = focal_35mm(path)
    if mm is None:
        return None
    f = mm * math.hypot(width, height) / FULL_FRAME_DIAGONAL_MM
    return PhotoCamera((f, f, width / 2.0, height / 2.0), mm)
