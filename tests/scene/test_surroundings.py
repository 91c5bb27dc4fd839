from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from rebar_data.scene.config import SceneConfig
from rebar_data.scene.mat_surface import MatSurface
from rebar_data.scene.sample import sample_scene
from rebar_data.scene.surroundings import DISTRACTOR_ID, GROUND_ID, build_surroundings


def _scene(seed=0, **distractors):
    s = sample_scene(SceneConfig(), np.random.default_rng(seed))
    d = replace(s.distractors, **distractors) if distractors else s.distractors
    return replace(s, distractors=d)


@pytest.mark.parametrize("shape", ["plane", "follow"])
@pytest.mark.parametrize("mesh", ["tunnel_rm", "planar_rm"])
def test_ground_lies_beneath_the_mat(mesh, shape, request):
    rm = request.getfixturevalue(mesh)
    s = _scene(lower_layer=False, spacers=0, loose_tie_wire=0, formwork_sides=0)
    s = replace(s, ground=replace(s.ground, shape=shape, distance_m=0.1, tilt_deg=4.0))
    objs = build_surroundings(s, rm)
    assert objs and all(o.instance_id == GROUND_ID for o in objs)
    surf = MatSurface.of(rm)
    centre, _, _, n = (x[0] for x in surf.frame(surf.centre()))
    # every ground point under the mat is at least the gap below the mat's lowest point (along the normal)
    lowest = np.min((np.asarray(rm.mesh.vertices) - centre) @ n)
    for o in objs:
        tri = o.shape.vertices[o.shape.triangles].mean(1)
        under = np.all(np.abs(surf.to_ab(tri) - surf.centre()) < 0.5, axis=1)
        if under.any():
            assert np.max((tri[under] - centre) @ n) <= lowest - 0.1 + 1e-3
    names = {o.name for o in objs}
    assert ("ground_mould" in names) == (shape == "follow" and mesh == "tunnel_rm")


def test_distractors_follow_the_sample(tunnel_rm):
    none = build_surroundings(
        _scene(lower_layer=False, spacers=0, loose_tie_wire=0, formwork_sides=0), tunnel_rm
    )
    assert {o.name for o in none if o.instance_id == DISTRACTOR_ID} == set()
    full = build_surroundings(
        _scene(lower_layer=True, spacers=4, loose_tie_wire=5, formwork_sides=0b1111), tunnel_rm
    )
    d = {o.name: o for o in full if o.instance_id == DISTRACTOR_ID}
    assert set(d) == {"lower_layer", "spacers", "loose_tie_wire", "formwork"}
    # the lower layer lies inside the element, beneath the top mat
    surf = MatSurface.of(tunnel_rm)
    s = _scene(lower_layer=True, spacers=4, loose_tie_wire=5, formwork_sides=0b1111)
    h = surf.height(d["lower_layer"].shape.vertices)
    assert h.max() <= surf.height_range_m[1] - s.distractors.lower_layer_depth_m + 1e-3  # the mat, moved down
    assert h.max() < surf.height_range_m[0]  # entirely beneath the top mat
    for o in full:
        assert o.shape.corner_uv_m.shape == (len(o.shape.triangles), 3, 2)
    again = build_surroundings(s, tunnel_rm)
    assert all(np.array_equal(a.shape.vertices, b.shape.vertices) for a, b in zip(full, again, strict=True))


def test_ground_and_lower_layer_of_a_wall_read_from_ifc(tmp_path):
    """The sample IFC wall: the ground lies behind its back mat, along the camera-side normal, and the lower
    layer is a copy of the top (front) mat alone, moved beneath it."""
    pytest.importorskip("ifcopenshell")
    from rebar_data.geometry.ifc_samples import write_wall
    from tests.ifc_models import read_mesh

    rm = read_mesh(tmp_path, write_wall(tmp_path / "wall.ifc"), crossings="top_mat")
    fit = rm.layout.surface
    s = _scene(lower_layer=True, spacers=0, loose_tie_wire=0, formwork_sides=0)
    s = replace(s, ground=replace(s.ground, shape="plane", distance_m=0.1, tilt_deg=0.0))
    objs = {o.name: o for o in build_surroundings(s, rm)}
    lowest = fit.height(np.asarray(rm.mesh.vertices)).min()  # the back mat's far side
    assert fit.height(objs["ground_plane"].shape.vertices).max() <= lowest - 0.1 + 1e-3
    h = fit.height(objs["lower_layer"].shape.vertices)
    top, r = fit.mats[fit.top_mat], 0.006 / np.cos(np.pi / 8) + 1e-6  # 8-sided tubes of the 12 mm bars
    depth = s.distractors.lower_layer_depth_m
    assert h.min() >= top.low_m - r - depth - 1e-6 and h.max() <= top.high_m + r - depth + 1e-6
