"""Procedural PBR texture maps for rebar and ground surfaces, generated from seeded noise and cached.

All maps tile seamlessly (noise is synthesised in the Fourier domain, so it is periodic). Maps are
square arrays: ``albedo`` (sRGB, uint8 RGB), ``roughness`` and ``metallic`` (uint8) and ``normal``
(tangent space, OpenGL convention, uint8 RGB).

The expensive part, the noise fields of one pattern ``variant`` at one size, is cached in memory and on
disk (``~/.cache/rebar-servo/textures`` unless told otherwise), so it is paid once per machine; mixing
them into a scene's rebar look (rust, pitting, mill scale, dust, wear, colour) is a few array operations.
"""

from __future__ import annotations

import hashlib
import os
from collections import OrderedDict
from pathlib import Path

import numpy as np
from scipy.special import ndtri

TEXTURE_VERSION = 2  # bump when generation changes, so stale cache files are not reused
DEFAULT_CACHE = Path("~/.cache/rebar-servo/textures")

Maps = dict[str, np.ndarray]


# --- noise --------------------------------------------------------------------------------------------


def periodic_noise(
    size: int, rng: np.random.Generator, *, beta: float, stretch: tuple[float, float] = (1.0, 1.0)
) -> np.ndarray:
    """Tileable noise with power spectrum ~ 1/f^beta, zero mean and unit standard deviation.

    ``stretch`` is (along y, along x), y being the row index: a larger value makes features longer in
    that direction, e.g. ``(0.25, 4.0)`` gives horizontal streaks.
    """
    white = rng.standard_normal((size, size)).astype(np.float32)
    spec = np.fft.rfft2(white)
    fy = np.fft.fftfreq(size)[:, None] * stretch[0]
    fx = np.fft.rfftfreq(size)[None, :] * stretch[1]
    f = np.sqrt(fx**2 + fy**2)
    f[0, 0] = np.inf
    spec *= f ** (-beta / 2.0)
    out = np.fft.irfft2(spec, s=(size, size)).astype(np.float32)
    out -= out.mean()
    return out / max(float(out.std()), 1e-12)


def _smoothstep(x: np.ndarray, lo: float, hi: float) -> np.ndarray:
    t = np.clip((x - lo) / max(hi - lo, 1e-6), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _coverage(field: np.ndarray, fraction: float, softness: float = 0.25) -> np.ndarray:
    """Mask in [0, 1] covering about ``fraction`` of a unit-normal field, with soft edges."""
    if fraction <= 0.0:
        return np.zeros_like(field)
    if fraction >= 1.0:
        return np.ones_like(field)
    t = float(ndtri(1.0 - fraction))
    return _smoothstep(field, t - softness, t + softness)


def _voronoi(size: int, rng: np.random.Generator, n_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """Periodic Voronoi: per pixel, the cell index and the gap between the two nearest seeds (pixels)."""
    from scipy.spatial import cKDTree

    seeds = rng.uniform(0, size, (n_cells, 2))
    shifts = np.array([(dy, dx) for dy in (-size, 0, size) for dx in (-size, 0, size)], float)
    tiled = (seeds[None, :, :] + shifts[:, None, :]).reshape(-1, 2)
    yy, xx = np.mgrid[0:size, 0:size]
    pix = np.stack([yy.ravel(), xx.ravel()], 1).astype(float)
    d, i = cKDTree(tiled).query(pix, k=2)
    cell = (i[:, 0] % n_cells).reshape(size, size)
    gap = (d[:, 1] - d[:, 0]).reshape(size, size).astype(np.float32)
    return cell, gap


def normal_map(height: np.ndarray, strength: float) -> np.ndarray:
    """Tangent-space normal map (OpenGL, uint8 RGB) of a periodic height field (height in texels)."""
    gx = (np.roll(height, -1, 1) - np.roll(height, 1, 1)) * 0.5 * strength
    gy = (np.roll(height, -1, 0) - np.roll(height, 1, 0)) * 0.5 * strength
    n = np.stack([-gx, gy, np.ones_like(height)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.clip((n * 0.5 + 0.5) * 255.0 + 0.5, 0, 255).astype(np.uint8)


def _u8(x: np.ndarray) -> np.ndarray:
    return np.clip(x * 255.0 + 0.5, 0, 255).astype(np.uint8)


_SRGB_STEPS = 16384


def _srgb_table() -> np.ndarray:
    x = np.linspace(0.0, 1.0, _SRGB_STEPS)
    s = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1.0 / 2.4) - 0.055)
    return np.clip(np.round(255.0 * s), 0, 255).astype(np.uint8)


_SRGB_LUT = _srgb_table()


def _srgb8(linear: np.ndarray) -> np.ndarray:
    """Linear values in [0, 1] to sRGB-encoded uint8 (through a table: pow() on every texel is slow)."""
    return _SRGB_LUT[np.clip(linear * (_SRGB_STEPS - 1) + 0.5, 0, _SRGB_STEPS - 1).astype(np.int32)]


def _linear(srgb255: tuple[float, float, float]) -> np.ndarray:
    x = np.asarray(srgb255, np.float32) / 255.0
    return np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)


# --- cache --------------------------------------------------------------------------------------------


class TextureCache:
    """Memory (LRU) and disk cache of generated arrays, keyed by name. Disk writes are atomic, so worker
    processes may share one folder."""

    def __init__(self, folder: str | Path | None = None, *, max_items: int = 12):
        self.folder = (
            Path(folder if folder is not None else DEFAULT_CACHE).expanduser() / f"v{TEXTURE_VERSION}"
        )
        self.max_items = max_items
        self._memory: OrderedDict[str, dict[str, np.ndarray]] = OrderedDict()

    def get(self, key: str, make) -> dict[str, np.ndarray]:
        """The arrays stored under ``key``, made with ``make()`` (and stored) when missing."""
        if key in self._memory:
            self._memory.move_to_end(key)
            return self._memory[key]
        path = self.folder / f"{key}.npz"
        arrays = _load_whole(path)
        if arrays is None:  # missing, or damaged (empty, cut short, not ours): made and stored again
            arrays = make()
            self._save(path, arrays)
        self._memory[key] = arrays
        while len(self._memory) > self.max_items:
            self._memory.popitem(last=False)
        return arrays

    def _save(self, path: Path, arrays: dict[str, np.ndarray]) -> None:
        tmp = path.with_name(f".{path.stem}.{os.getpid()}.tmp.npz")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            np.savez(tmp, **arrays)
            tmp.replace(path)
        except OSError:  # a read-only home or a full disk: keep the memory copy only
            tmp.unlink(missing_ok=True)


def _load_whole(path: Path) -> dict[str, np.ndarray] | None:
    """The arrays of a cached ``.npz`` file, or None when it is missing or damaged: a zip archive whose
    every member is read whole (which checks each member's CRC-32), with at least one array in it. A power
    cut's 0-byte or half-written file, or any other file there, is None, so the cache makes it again."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except Exception:  # noqa: BLE001  (EOFError, BadZipFile, zlib.error, ValueError...: all mean damaged)
        return None
    return arrays or None


def _seed(*parts: object) -> int:
    digest = hashlib.sha256(repr(parts).encode()).digest()
    return int.from_bytes(digest[:8], "little")


# --- rebar --------------------------------------------------------------------------------------------

_STEEL = _linear((118, 118, 122))
_MILL_SCALE = _linear((56, 58, 64))
_RUST_LIGHT = _linear((176, 92, 40))
_RUST_DARK = _linear((92, 44, 22))
_PIT = _linear((36, 22, 14))
_DUST = _linear((150, 144, 134))


def rebar_fields(variant: int, size: int) -> dict[str, np.ndarray]:
    """The noise fields behind every rebar look of one pattern ``variant`` (float16, unit normal)."""
    rng = np.random.default_rng(_seed("rebar", variant, size))
    n = lambda beta, stretch=(1.0, 1.0): periodic_noise(size, rng, beta=beta, stretch=stretch)  # noqa: E731
    pits = n(0.6)
    pits = np.clip((pits - 2.0) / 1.2, 0.0, 1.0)  # sparse spots where fine noise peaks
    fields = {
        "rust": n(2.4),
        "rust_detail": n(1.2),
        "flakes": n(1.7),
        "dust": n(2.6),
        "wear": n(1.8, stretch=(0.25, 4.0)),  # streaks along the bar (u, the texture's columns axis)
        "tone": n(3.2),
        "pits": pits,
    }
    return {k: v.astype(np.float16) for k, v in fields.items()}


def rebar_maps(m, fields: dict[str, np.ndarray]) -> Maps:
    """Albedo, roughness, metallic and normal maps of a procedural rebar look (a MaterialSample's
    ``variant``, ``rust``, ``mill_scale``, ``dust``, ``pitting`` and ``wear``; nothing else)."""
    f = {k: v.astype(np.float32) for k, v in fields.items()}
    mill = _coverage(f["flakes"], m.mill_scale, 0.15)[..., None]
    albedo = _STEEL * (1 - mill) + _MILL_SCALE * mill
    rough = 0.45 * (1 - mill[..., 0]) + 0.55 * mill[..., 0]
    metal = 0.8 * (1 - mill[..., 0]) + 0.6 * mill[..., 0]

    rust = _coverage(f["rust"] + 0.35 * f["rust_detail"], m.rust, 0.3)[..., None]
    mix = _smoothstep(f["rust_detail"], -1.5, 1.5)[..., None]
    rust_col = _RUST_DARK * (1 - mix) + _RUST_LIGHT * mix
    albedo = albedo * (1 - rust) + rust_col * rust
    rough = rough * (1 - rust[..., 0]) + 0.9 * rust[..., 0]
    metal = metal * (1 - rust[..., 0])

    pits = (f["pits"] * m.pitting * (0.3 + 0.7 * rust[..., 0]))[..., None]
    albedo = albedo * (1 - pits) + _PIT * pits

    wear = _coverage(f["wear"], m.wear, 0.2)[..., None]
    albedo = albedo * (1 - wear) + _STEEL * 1.1 * wear
    rough = rough * (1 - wear[..., 0]) + 0.3 * wear[..., 0]
    metal = metal * (1 - wear[..., 0]) + 0.9 * wear[..., 0]

    dust = (_coverage(f["dust"], m.dust, 0.6) * 0.6)[..., None]
    albedo = albedo * (1 - dust) + _DUST * dust
    rough = rough * (1 - dust[..., 0]) + 0.95 * dust[..., 0]
    metal = metal * (1 - dust[..., 0])

    albedo = albedo * (1.0 + 0.12 * f["tone"][..., None] * np.array([1.0, 0.85, 0.7], np.float32))
    height = 0.8 * rust[..., 0] * f["rust_detail"] - 4.0 * pits[..., 0] + 0.3 * mill[..., 0] * f["flakes"]
    return {
        "albedo": _srgb8(albedo),
        "roughness": _u8(rough),
        "metallic": _u8(metal),
        "normal": normal_map(height, 1.0),
    }


def bar_tints(m, count: int, rng: np.random.Generator) -> np.ndarray:
    """(count, 3) linear RGB multiplier of each bar of a scene's rebar ``m``: one tint a bar around the
    scene's ``colour_variation`` (a darker bar is a little warmer), scaled so the brightest is 1. Every
    renderer draws them from ``default_rng(m.tint_seed)``, so the same bar gets the same tint in each."""
    k = m.colour_variation * np.clip(rng.normal(0.0, 1.0, (count, 1)), -2.0, 2.0)
    rgb = 1.0 + k * np.array([0.8, 0.9, 1.0])
    return rgb / rgb.max()


def rebar_tint(m) -> np.ndarray:
    """Linear RGB multiplier of a scene's rebar: its hue shift (yellower rust for positive values, redder
    for negative) and brightness, applied on top of the maps so they need no new texture."""
    h = m.hue_shift
    tint = (
        np.array([1.0, 1.0 + 0.3 * h, 1.0 + 0.1 * h])
        if h >= 0
        else np.array([1.0, 1.0 + 0.3 * h, 1.0 + 0.3 * h])
    )
    return (tint / tint.max() * m.brightness).astype(np.float32)


# --- ground -------------------------------------------------------------------------------------------


def ground_maps(kind: str, variant: int, size: int) -> Maps:
    """Maps of a ground surface: ``concrete``, ``soil``, ``plywood`` (formwork) or ``gravel``."""
    rng = np.random.default_rng(_seed("ground", kind, variant, size))
    n = lambda beta, stretch=(1.0, 1.0): periodic_noise(size, rng, beta=beta, stretch=stretch)  # noqa: E731
    return {"concrete": _concrete, "soil": _soil, "plywood": _plywood, "gravel": _gravel}[kind](size, rng, n)


def _concrete(size, rng, n) -> Maps:
    base = _linear(tuple(rng.uniform(135, 165) * np.array([1.0, 0.99, 0.95])))
    stain = n(3.0)
    grain = n(0.9)
    pores = np.clip((n(0.3) - 2.6) / 0.6, 0, 1)
    shade = 1.0 + 0.12 * stain + 0.06 * grain - 0.5 * pores
    albedo = base * shade[..., None]
    rough = np.clip(0.85 + 0.05 * grain, 0, 1)
    height = 0.4 * grain - 3.0 * pores
    return {
        "albedo": _srgb8(albedo),
        "roughness": _u8(rough),
        "metallic": np.zeros((size, size), np.uint8),
        "normal": normal_map(height, 0.6),
    }


def _soil(size, rng, n) -> Maps:
    base = _linear(tuple(rng.uniform(80, 120) * np.array([1.0, 0.78, 0.58])))
    clumps = n(1.8)
    damp = _coverage(n(3.0), 0.35, 0.5)
    grain = n(0.8)
    pebbles = np.clip((n(0.5) - 2.2) / 0.5, 0, 1)
    shade = (1.0 + 0.25 * clumps + 0.1 * grain) * (1.0 - 0.35 * damp)
    albedo = base * shade[..., None]
    albedo = albedo * (1 - pebbles[..., None]) + _linear((150, 140, 125)) * pebbles[..., None]
    rough = np.clip(0.95 - 0.2 * damp, 0, 1)
    height = 1.2 * clumps + 0.5 * grain + 3.0 * pebbles
    return {
        "albedo": _srgb8(albedo),
        "roughness": _u8(rough),
        "metallic": np.zeros((size, size), np.uint8),
        "normal": normal_map(height, 0.5),
    }


def _plywood(size, rng, n) -> Maps:
    base = _linear(tuple(rng.uniform(170, 205) * np.array([1.0, 0.8, 0.55])))
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size
    warp = n(2.5, stretch=(0.25, 2.0))
    rings = np.sin(2 * np.pi * (int(rng.integers(20, 40)) * yy + 0.6 * warp))
    grain = n(1.0, stretch=(0.1, 4.0))
    oil = _coverage(n(3.0), float(rng.uniform(0.1, 0.5)), 0.6)  # form oil and concrete residue
    residue = _coverage(n(2.0), float(rng.uniform(0.0, 0.2)), 0.3)
    shade = 1.0 + 0.12 * rings + 0.06 * grain - 0.25 * oil
    albedo = base * shade[..., None]
    albedo = albedo * (1 - residue[..., None]) + _linear((150, 148, 142)) * residue[..., None]
    seam = (np.minimum(xx, 1 - xx) < 2.0 / size) | (np.minimum(yy, 1 - yy) < 2.0 / size)
    albedo[seam] *= 0.45
    rough = np.clip(0.65 - 0.2 * oil + 0.2 * residue, 0, 1)
    height = 0.3 * rings + 0.2 * grain - 2.0 * seam
    return {
        "albedo": _srgb8(albedo),
        "roughness": _u8(rough),
        "metallic": np.zeros((size, size), np.uint8),
        "normal": normal_map(height, 0.5),
    }


def _gravel(size, rng, n) -> Maps:
    cells = int(size * size / 900)  # stones about 30 texels across
    cell, gap = _voronoi(size, rng, cells)
    grey = rng.uniform(85, 175, cells)[:, None] * rng.uniform(
        [0.97, 0.94, 0.88], [1.03, 1.0, 0.97], (cells, 3)
    )
    palette = np.stack([_linear(tuple(c)) for c in grey])
    tone = rng.uniform(0.8, 1.15, cells).astype(np.float32)
    albedo = palette[cell] * tone[cell][..., None]
    edge = _smoothstep(gap, 0.0, 5.0)
    speck = n(0.5)
    albedo = albedo * (0.45 + 0.55 * edge)[..., None] * (1.0 + 0.15 * speck)[..., None]
    rough = np.clip(0.75 + 0.15 * (1 - edge), 0, 1)
    height = 6.0 * np.sqrt(np.clip(gap, 0, 12) / 12.0) + 0.3 * speck
    return {
        "albedo": _srgb8(albedo),
        "roughness": _u8(rough),
        "metallic": np.zeros((size, size), np.uint8),
        "normal": normal_map(height, 0.6),
    }
