from __future__ import annotations

import numpy as np

from rebar_data.servo.targets import cluster_detections, persistent_clusters, row_major, select_targets


def test_clusters_merge_nearby_detections_with_score_weights():
    det = np.array([[100, 100, 1.0], [102, 100, 1.0], [300, 100, 0.9], [100, 300, 0.8]])
    c = cluster_detections(det, 8.0)
    assert len(c.center) == 3
    np.testing.assert_allclose(c.center[0], [101, 100])
    assert list(c.count) == [2, 1, 1]


def test_persistence_drops_a_one_frame_spurious_detection_and_ignores_dropped_frames():
    grid = np.array([[100, 100, 1.0], [200, 100, 1.0]])
    frames = [grid, np.vstack([grid, [[400, 300, 0.9]]]), np.zeros((0, 3)), grid]
    c = persistent_clusters(frames, 8.0)
    assert len(c.center) == 2


def test_row_major_order_tolerates_curved_rows():
    pts = np.array([[300, 205], [100, 200], [200, 195], [110, 300], [210, 310]])
    assert list(row_major(pts, 30.0)) == [1, 2, 0, 3, 4]


def test_selection_takes_the_nearest_or_a_random_adjacent_group():
    u, v = np.meshgrid(np.arange(60, 640, 100.0), np.arange(40, 480, 100.0))
    centers = np.stack([u.ravel(), v.ravel()], axis=1)
    kw = {"width": 640, "height": 480, "margin_px": 30.0, "row_tolerance_px": 30.0}
    idx = select_targets(centers, 4, desired_px=np.array([318.0, 193.0]), **kw)
    np.testing.assert_allclose(centers[idx], [[260, 140], [360, 140], [260, 240], [360, 240]])
    grp = select_targets(centers, 3, desired_px=np.zeros(2), rng=np.random.default_rng(0), **kw)
    d = np.linalg.norm(centers[grp][:, None] - centers[grp][None], axis=2)
    assert d.max() <= 2 * 100 * np.sqrt(2) + 1e-9  # adjacent crossings, not scattered ones
