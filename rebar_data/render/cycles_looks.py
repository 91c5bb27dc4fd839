"""What a Cycles frame looks like: a scene's look drawn from its sample, and its Blender node graphs.

The Cycles renderer shows what the Open3D renderer cannot show well: light bouncing between bars and
off the ground, glossy bare steel, rust, mill scale and epoxy coating, wet and dry grounds, and sky
light at noon, at dusk and under cloud. :func:`draw_look` draws those choices from a generator seeded
by the scene sample (the same sample gives the same look), taking what the sample already says where
it says it (rust level, hue, ground kind and brightness, lamps, shadow softness). Every texture is
procedural (Blender's noise, Voronoi and wave textures on Principled BSDF materials): nothing is
downloaded.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from rebar_data.scene.sample import SceneSample

FINISHES = ("bright", "rust", "mill_scale", "epoxy")
GROUNDS = ("concrete", "soil", "wood", "gravel")
SKIES = ("noon", "dusk", "overcast")

# Irradiance on an upward-facing surface from Blender's Nishita sky (sun disc off, strength 1, default
# air, dust and ozone), by sun elevation in degrees: luminance of a white diffuse plane's render times pi.
SKY_ELEVATION_DEG = np.array([3.0, 10.0, 30.0, 70.0])
SKY_IRRADIANCE = np.array([2.82, 5.57, 8.31, 9.6])
# the same for the overcast sky below (radiance 1 at the zenith, 0.55 at the horizon): about 0.92 pi
OVERCAST_IRRADIANCE = 2.9

LOOK_STREAM = 0x6379636C  # mixes the scene's seeds into a stream of its own, apart from the tint's


@dataclass(frozen=True)
class CyclesLook:
    """Everything a Cycles scene adds to its scene sample. Light is in lux on the mat (only ratios count:
    the renderer scales every light together, as auto-exposure would)."""

    finish: str  # bright | rust | mill_scale | epoxy
    rust_coverage: float  # share of the bar surface rusted (epoxy: damaged)
    steel_rgb: tuple[float, float, float]  # linear base colour of the bare or coated surface
    steel_metallic: float
    steel_roughness: float
    rust_dark_rgb: tuple[float, float, float]
    rust_light_rgb: tuple[float, float, float]
    pattern_scale: float  # rust blotches per metre
    bump: float  # relief strength of bars
    ground: str  # concrete | soil | wood | gravel
    ground_rgb: tuple[float, float, float]
    wet: bool
    puddles: float  # share of a wet ground under standing water
    sky: str  # noon | dusk | overcast
    sun_azimuth_deg: float  # in the mat's frame, as the scene's lights
    sun_elevation_deg: float
    sun_angle_deg: float  # the sun's angular diameter: shadow softness
    sun_temperature_k: float
    sun_lux: float  # on a surface facing the sun
    sky_lux: float  # what the sky alone gives the mat
    haze: float  # the sky's dust density
    texture_offset: tuple[float, float, float]  # moves every procedural pattern, metres


def _rgb(x) -> tuple[float, float, float]:
    return tuple(float(c) for c in np.clip(x, 0.0, 1.0))


def draw_look(scene: SceneSample) -> CyclesLook:
    """The scene's Cycles look: every choice from one generator seeded by the sample's seeds, drawn in a
    fixed order whatever is chosen."""
    rng = np.random.default_rng([scene.rebar.tint_seed, scene.distractors.seed, LOOK_STREAM])
    r = scene.rebar
    finish = FINISHES[int(rng.choice(4, p=[0.2, 0.35, 0.25, 0.2]))]
    u = rng.uniform(0.0, 1.0, 12)
    hue = r.hue_shift  # + yellow-brown, - red-brown
    rust_light = np.array([0.36 + 0.06 * hue, 0.13 + 0.05 * hue, 0.045]) * r.brightness
    rust_dark = np.array([0.10, 0.037 + 0.01 * hue, 0.018]) * r.brightness
    coverage = {
        "bright": 0.12 * u[0],
        "rust": r.rust,
        "mill_scale": 0.35 * r.rust,
        "epoxy": 0.01 + 0.07 * u[0],
    }[finish]
    steel = {
        "bright": (np.array([0.56, 0.57, 0.58]) * (0.85 + 0.2 * u[1]), 1.0, 0.12 + 0.22 * u[2]),
        "rust": (np.array([0.22, 0.21, 0.2]) * (0.8 + 0.4 * u[1]), 0.85, 0.35 + 0.2 * u[2]),
        "mill_scale": (np.array([0.075, 0.08, 0.09]) * (0.8 + 0.6 * u[1]), 0.7, 0.3 + 0.25 * u[2]),
        # fusion-bonded epoxy: the usual green, from olive to bluish
        "epoxy": (
            np.array([0.02 + 0.04 * u[1], 0.1 + 0.1 * u[3], 0.03 + 0.06 * u[4]]),
            0.0,
            0.22 + 0.25 * u[2],
        ),
    }[finish]
    g = scene.ground
    ground = {"concrete": "concrete", "soil": "soil", "plywood": "wood", "gravel": "gravel"}.get(
        g.kind, "concrete"
    )
    base = {
        "concrete": [0.42, 0.41, 0.39],
        "soil": [0.16, 0.11, 0.07],
        "wood": [0.5, 0.32, 0.17] if u[5] < 0.6 else [0.16, 0.07, 0.045],  # pine or film-faced formwork
        "gravel": [0.35, 0.33, 0.3],
    }[ground]
    wet = bool(u[6] < (0.0 if ground == "wood" else 0.35))
    ground_rgb = np.array(base) * (0.6 + 0.7 * g.brightness)
    sky = SKIES[int(rng.integers(3))]
    elevation = {"noon": 40.0 + 40.0 * u[7], "dusk": 3.0 + 10.0 * u[7], "overcast": 35.0 + 40.0 * u[7]}[sky]
    sun_lux = {"noon": 60_000 + 40_000 * u[8], "dusk": 3_000 + 9_000 * u[8], "overcast": 4_000 * u[8]}[sky]
    sun_on_mat = sun_lux * np.sin(np.radians(elevation))
    sky_lux = {
        "noon": (0.15 + 0.25 * u[10]) * sun_on_mat,
        "dusk": (0.6 + 1.2 * u[10]) * sun_on_mat,
        "overcast": 8_000.0 + 12_000.0 * u[10],
    }[sky]
    return CyclesLook(
        finish=finish,
        rust_coverage=float(coverage),
        steel_rgb=_rgb(steel[0]),
        steel_metallic=float(steel[1]),
        steel_roughness=float(steel[2] * r.roughness_scale * (0.6 if wet else 1.0)),
        rust_dark_rgb=_rgb(rust_dark),
        rust_light_rgb=_rgb(rust_light),
        pattern_scale=float(20.0 + 40.0 * u[9]),
        bump=float(0.15 + 0.35 * r.pitting * (1.0 if finish == "rust" else 0.4)),
        ground=ground,
        ground_rgb=_rgb(ground_rgb * (0.4 if wet else 1.0)),
        wet=wet,
        puddles=float(0.2 + 0.5 * u[10]) if wet else 0.0,
        sky=sky,
        sun_azimuth_deg=float(scene.sun.azimuth_deg if scene.sun.kind == "sun" else 360.0 * u[11]),
        sun_elevation_deg=float(elevation),
        sun_angle_deg=float(0.5 + 3.0 * scene.shadow_softness if sky != "overcast" else 30.0),
        sun_temperature_k=float(
            {"noon": 5800.0, "dusk": 3000.0, "overcast": 6500.0}[sky] + 600 * (u[8] - 0.5)
        ),
        sun_lux=float(sun_lux),
        sky_lux=float(sky_lux),
        haze=float({"noon": 1.0, "dusk": 2.0, "overcast": 4.0}[sky] * (0.5 + u[9])),
        texture_offset=tuple(float(x) for x in rng.uniform(-50.0, 50.0, 3)),
    )


def sky_irradiance(look: CyclesLook) -> float:
    """Irradiance an upward-facing surface gets from the look's sky at strength 1."""
    if look.sky == "overcast":
        return OVERCAST_IRRADIANCE
    return float(np.interp(look.sun_elevation_deg, SKY_ELEVATION_DEG, SKY_IRRADIANCE))


# --- node graphs ----------------------------------------------------------------------------------------


class Graph:
    """Builds a Blender node tree: ``node(kind, key=value...)`` sets inputs by name (a socket links it)
    and ``props`` sets node properties."""

    def __init__(self, tree):
        self.tree = tree
        tree.nodes.clear()

    def node(self, kind: str, props: dict | None = None, **inputs):
        n = self.tree.nodes.new(kind)
        for k, v in (props or {}).items():
            setattr(n, k, v)
        for name, value in inputs.items():
            self.set(n, name, value)
        return n

    def set(self, node, name: str, value) -> None:
        sock = _socket(node.inputs, name)
        if hasattr(value, "is_output"):
            self.tree.links.new(value, sock)
        elif sock.type == "RGBA":
            sock.default_value = (*value, 1.0) if len(value) == 3 else value
        else:
            sock.default_value = value

    def noise(self, vector, scale: float, *, detail: float = 4.0, roughness: float = 0.55, distortion=0.0):
        return self.node(
            "ShaderNodeTexNoise",
            Vector=vector,
            Scale=scale,
            Detail=detail,
            Roughness=roughness,
            Distortion=distortion,
        ).outputs["Fac"]

    def step(self, value, lo: float, hi: float, to=(0.0, 1.0)):
        """``value`` mapped from [lo, hi] to ``to`` with a smooth step, clamped."""
        return self.node(
            "ShaderNodeMapRange",
            {"interpolation_type": "SMOOTHSTEP", "clamp": True},
            Value=value,
            **{"From Min": lo, "From Max": hi, "To Min": to[0], "To Max": to[1]},
        ).outputs["Result"]

    def math(self, op: str, *values):
        n = self.node("ShaderNodeMath", {"operation": op})
        for sock, v in zip(n.inputs, values, strict=False):
            if hasattr(v, "is_output"):
                self.tree.links.new(v, sock)
            else:
                sock.default_value = v
        return n.outputs[0]

    def mix(self, factor, a, b, *, colour: bool = True, blend: str = "MIX"):
        kind = "RGBA" if colour else "FLOAT"
        n = self.node("ShaderNodeMix", {"data_type": kind, "blend_type": blend, "clamp_factor": True})
        suffix = "Color" if colour else "Float"
        for ident, v in (("Factor_Float", factor), (f"A_{suffix}", a), (f"B_{suffix}", b)):
            sock = next(s for s in n.inputs if s.identifier == ident)
            if hasattr(v, "is_output"):
                self.tree.links.new(v, sock)
            elif colour and ident != "Factor_Float":
                sock.default_value = (*v, 1.0) if len(v) == 3 else v
            else:
                sock.default_value = v
        return next(s for s in n.outputs if s.identifier == f"Result_{suffix}")

    def principled(self, out_node, **inputs):
        bsdf = self.node("ShaderNodeBsdfPrincipled", **inputs)
        self.tree.links.new(bsdf.outputs["BSDF"], out_node.inputs["Surface"])
        return bsdf


def _socket(sockets, name: str):
    for s in sockets:
        if s.name == name and s.enabled:
            return s
    return sockets[name]


def _coords(g: Graph, look: CyclesLook, source: str):
    """Texture coordinates in metres (object space, or the surface's UV metres), moved by the look."""
    tc = g.node("ShaderNodeTexCoord")
    return g.node("ShaderNodeMapping", Vector=tc.outputs[source], Location=look.texture_offset).outputs[
        "Vector"
    ]


def steel_material(bpy, look: CyclesLook, name: str = "rebar"):
    """Bars: bare, mill-scaled or epoxy-coated steel with rust (or damage) in blotches, a tint per bar
    (``bar_tint`` attribute) and a per-bar share of rust (``bar_random``)."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    g = Graph(mat.node_tree)
    out = g.node("ShaderNodeOutputMaterial")
    p = _coords(g, look, "Object")
    per_bar = g.node("ShaderNodeAttribute", {"attribute_name": "bar_random"}).outputs["Fac"]
    tint = g.node("ShaderNodeAttribute", {"attribute_name": "bar_tint"}).outputs["Color"]
    cov = g.math("MULTIPLY_ADD", per_bar, 0.3, look.rust_coverage - 0.15)  # +-0.15 by bar
    blotch = g.noise(p, look.pattern_scale, detail=5.0, roughness=0.62)
    threshold = g.math("MULTIPLY_ADD", cov, -0.3, 0.64)  # noise above 0.64 - 0.3 coverage is rust
    rust = g.step(g.math("SUBTRACT", blotch, threshold), -0.03, 0.03)
    streak = g.noise(p, look.pattern_scale * 6.0, detail=3.0, roughness=0.7)
    rust_rgb = g.mix(streak, look.rust_dark_rgb, look.rust_light_rgb)
    scale_var = g.noise(p, look.pattern_scale * 3.0, detail=3.0)
    steel_rgb = g.mix(
        g.step(scale_var, 0.3, 0.7), np.array(look.steel_rgb) * 0.8, np.array(look.steel_rgb) * 1.15
    )
    base = g.mix(rust, steel_rgb, rust_rgb)
    base = g.mix(1.0, base, tint, blend="MULTIPLY")
    rough = g.mix(rust, look.steel_roughness, 0.88, colour=False)
    metal = g.mix(rust, look.steel_metallic, 0.0, colour=False)
    fine = g.noise(p, 900.0, detail=2.0, roughness=0.6)
    height = g.math("MULTIPLY_ADD", rust, 0.6, fine)
    bump = g.node("ShaderNodeBump", Strength=look.bump, Distance=0.0004, Height=height)
    coat = 0.5 if look.finish == "epoxy" else 0.0
    g.principled(
        out,
        **{
            "Base Color": base,
            "Metallic": metal,
            "Roughness": rough,
            "Normal": bump.outputs["Normal"],
            "Coat Weight": coat,
            "Coat Roughness": 0.15,
        },
    )
    return mat


def tie_wire_material(bpy, look: CyclesLook):
    """Black annealed tie wire."""
    mat = bpy.data.materials.new("tie_wire")
    mat.use_nodes = True
    g = Graph(mat.node_tree)
    out = g.node("ShaderNodeOutputMaterial")
    g.principled(out, **{"Base Color": (0.045, 0.043, 0.045), "Metallic": 0.7, "Roughness": 0.45})
    return mat


def ground_material(bpy, look: CyclesLook, kind: str, name: str):
    """Concrete (dry, or wet with puddles), soil, formwork wood or gravel, textured in surface metres."""
    mat = bpy.data.materials.new(name)
    mat.use_nodes = True
    g = Graph(mat.node_tree)
    out = g.node("ShaderNodeOutputMaterial")
    p = _coords(g, look, "UV")
    rgb = np.array(look.ground_rgb if kind == look.ground else _dry(kind))
    wet = look.wet and kind == look.ground
    if kind == "wood":
        grain = g.node(
            "ShaderNodeTexWave",
            {"wave_type": "BANDS", "bands_direction": "Y", "wave_profile": "SAW"},
            Vector=g.node("ShaderNodeMapping", Vector=p, Scale=(0.15, 1.0, 1.0)).outputs["Vector"],
            Scale=30.0,
            Distortion=4.0,
            Detail=3.0,
            **{"Detail Scale": 0.8},
        ).outputs["Fac"]  # grain along the board: the pattern stretched along x
        base = g.mix(g.step(grain, 0.2, 0.9), rgb * 1.15, rgb * 0.7)
        rough = 0.35 if rgb.max() < 0.2 else 0.65  # film-faced boards are smoother
        height = grain
        strength = 0.1
    elif kind == "gravel":
        cells = g.node("ShaderNodeTexVoronoi", Vector=p, Scale=45.0)
        shade = g.mix(cells.outputs["Color"], rgb * 0.6, rgb * 1.4)
        base = g.mix(g.noise(p, 3.0), shade, rgb * np.array([1.1, 0.95, 0.8]))
        rough = 0.8
        height = g.math("POWER", cells.outputs["Distance"], 0.5)
        strength = 0.8
    else:  # concrete, soil
        large = g.noise(p, 2.0, detail=4.0, roughness=0.6)
        base = g.mix(g.step(large, 0.3, 0.7), rgb * 0.8, rgb * 1.2)
        fleck = g.node("ShaderNodeTexVoronoi", Vector=p, Scale=220.0).outputs["Distance"]
        base = g.mix(g.step(fleck, 0.12, 0.05), base, rgb * 0.55)  # aggregate and pores
        fine = g.noise(p, 180.0 if kind == "concrete" else 40.0, detail=4.0, roughness=0.7)
        height = fine
        rough = 0.9 if kind == "concrete" else 0.97
        strength = 0.25 if kind == "concrete" else 0.7
    if wet:
        puddle = g.step(g.noise(p, 0.8, detail=5.0), 0.62 - 0.25 * look.puddles, 0.66 - 0.25 * look.puddles)
        rough = g.mix(puddle, 0.35, 0.04, colour=False)
        base = g.mix(puddle, base, np.array(look.ground_rgb) * 0.6)
        strength = g.mix(puddle, strength, 0.0, colour=False)
    bump = g.node("ShaderNodeBump", Strength=strength, Distance=0.002, Height=height)
    g.principled(out, **{"Base Color": base, "Roughness": rough, "Normal": bump.outputs["Normal"]})
    return mat


def _dry(kind: str) -> tuple[float, float, float]:
    return {
        "concrete": (0.42, 0.41, 0.39),
        "soil": (0.16, 0.11, 0.07),
        "wood": (0.5, 0.32, 0.17),
        "gravel": (0.35, 0.33, 0.3),
    }[kind]


def world(bpy, look: CyclesLook, strength: float, sun_dir) -> object:
    """The sky: Blender's Nishita sky towards the sun (noon, dusk), or a grey overcast gradient."""
    w = bpy.data.worlds.new("sky")
    w.use_nodes = True
    g = Graph(w.node_tree)
    out = g.node("ShaderNodeOutputWorld")
    if look.sky == "overcast":
        tc = g.node("ShaderNodeTexCoord")
        z = g.node("ShaderNodeSeparateXYZ", Vector=tc.outputs["Generated"]).outputs["Z"]
        up = g.step(z, -0.05, 0.6)
        colour = g.mix(up, (0.55, 0.56, 0.58), (1.0, 1.0, 1.02))
    else:
        sky = g.node(
            "ShaderNodeTexSky",
            {
                "sky_type": "NISHITA",
                "sun_disc": False,
                "sun_elevation": float(np.radians(look.sun_elevation_deg)),
                "sun_rotation": float(np.arctan2(sun_dir[0], sun_dir[1])),
                "dust_density": look.haze,
            },
        )
        colour = sky.outputs["Color"]
    bg = g.node("ShaderNodeBackground", Color=colour, Strength=strength)
    w.node_tree.links.new(bg.outputs["Background"], out.inputs["Surface"])
    return w
