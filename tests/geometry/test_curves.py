from __future__ import annotations

import numpy as np
import pytest

from rebar_data.geometry.curves import Arc, CurveArrays, Line, closest_points


def _dist_to_line(p, line):
    return np.linalg.norm(line.point(line.project(p)) - p)


def test_line_line_closest_points_are_perpendicular():
    a = Line(np.array([-1.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]))
    b = Line(np.array([0.3, -1.0, 0.012]), np.array([0.3, 1.0, 0.012]))
    _, _, pa, pb = closest_points(a, b)
    np.testing.assert_allclose(pa, [0.3, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(pb, [0.3, 0.0, 0.012], atol=1e-15)


def test_line_arc_closest_points_on_both_curves_and_perpendicular():
    arc = Arc(np.zeros(3), 3.0, np.array([-1.0, 0.0, 0.0]), np.array([0.0, -0.3, 0.9539392014169456]), 0.6)
    line = Line(np.array([-1.0, 0.1, 2.988]), np.array([1.0, 0.1, 2.988]))
    s_a, s_b, pa, pb = closest_points(arc, line)
    assert abs(np.linalg.norm(pa) - 3.0) < 1e-12  # on the arc's circle
    assert abs(pa[0]) < 1e-12  # in the arc's plane
    assert _dist_to_line(pb, line) < 1e-12
    d = pb - pa
    assert abs(np.dot(d, arc.tangent(s_a))) < 1e-12
    assert abs(np.dot(d, line.direction)) < 1e-12


def test_arc_arc_closest_points_are_stationary():
    a = Arc(
        np.array([0.0, 0.0, -5.0]),
        5.0,
        np.array([1.0, 0.0, 0.0]),
        np.array([0.0, 0.2, 0.9797958971132712]),
        0.5,
    )
    b = Arc.through(
        np.array([-1.0, -0.05, 0.01]), np.array([1.0, -0.05, 0.01]), np.array([0.0, 0.0, -1.0]), 0.02
    )
    s_a, s_b, pa, pb = closest_points(a, b)
    d = pb - pa
    assert abs(np.dot(d, a.tangent(s_a))) < 1e-12
    assert abs(np.dot(d, b.tangent(s_b))) < 1e-12
    # brute force over a fine grid never beats it
    sa = np.linspace(0, a.length, 2001)
    sb = np.linspace(0, b.length, 2001)
    brute = np.min(np.linalg.norm(a.point(sa)[:, None] - b.point(sb)[None], axis=-1))
    assert np.linalg.norm(d) <= brute + 1e-12


@pytest.mark.parametrize("phi", [0.0, 0.1, 0.35])
def test_arc_projection_round_trip(phi):
    arc = Arc(np.array([1.0, 2.0, 3.0]), 2.0, np.array([0.0, 0.0, 1.0]), np.array([1.0, 0.0, 0.0]), 0.35)
    p = arc.point(phi * 2.0)
    assert arc.project(p) == pytest.approx(phi * 2.0, abs=1e-12)


def test_arc_through_has_requested_sagitta():
    a, b = np.array([0.0, 0.0, 0.0]), np.array([2.0, 0.0, 0.0])
    arc = Arc.through(a, b, np.array([0.0, 0.0, -1.0]), 0.01)
    np.testing.assert_allclose(arc.start, a, atol=1e-12)
    np.testing.assert_allclose(arc.end, b, atol=1e-12)
    np.testing.assert_allclose(arc.point(arc.length / 2), [1.0, 0.0, -0.01], atol=1e-12)


def test_curve_arrays_agree_with_each_curve():
    """The batched evaluation gives what each curve gives alone: projections (clamped to a line's ends, the
    nearer end outside an arc's sweep), points and tangents."""
    rng = np.random.default_rng(3)
    curves = [
        Line(np.array([0.0, 0.0, 0.0]), np.array([1.0, 0.2, 0.0])),
        Arc.through(np.array([0.0, 0.0, 0.0]), np.array([1.2, 0.0, 0.0]), np.array([0.0, 0.0, 1.0]), 0.05),
        Arc(np.array([0.0, 0.0, -3.0]), 3.0, np.array([-1.0, 0.0, 0.0]), np.array([0.0, -0.3, 0.954]), 0.6),
    ]
    arrays = CurveArrays.of(curves)
    idx = rng.integers(len(curves), size=300)
    p = rng.normal(0.0, 1.5, (300, 3))
    s = arrays.project(idx, p)
    np.testing.assert_allclose(s, [curves[i].project(q) for i, q in zip(idx, p, strict=True)], atol=1e-12)
    assert (s < 1e-12).any() and any(abs(s[k] - curves[i].length) < 1e-12 for k, i in enumerate(idx))
    np.testing.assert_allclose(
        arrays.point(idx, s), [curves[i].point(t) for i, t in zip(idx, s, strict=True)], atol=1e-12
    )
    np.testing.assert_allclose(
        arrays.tangent(idx, s), [curves[i].tangent(t) for i, t in zip(idx, s, strict=True)], atol=1e-12
    )
