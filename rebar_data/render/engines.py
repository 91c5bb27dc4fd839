"""Which renderer draws a pipeline's RGB images (``render.engine``), and what info.json records of it.

``open3d`` is the project's own renderer (:class:`rebar_data.render.renderer.Renderer`); ``cycles`` is
Blender's path tracer (:class:`rebar_data.render.cycles.CyclesRenderer`, the optional extra ``cycles``).
Both take the same scenes and cameras and label through the same ray cast.
"""

from __future__ import annotations

from importlib import metadata

from rebar_data.scene.config import RenderConfig


def renderer_class(cfg: RenderConfig) -> type:
    """The renderer class for ``cfg.engine`` (the Cycles one needs bpy: see :func:`check_engine`)."""
    if cfg.engine == "cycles":
        from rebar_data.render.cycles import CyclesRenderer

        return CyclesRenderer
    from rebar_data.render.renderer import Renderer

    return Renderer


def check_engine(cfg: RenderConfig) -> None:
    """Raise a ConfigError naming the fix when the engine's package is missing (before anything is written)."""
    if cfg.engine == "cycles":
        from rebar_data.render.cycles import require_bpy

        require_bpy()


def engine_record(cfg: RenderConfig) -> dict:
    """What info.json's ``renderer`` says: the engine, its version and the settings that change pixels."""
    if cfg.engine == "cycles":
        from rebar_data.render.cycles import blender_version

        c = cfg.cycles
        return {
            "engine": "cycles",
            "blender": blender_version(),
            "device": "CPU",
            "samples": c.samples,
            "adaptive_threshold": c.adaptive_threshold,
            "max_bounces": c.max_bounces,
            "denoiser": "OpenImageDenoise" if c.denoise else "none",
        }
    return {"engine": "open3d", "open3d": metadata.version("open3d")}
