"""From raw detections to an ordered list of targets: clustering, persistence over frames, row-major order.

As in the paper, detections are grouped into distinct crossings and visited in row-major order (top
row first, left to right). Clustering over a few frames of a still camera also removes detections that
do not persist (a spurious hit in one frame).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Clusters:
    """Cluster centres (N, 2) in pixels, mean score and how many detections each holds."""

    center: np.ndarray
    score: np.ndarray
    count: np.ndarray


def cluster_detections(detections: np.ndarray, radius_px: float, *, min_score: float = 0.0) -> Clusters:
    """Group detections within ``radius_px`` of a cluster's seed (strongest first); score-weighted centres."""
    det = np.asarray(detections, float).reshape(-1, 3)
    det = det[det[:, 2] >= min_score]
    order = np.argsort(-det[:, 2], kind="stable")
    seeds: list[np.ndarray] = []
    members: list[list[int]] = []
    for i in order:
        p = det[i, :2]
        if seeds:
            d = np.linalg.norm(np.array(seeds) - p, axis=1)
            j = int(np.argmin(d))
            if d[j] <= radius_px:
                members[j].append(i)
                continue
        seeds.append(p)
        members.append([i])
    if not seeds:
        return Clusters(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64))
    center = np.array([np.average(det[m, :2], axis=0, weights=np.maximum(det[m, 2], 1e-9)) for m in members])
    score = np.array([det[m, 2].mean() for m in members])
    count = np.array([len(m) for m in members], np.int64)
    return Clusters(center, score, count)


def persistent_clusters(frames: list[np.ndarray], radius_px: float, *, min_fraction: float = 0.5) -> Clusters:
    """Clusters over several frames of a still camera, kept when seen in at least ``min_fraction`` of them.

    Frames with no detections at all (a dropped frame) do not count against a cluster.
    """
    seen = [f for f in frames if len(f)]
    if not seen:
        return Clusters(np.zeros((0, 2)), np.zeros(0), np.zeros(0, np.int64))
    allc = cluster_detections(np.vstack(seen), radius_px)
    keep = allc.count >= max(1, int(np.ceil(min_fraction * len(seen))))
    return Clusters(allc.center[keep], allc.score[keep], allc.count[keep])


def row_major(points: np.ndarray, row_tolerance_px: float) -> np.ndarray:
    """Indices ordering points (N, 2) into rows (by v, a new row when v jumps by more than the tolerance),
    each row left to right."""
    pts = np.asarray(points, float).reshape(-1, 2)
    if len(pts) == 0:
        return np.zeros(0, np.int64)
    by_v = np.argsort(pts[:, 1], kind="stable")
    rows: list[list[int]] = [[int(by_v[0])]]
    for i in by_v[1:]:
        if pts[i, 1] - pts[rows[-1][-1], 1] > row_tolerance_px:
            rows.append([])
        rows[-1].append(int(i))
    return np.array([i for row in rows for i in sorted(row, key=lambda k: pts[k, 0])], np.int64)


def select_targets(
    centers: np.ndarray,
    count: int,
    *,
    desired_px: np.ndarray,
    width: int,
    height: int,
    margin_px: float,
    row_tolerance_px: float,
    rng: np.random.Generator | None = None,
) -> np.ndarray:
    """Indices of up to ``count`` targets, in row-major order.

    Candidates lie at least ``margin_px`` inside the image. Without ``rng`` the ``count`` nearest to the
    desired image point are taken (the paper's set-up); with ``rng``, a random candidate and its
    ``count - 1`` nearest neighbours (a random group of adjacent crossings, so that each target is still in
    view when the one before it is centred).
    """
    c = np.asarray(centers, float).reshape(-1, 2)
    inside = (c[:, 0] >= margin_px) & (c[:, 0] < width - margin_px)
    inside &= (c[:, 1] >= margin_px) & (c[:, 1] < height - margin_px)
    idx = np.nonzero(inside)[0]
    if len(idx) == 0:
        return idx
    anchor = np.asarray(desired_px, float) if rng is None else c[idx[rng.integers(len(idx))]]
    idx = idx[np.argsort(np.linalg.norm(c[idx] - anchor, axis=1), kind="stable")[:count]]
    return idx[row_major(c[idx], row_tolerance_px)]
