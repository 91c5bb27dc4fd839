"""The lighting kit's physics: colour temperature to RGB, and a scene's lights as renderer-ready specs.

Lights are sampled as the illuminance each gives at the mat's centre (what a site photographer would
meter) and placed in the mat's frame. :func:`light_specs` turns them into world-space lights in
Filament's units (lux for the sun, lumens for point and spot lights) and scales all of them together so
the mat's centre receives ``exposure_lux``, as a camera's auto-exposure would: the 8-bit linear image the
renderer reads back then uses its range well whatever the lights.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

# lux that one unit of Filament's indirect-light intensity gives an upward-facing surface, per bundled
# environment (measured with a matte grey plane against a sun of known illuminance)
ENVIRONMENT_LUX_PER_UNIT = {
    "default": 3.05,
    "brightday": 1.68,
    "crossroads": 5.42,
    "hall": 2.16,
    "konzerthaus": 3.36,
    "nightlights": 1.88,
    "park": 8.8,
    "park2": 1.59,
    "pillars": 1.05,
    "streetlamp": 1.71,
}

_SRGB_FROM_XYZ = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])


def kelvin_to_rgb(temperature_k: float) -> np.ndarray:
    """Linear-sRGB colour (max channel 1) of a black body at ``temperature_k`` (1667-25000 K).

    Planckian locus chromaticity by Kim et al.'s cubic fit, then XYZ to linear sRGB.
    """
    t = float(np.clip(temperature_k, 1667.0, 25000.0))
    if t <= 4000.0:
        x = -0.2661239e9 / t**3 - 0.2343589e6 / t**2 + 0.8776956e3 / t + 0.179910
    else:
        x = -3.0258469e9 / t**3 + 2.1070379e6 / t**2 + 0.2226347e3 / t + 0.240390
    if t <= 2222.0:
        y = -1.1063814 * x**3 - 1.34811020 * x**2 + 2.18555832 * x - 0.20219683
    elif t <= 4000.0:
        y = -0.9549476 * x**3 - 1.37418593 * x**2 + 2.09137015 * x - 0.16748867
    else:
        y = 3.0817580 * x**3 - 5.87338670 * x**2 + 3.75112997 * x - 0.37001483
    xyz = np.array([x / y, 1.0, (1.0 - x - y) / y])
    rgb = np.clip(_SRGB_FROM_XYZ @ xyz, 0.0, None)
    return rgb / rgb.max()


@dataclass(frozen=True)
class LightSpec:
    """One renderer light in world coordinates and Filament units."""

    name: str
    kind: str  # "sun" | "point" | "spot"
    colour: np.ndarray  # linear RGB, max 1
    intensity: float  # lux (sun) or lumens (point, spot)
    position: np.ndarray  # world (unused for the sun)
    direction: np.ndarray  # world unit vector the light travels along (unused for points)
    inner_cone_rad: float = 0.0  # spot half-angles
    outer_cone_rad: float = 0.0
    falloff_m: float = 100.0
    shadows: bool = False


def direction_in_frame(azimuth_deg: float, elevation_deg: float, t_a, t_b, n) -> np.ndarray:
    """Unit vector from the mat towards a light at ``azimuth``/``elevation`` in the frame (t_a, t_b, n)."""
    az, el = np.radians(azimuth_deg), np.radians(elevation_deg)
    v = np.cos(el) * (np.cos(az) * t_a + np.sin(az) * t_b) + np.sin(el) * n
    return v / np.linalg.norm(v)


def light_specs(scene, frame: tuple[np.ndarray, ...]) -> tuple[list[LightSpec], float, float]:
    """World lights of ``scene`` (a SceneSample) for the mat frame ``(centre, t_a, t_b, n)``.

    Returns the lights, the indirect light's Filament intensity, and the common scale applied to every
    light (Filament units per sampled unit), so the mat's centre gets ``scene.exposure_lux``.
    """
    centre, t_a, t_b, n = frame
    on_mat = 0.0  # estimated illuminance on the mat's centre, sampled units
    unscaled: list[LightSpec] = []
    for i, light in enumerate([scene.sun, *scene.lamps]):
        if light.kind == "none":
            continue
        to_light = direction_in_frame(light.azimuth_deg, light.elevation_deg, t_a, t_b, n)
        on_mat += light.illuminance_lux * max(float(np.dot(to_light, n)), 0.0)
        colour = kelvin_to_rgb(light.temperature_k)
        shadows = bool(scene.shadows and light.shadows)
        name = f"light{i}"
        pos = centre + light.distance_m * to_light
        if light.kind == "sun":
            unscaled.append(
                LightSpec(name, "sun", colour, light.illuminance_lux, pos, -to_light, shadows=shadows)
            )
        elif light.kind == "point":
            flux = light.illuminance_lux * 4.0 * np.pi * light.distance_m**2  # intensity (cd) = flux / 4 pi
            unscaled.append(LightSpec(name, "point", colour, flux, pos, -to_light, shadows=shadows))
        else:
            unscaled.extend(_spots(name, light, colour, pos, centre, shadows))
    on_mat += scene.ambient.illuminance_lux
    scale = scene.exposure_lux / max(on_mat, 1e-6)
    lights = [replace(s, intensity=s.intensity * scale) for s in unscaled]
    ibl = scene.ambient.illuminance_lux * scale / ENVIRONMENT_LUX_PER_UNIT[scene.ambient.environment]
    return lights, float(ibl), float(scale)


def _spots(name: str, light, colour: np.ndarray, pos: np.ndarray, centre: np.ndarray, shadows: bool):
    """A spot light, or an area light's grid of spots (only its first spot casts shadows)."""
    axis = centre - pos
    dist = float(np.linalg.norm(axis))
    axis /= dist
    flux = light.illuminance_lux * np.pi * dist**2  # Filament's spot: intensity (cd) = flux / pi
    if light.kind == "spot":
        outer = np.radians(light.cone_deg) / 2.0
        return [LightSpec(name, "spot", colour, flux, pos, axis, 0.7 * outer, outer, 100.0, shadows)]
    inner, outer = np.radians(30.0), np.radians(75.0)  # a panel lights its whole half-space
    helper = np.array([0.0, 0.0, 1.0]) if abs(axis[2]) < 0.9 else np.array([1.0, 0.0, 0.0])
    u = np.cross(axis, helper)
    u /= np.linalg.norm(u)
    v = np.cross(axis, u)
    g = light.grid
    offsets = (np.arange(g) - (g - 1) / 2.0) / max(g, 1) * light.size_m
    out = []
    for k, (du, dv) in enumerate((du, dv) for du in offsets for dv in offsets):
        p = pos + du * u + dv * v
        d = centre - p
        d /= np.linalg.norm(d)
        out.append(
            LightSpec(
                f"{name}_{k}", "spot", colour, flux / g**2, p, d, inner, outer, 100.0, shadows and k == 0
            )
        )
    return out
