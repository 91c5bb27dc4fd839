"""A photograph's camera from its EXIF 35 mm equivalent focal length (tag 0xA405): the intrinsics
`rebar detect IMAGES` reads a photograph with when ``--camera`` gives none.

fx = fy = f35 x the image's diagonal in pixels / 43.27 mm (the 36 x 24 mm frame's diagonal), the principal
point at the image's centre; no tag, 0 or an implausible value (:data:`PLAUSIBLE_35MM`) gives None. Why it
matters, with figures: ``docs/detector/experiments.md``, the photo module text."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

# the diagonal of a 36 x 24 mm frame, which the 35 mm equivalent focal length refers to
FULL_FRAME_DIAGONAL_MM = math.hypot(36.0, 24.0)
EXIF_IFD = 0x8769  # the Exif sub-IFD, where the camera settings are
FOCAL_LENGTH_35MM = 0xA405
# the 35 mm equivalents lenses have (13 mm phone ultra-wides to 2000 mm telephotos); outside: a corrupt tag
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
