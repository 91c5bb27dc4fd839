"""The user's own texture maps: find the sets in a folder (Poly Haven and ambientCG naming) and load them.

A set is the maps of one material: an albedo map (required) and optionally roughness, metallic, a
combined AO/roughness/metal map (``_arm``) and a normal map (OpenGL convention, or DirectX with its
green channel flipped on load). Files are grouped into sets by their name with the map and resolution
tokens removed, so ``rusty_metal_diff_1k.jpg`` and ``rusty_metal_rough_1k.jpg`` form one set.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

TEXTURE_SUFFIXES = (".png", ".jpg", ".jpeg", ".tif", ".tiff", ".bmp", ".webp")

# last token (or two tokens) of a file name -> map kind
_MAP_TOKENS: dict[tuple[str, ...], str] = {
    ("nor", "gl"): "normal",
    ("nor", "dx"): "normal_dx",
    ("normal", "gl"): "normal",
    ("normal", "dx"): "normal_dx",
    ("normalgl",): "normal",
    ("normaldx",): "normal_dx",
    ("normal",): "normal",
    ("nrm",): "normal",
    ("nor",): "normal",
    ("base", "color"): "albedo",
    ("base", "colour"): "albedo",
    ("basecolor",): "albedo",
    ("basecolour",): "albedo",
    ("albedo",): "albedo",
    ("diff",): "albedo",
    ("diffuse",): "albedo",
    ("color",): "albedo",
    ("colour",): "albedo",
    ("col",): "albedo",
    ("rough",): "roughness",
    ("roughness",): "roughness",
    ("metal",): "metallic",
    ("metallic",): "metallic",
    ("metalness",): "metallic",
    ("arm",): "arm",
}
_NOISE_TOKEN = re.compile(r"^(\d+k|jpg|png|exr|tif|tiff)$")


@dataclass(frozen=True)
class TextureSet:
    """Paths of one material's maps (albedo always present)."""

    name: str
    albedo: Path
    roughness: Path | None = None
    metallic: Path | None = None
    arm: Path | None = None
    normal: Path | None = None
    normal_is_directx: bool = False


def _classify(stem: str) -> tuple[str, str] | None:
    """(map kind, set key) of a file name stem, or None when it names no known map.

    The map's name is the last token that is not a resolution or format (``_diff_1k``, ``_1K-JPG_Color``).
    """
    tokens = [t for t in re.split(r"[^a-z0-9]+", stem.lower()) if t]
    meaningful = [i for i, t in enumerate(tokens) if not _NOISE_TOKEN.match(t)]
    if not meaningful:
        return None
    end = meaningful[-1] + 1
    for n in (2, 1):
        pattern = tuple(tokens[max(0, end - n) : end])
        if len(pattern) == n and pattern in _MAP_TOKENS:
            rest = tokens[: end - n] + tokens[end:]
            key = "_".join(t for t in rest if not _NOISE_TOKEN.match(t)) or "texture"
            return _MAP_TOKENS[pattern], key
    return None


def find_texture_sets(folder: str | Path) -> list[TextureSet]:
    """Every texture set in ``folder`` (not recursive) that has an albedo map, sorted by name."""
    folder = Path(folder)
    groups: dict[str, dict[str, Path]] = {}
    for p in sorted(folder.iterdir()):
        if p.suffix.lower() not in TEXTURE_SUFFIXES or not p.is_file():
            continue
        found = _classify(p.stem)
        if found is None:
            continue
        kind, key = found
        groups.setdefault(key, {}).setdefault(kind, p)
    sets = []
    for key, maps in sorted(groups.items()):
        if "albedo" not in maps:
            continue
        normal = maps.get("normal") or maps.get("normal_dx")
        sets.append(
            TextureSet(
                name=f"{folder.name}/{key}",
                albedo=maps["albedo"],
                roughness=maps.get("roughness"),
                metallic=maps.get("metallic"),
                arm=maps.get("arm"),
                normal=normal,
                normal_is_directx=normal is not None and "normal" not in maps,
            )
        )
    return sets


@lru_cache(maxsize=32)
def load_texture_set(ts: TextureSet, size_px: int) -> dict[str, np.ndarray]:
    """The set's maps as arrays of ``size_px`` square: albedo (sRGB RGB uint8), roughness and metallic
    (uint8, absent when the set has none) and normal (RGB uint8, OpenGL convention)."""
    out = {"albedo": _read(ts.albedo, size_px, colour=True)}
    if ts.arm is not None:
        arm = _read(ts.arm, size_px, colour=True)
        out["roughness"] = np.ascontiguousarray(arm[..., 1])
        out["metallic"] = np.ascontiguousarray(arm[..., 2])
    if ts.roughness is not None:
        out["roughness"] = _read(ts.roughness, size_px, colour=False)
    if ts.metallic is not None:
        out["metallic"] = _read(ts.metallic, size_px, colour=False)
    if ts.normal is not None:
        n = _read(ts.normal, size_px, colour=True)
        if ts.normal_is_directx:
            n = n.copy()
            n[..., 1] = 255 - n[..., 1]
        out["normal"] = n
    return out


def _read(path: Path, size_px: int, *, colour: bool) -> np.ndarray:
    import cv2

    from rebar_data.config import ConfigError

    img = cv2.imread(str(path), cv2.IMREAD_COLOR if colour else cv2.IMREAD_GRAYSCALE)
    if img is None:
        raise ConfigError(f"{path}: cannot be read as an image; accepted: PNG, JPEG or TIFF texture maps")
    if img.dtype != np.uint8:
        img = (img / np.iinfo(img.dtype).max * 255).astype(np.uint8)
    img = cv2.resize(img, (size_px, size_px), interpolation=cv2.INTER_AREA)
    if colour:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2RGB)
    return np.ascontiguousarray(img)
