"""Memory stays flat over many frames and scene changes (its own renderer, with full-size textures)."""

from __future__ import annotations

import numpy as np

from rebar_data.camera import Intrinsics
from rebar_data.render.bench import _rss_mb
from rebar_data.render.renderer import Renderer
from rebar_data.scene.cameras import look_at
from rebar_data.scene.config import RenderConfig, SceneConfig
from rebar_data.scene.sample import sample_scene
from tests.render.test_sensor import OFF


def test_scene_changes_and_frames_keep_memory_flat(tunnel_rm, tmp_path):
    """Open3D keeps every distinct texture it uploads (7.5 MB a 1024 px map): scene changes must reuse
    the same few maps, so memory stops growing once the allowed looks have been seen."""
    cfg = SceneConfig.model_validate(
        {
            "materials": {"rebar": {"variants": 1, "rust": [0.6], "mill_scale": [0.3], "dust": [0.0]}},
            "surroundings": {"ground": {"variants": 1, "kinds": {"concrete": 1.0}}},
        }
    )
    k = Intrinsics(320, 240, 300.0, 300.0, 160.0, 120.0)  # the size the other render tests use: one renderer
    T = look_at(np.array([0.0, 0.1, 0.6]), np.array([0.0, 0.0, 0.05]), np.array([1.0, 0, 0]))
    with Renderer(k, RenderConfig(texture_size_px=1024, cache_dir=tmp_path)) as r:
        r.set_mesh(tunnel_rm)
        rss, bars = [], []
        for i in range(14):
            r.set_scene(sample_scene(cfg, np.random.default_rng(40 + i)))
            for j in range(3):
                frame = r.render(T, OFF, np.random.default_rng(3 * i + j))
            bars.append(frame.rgb[frame.instance >= 0].mean(0))
            if i in (3, 13):
                rss.append(_rss_mb())
    assert rss[1] - rss[0] < 20  # MB over 10 scene changes (a new look each time would add ~200)
    assert np.ptp(np.array(bars), axis=0).max() > 3  # the scenes still look different
