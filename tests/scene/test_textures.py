from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np

from rebar_data.scene.config import SceneConfig
from rebar_data.scene.sample import sample_scene
from rebar_data.scene.texture_folders import find_texture_sets, load_texture_set
from rebar_data.scene.textures import TextureCache, ground_maps, periodic_noise, rebar_fields, rebar_maps


def test_noise_tiles_seamlessly_and_is_seeded():
    a = periodic_noise(128, np.random.default_rng(0), beta=2.0)
    assert np.array_equal(a, periodic_noise(128, np.random.default_rng(0), beta=2.0))
    assert abs(a.mean()) < 1e-5 and np.isclose(a.std(), 1.0, atol=1e-4)
    inner = np.abs(np.diff(a, axis=1)).mean()
    seam = np.abs(a[:, 0] - a[:, -1]).mean()  # across the wrap: no bigger a step than inside
    assert seam < 1.5 * inner


def test_rebar_layers_change_the_look():
    fields = rebar_fields(0, 128)
    base = sample_scene(SceneConfig(), np.random.default_rng(0)).rebar
    clean = replace(base, rust=0.0, pitting=0.0, dust=0.0, wear=0.0, mill_scale=0.0, colour_variation=0.0)
    rusty = replace(clean, rust=1.0)
    dusty = replace(clean, dust=1.0)
    c, r, d = (rebar_maps(m, fields) for m in (clean, rusty, dusty))
    for maps in (c, r, d):
        assert maps["albedo"].shape == (128, 128, 3) and maps["albedo"].dtype == np.uint8
        assert maps["normal"].shape == (128, 128, 3) and maps["roughness"].shape == (128, 128)

    def redness(m):
        return m["albedo"][..., 0].mean() / m["albedo"][..., 2].mean()

    assert redness(r) > 1.5 * redness(c)  # rust is orange-brown
    assert r["metallic"].mean() < 0.2 * c["metallic"].mean()  # and not metallic
    assert d["roughness"].mean() > c["roughness"].mean()  # dust is matte


def test_ground_kinds_differ():
    maps = {k: ground_maps(k, 1, 64) for k in ("concrete", "soil", "plywood", "gravel")}
    means = {k: m["albedo"].reshape(-1, 3).mean(0) for k, m in maps.items()}
    assert means["soil"][0] > means["soil"][2] + 10  # brown
    assert abs(means["concrete"][0] - means["concrete"][2]) < 15  # grey
    assert means["plywood"][0] > means["plywood"][2] + 30  # wood


def test_cache_stores_on_disk_and_reuses(tmp_path):
    calls = []

    def make():
        calls.append(1)
        return {"a": np.arange(6, dtype=np.float16).reshape(2, 3)}

    c1 = TextureCache(tmp_path)
    first = c1.get("k", make)
    assert len(calls) == 1 and any(tmp_path.rglob("k.npz"))
    c2 = TextureCache(tmp_path)  # a new process: read from disk
    assert np.array_equal(c2.get("k", make)["a"], first["a"]) and len(calls) == 1


def test_user_texture_sets_in_poly_haven_and_ambientcg_names(tmp_path):
    img = np.zeros((16, 16, 3), np.uint8)
    img[..., 1] = 200  # a normal map's green
    for name in (
        "rusty_steel_diff_1k.jpg",
        "rusty_steel_rough_1k.jpg",
        "rusty_steel_nor_dx_1k.png",
        "Metal049A_1K-JPG_Color.jpg",
        "Metal049A_1K-JPG_NormalGL.jpg",
        "readme.txt",
    ):
        cv2.imwrite(str(tmp_path / name), img) if name.endswith(("jpg", "png")) else (
            tmp_path / name
        ).write_text("")
    sets = {s.name.split("/")[-1]: s for s in find_texture_sets(tmp_path)}
    assert set(sets) == {"rusty_steel", "metal049a"}
    rs = sets["rusty_steel"]
    assert rs.roughness is not None and rs.normal is not None and rs.normal_is_directx
    maps = load_texture_set(rs, 32)
    assert maps["albedo"].shape == (32, 32, 3) and maps["roughness"].shape == (32, 32)
    assert maps["normal"][..., 1].mean() < 100  # DirectX green flipped to OpenGL's
    assert "roughness" not in load_texture_set(sets["metal049a"], 32)


def test_a_damaged_cache_file_is_made_again(tmp_path):
    calls = []

    def make():
        calls.append(1)
        return {"a": np.arange(4096, dtype=np.float16)}

    TextureCache(tmp_path).get("k", make)
    (path,) = tmp_path.rglob("k.npz")
    whole = path.read_bytes()
    import io
    import zipfile

    empty_zip = io.BytesIO()
    zipfile.ZipFile(empty_zip, "w").close()
    for damaged in (b"", whole[: len(whole) // 2], whole[:-30] + b"\0" * 30, empty_zip.getvalue()):
        path.write_bytes(damaged)  # a power cut's 0-byte or half-written file, a bad CRC, an empty archive
        arrays = TextureCache(tmp_path).get("k", make)  # a new process: reads the file, sees the damage
        assert np.array_equal(arrays["a"], make()["a"])
        assert path.read_bytes() == whole  # made again, and the damaged file replaced
    assert len(calls) == 1 + 2 * 4
    assert [p.name for p in path.parent.iterdir()] == ["k.npz"]  # no temporary file left
