from __future__ import annotations

import numpy as np
import torch

from rebar_data.perception.inference.detector import decode
from rebar_data.perception.training.loss import detection_loss
from rebar_data.perception.training.targets import encode_targets


def _logit(p: np.ndarray) -> np.ndarray:
    p = np.clip(p, 1e-6, 1 - 1e-6)
    return np.log(p / (1 - p))


def test_encode_then_decode_gives_the_points_back_to_the_sub_pixel():
    rng = np.random.default_rng(0)
    # points on a jittered 16 px grid: at least 3 cells apart, anywhere inside their cells
    grid = np.stack(np.meshgrid(np.arange(8, 250, 16.0), np.arange(8, 186, 16.0)), -1).reshape(-1, 2)
    pts = grid + rng.uniform(-3.9, 3.9, grid.shape)
    heat, hw, off, ow = encode_targets(pts, np.zeros((0, 2)), 48, 64, sigma_cells=1.0)
    assert (heat == 1.0).sum() == len(pts)
    det = decode(_logit(heat), off, threshold=0.5)
    assert len(det) == len(pts)
    found = det[np.lexsort((det[:, 0], det[:, 1]))][:, :2]
    want = pts[np.lexsort((pts[:, 0], pts[:, 1]))]
    np.testing.assert_allclose(found, want, atol=1e-4)


def test_offsets_around_a_point_all_lead_to_it():
    heat, _, off, ow = encode_targets(np.array([[21.3, 30.9]]), np.zeros((0, 2)), 16, 16, sigma_cells=1.0)
    i, j = np.nonzero(ow)
    assert len(i) == 9
    u = 4 * (j + 0.5 + off[0, i, j])
    v = 4 * (i + 0.5 + off[1, i, j])
    np.testing.assert_allclose(u, 21.3, atol=1e-5)
    np.testing.assert_allclose(v, 30.9, atol=1e-5)


def test_ignored_points_zero_the_weight_around_them_but_not_at_positives():
    pos = np.array([[30.0, 30.0]])
    ign = np.array([[38.0, 30.0], [100.0, 100.0]])
    heat, hw, _, _ = encode_targets(pos, ign, 32, 32, sigma_cells=1.0)
    assert hw[25, 25] == 0.0 and hw[27, 27] == 0.0  # around (100, 100)
    assert hw[7, 7] == 1.0  # the positive's own cell stays
    assert hw[7, 9] == 0.0  # beside the ignored point at (38, 30)
    assert hw[0, 0] == 1.0


def test_decode_never_gives_two_peaks_for_a_plateau_of_saturated_scores():
    logit = np.full((8, 8), -10.0, np.float32)
    logit[3, 3], logit[3, 4] = 40.0, 40.5  # both round to probability 1.0 in float32
    det = decode(logit, np.zeros((2, 8, 8), np.float32), threshold=0.5)
    assert len(det) == 1 and det[0, 0] == 4 * 4.5


def test_loss_is_lowest_for_the_target_itself():
    pts = np.array([[20.0, 20.0], [45.0, 50.0]])
    heat, hw, off, ow = encode_targets(pts, np.zeros((0, 2)), 16, 16, sigma_cells=1.0)
    t = [torch.from_numpy(a)[None] for a in (heat, hw, off, ow)]
    perfect = torch.from_numpy(np.concatenate([_logit(heat)[None], off]))[None].float()
    noisy = perfect + 0.5 * torch.randn(perfect.shape, generator=torch.Generator().manual_seed(0))
    assert detection_loss(perfect, *t)[0] < detection_loss(noisy, *t)[0]
