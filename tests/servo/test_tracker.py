from __future__ import annotations

import cv2
import numpy as np

from rebar_data.servo.config import TrackerSettings
from rebar_data.servo.tracker import TargetTracker


def _grid_image(offset: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A rebar-like grid (bars every 100 px) shifted by ``offset`` pixels, with a little sensor noise."""
    h, w = 480, 640
    u, v = np.meshgrid(np.arange(w) + 0.5 - offset[0], np.arange(h) + 0.5 - offset[1])
    bars = (np.abs(((u - 20) % 100) - 50) < 6) | (np.abs(((v - 40) % 100) - 50) < 6)
    img = np.where(bars, 170.0, 40.0)
    img = cv2.GaussianBlur(img, (0, 0), 1.2) + rng.normal(0, 1.0, img.shape)
    return np.repeat(np.clip(img, 0, 255).astype(np.uint8)[..., None], 3, axis=2)


def _crossing(offset):
    return np.array([370.0, 290.0]) + offset  # a bar crossing of the grid above


def test_klt_follows_a_moving_crossing_between_detections():
    rng = np.random.default_rng(0)
    tr = TargetTracker(TrackerSettings(detection_sigma_px=0.1))
    offset = np.zeros(2)
    tr.seed(_grid_image(offset, rng), _crossing(offset))
    for _ in range(15):
        offset = offset + [2.5, -1.5]
        state = tr.update(_grid_image(offset, rng), np.zeros((0, 3)))  # no detections at all
        assert state.source == "predicted"
    assert np.linalg.norm(state.point - _crossing(offset)) < 1.0


def test_noisy_detections_are_averaged():
    rng = np.random.default_rng(1)
    tr = TargetTracker(TrackerSettings(detection_sigma_px=2.0))
    img = _grid_image(np.zeros(2), rng)
    truth = _crossing(np.zeros(2))
    first = truth + rng.normal(0, 2.0, 2)
    tr.seed(img, first, 2.0)
    for _ in range(40):
        det = np.append(truth + rng.normal(0, 2.0, 2), 1.0)[None]
        state = tr.update(img, det)
    assert state.sigma_px < 0.5
    assert np.linalg.norm(state.point - truth) < 1.0


def test_a_spurious_detection_is_ignored_and_a_persistent_offset_reseeds():
    rng = np.random.default_rng(2)
    tr = TargetTracker(TrackerSettings(detection_sigma_px=0.2))
    img = _grid_image(np.zeros(2), rng)
    truth = _crossing(np.zeros(2))
    tr.seed(img, truth, 0.2)
    state = tr.update(img, np.array([[truth[0] + 12, truth[1], 1.0]]))  # once, 12 px off
    assert np.linalg.norm(state.point - truth) < 0.5
    for _ in range(2):  # the detector insists (three frames in all): the track restarts there
        state = tr.update(img, np.array([[truth[0] + 12, truth[1], 1.0]]))
    assert state.source == "reseeded"
    assert np.linalg.norm(state.point - (truth + [12, 0])) < 1e-9


def test_the_arm_motion_prediction_carries_the_point_when_klt_cannot():
    rng = np.random.default_rng(3)
    tr = TargetTracker(TrackerSettings())
    blank = np.zeros((480, 640, 3), np.uint8)  # nothing for KLT to hold on to
    tr.seed(blank, np.array([300.0, 200.0]), 0.1)
    state = tr.update(blank, np.zeros((0, 3)), motion=(np.array([310.0, 195.0]), 0.05))
    assert state.source == "predicted"
    np.testing.assert_allclose(state.point, [310.0, 195.0])
    state = tr.update(blank, np.zeros((0, 3)))  # neither: lost, the point stays where it was
    assert state.lost and tr.lost_frames == 1
    np.testing.assert_allclose(state.point, [310.0, 195.0])
    state = tr.update(blank, np.array([[316.0, 190.0, 0.9]]))  # seen again inside the gate: re-acquired
    assert state.source == "reseeded" and not state.lost
    del rng
