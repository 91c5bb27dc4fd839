"""Follow one target crossing from frame to frame: KLT and the arm's motion, corrected by the detector.

Between detections the point is predicted by OpenCV's pyramidal Lucas-Kanade tracker (precise from one
frame to the next, drifting over many) fused with the prediction of the arm's own motion when the
caller has one (the camera's displacement and the point's depth; what the interaction matrix predicts).
The nearest detection inside a statistical gate then corrects the prediction with a Kalman update
(detector noise ``detection_sigma_px``; KLT error ``klt_sigma_px`` plus ``klt_motion_fraction`` of the
image motion). So a noisy detector is averaged over every frame of a visit, moving or not.

KLT is re-seeded on the fused point every frame; it counts as drifted (and is ignored for that frame)
when it disagrees with the motion prediction by more than ``drift_px`` and the noise allows. A detection
just outside the gate is ignored unless it persists consistently for three frames, then the track
restarts on it. With no prediction and no detection the target is lost: the point stays where it was
last seen, for the controller to hold still and re-acquire (a detection within ``gate_px``).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from rebar_data.servo.config import TrackerSettings

# What a suite does not set (its settings are :class:`rebar_data.servo.config.TrackerSettings`).
PYRAMID_LEVELS = 3  # KLT's pyramid levels above the image
FORWARD_BACKWARD_PX = 0.5  # largest forward-backward KLT disagreement that keeps its point
MIN_GATE_PX = 3.0  # the detection gate's floor


@dataclass(frozen=True)
class TrackState:
    """The target's image point after a frame, its standard deviation (px) and what produced it.

    ``source``: ``detected`` (the prediction corrected by a detection), ``predicted`` (KLT and/or the arm's
    motion only), ``reseeded`` (restarted on a detection), ``lost`` (nothing; the point is the last known).
    """

    point: np.ndarray
    sigma_px: float
    source: str
    klt_point: np.ndarray | None
    detection: np.ndarray | None

    @property
    def lost(self) -> bool:
        return self.source == "lost"


class TargetTracker:
    """KLT plus detections for one target; call :meth:`seed` once, then :meth:`update` every frame."""

    def __init__(self, config: TrackerSettings | None = None):
        self.cfg = config if config is not None else TrackerSettings()
        self._gray: np.ndarray | None = None
        self.point = np.full(2, np.nan)
        self.var = np.inf
        self.lost_frames = 0  # consecutive frames without the target, now
        self.lost_total = 0
        self.reseeds = 0
        self.frames_since_detection = 0
        self._outliers: list[np.ndarray] = []

    def seed(self, rgb: np.ndarray, point: np.ndarray, sigma_px: float | None = None) -> None:
        """Start tracking ``point`` (pixels) in this frame, known to ``sigma_px`` (default: one detection's)."""
        self._gray = _gray(rgb)
        self.point = np.asarray(point, float).copy()
        self.var = (self.cfg.detection_sigma_px if sigma_px is None else sigma_px) ** 2
        self.lost_frames = 0

    def update(
        self, rgb: np.ndarray, detections: np.ndarray, motion: tuple[np.ndarray, float] | None = None
    ) -> TrackState:
        """Track into a new frame.

        Args:
            rgb: The frame.
            detections: Its detections (N, 3), or none.
            motion: Optionally, where the arm's own motion since the last frame puts the point, and that
                prediction's standard deviation (px): fused with KLT's, and the check KLT's drift is
                measured against.
        """
        cfg = self.cfg
        gray = _gray(rgb)
        klt = self._klt(gray)
        det = np.asarray(detections, float).reshape(-1, 3)[:, :2]
        r = cfg.detection_sigma_px**2
        preds: list[tuple[np.ndarray, float]] = []
        if klt is not None:
            step = float(np.linalg.norm(klt - self.point))
            q_klt = (cfg.klt_sigma_px + cfg.klt_motion_fraction * step) ** 2
            preds.append((klt, q_klt))
        if motion is not None and np.all(np.isfinite(motion[0])):
            q_motion = float(motion[1]) ** 2
            if klt is not None and np.linalg.norm(klt - motion[0]) > max(
                cfg.drift_px, 4 * np.sqrt(q_klt + q_motion)
            ):
                preds = []  # KLT drifted off the point: it restarts from the fused point next frame
                self.reseeds += 1
            preds.append((np.asarray(motion[0], float), q_motion))
        if preds:
            w = np.array([1.0 / max(q, 1e-12) for _, q in preds])
            pred = sum(wi * p for wi, (p, _) in zip(w, preds, strict=True)) / w.sum()
            var = self.var + 1.0 / w.sum()
        else:
            pred, var = self.point, self.var + (cfg.gate_px / 3) ** 2
        match, source = None, "predicted" if preds else "lost"
        if len(det):
            d = np.linalg.norm(det - pred, axis=1)
            j = int(np.argmin(d))
            gate = max(MIN_GATE_PX, 3.5 * np.sqrt(var + r))
            if not preds and d[j] <= cfg.gate_px:
                self.point, self.var, source = det[j].copy(), r, "reseeded"  # re-acquired
                self.reseeds += 1
                match = det[j]
            elif d[j] <= gate:
                k = var / (var + r)
                self.point, self.var, source = pred + k * (det[j] - pred), (1 - k) * var, "detected"
                match = det[j]
                self._outliers = []
            elif d[j] <= cfg.gate_px:
                # A detection near but outside the gate: noise, a spurious hit, or the track is off. When it
                # persists, consistently, for three frames, trust the detector and restart there.
                self._outliers = [*self._outliers[-2:], det[j] - pred]
                spread = (
                    np.ptp(np.array(self._outliers), axis=0).max() if len(self._outliers) == 3 else np.inf
                )
                if spread <= 3 * cfg.detection_sigma_px + 1.0:
                    self.point, self.var, source = det[j].copy(), r, "reseeded"
                    self.reseeds += 1
                    match = det[j]
                    self._outliers = []
        self.frames_since_detection = 0 if match is not None else self.frames_since_detection + 1
        if match is None and preds:
            self.point, self.var = pred, var
        if source == "lost":
            self.var = var
            self.lost_frames += 1
            self.lost_total += 1
        else:
            self.lost_frames = 0
        self._gray = gray
        return TrackState(self.point.copy(), float(np.sqrt(self.var)), source, klt, match)

    def _klt(self, gray: np.ndarray) -> np.ndarray | None:
        """Where the point moved from the previous frame, or None when KLT loses it."""
        if self._gray is None or not np.all(np.isfinite(self.point)):
            return None
        cfg = self.cfg
        p0 = self.point.reshape(1, 1, 2).astype(np.float32)
        kw = {
            "winSize": (cfg.window_px, cfg.window_px),
            "maxLevel": PYRAMID_LEVELS,
            "criteria": (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01),
        }
        p1, st, _ = cv2.calcOpticalFlowPyrLK(self._gray, gray, p0, None, **kw)
        if p1 is None or not st[0, 0]:
            return None
        back, st_b, _ = cv2.calcOpticalFlowPyrLK(gray, self._gray, p1, None, **kw)
        if back is None or not st_b[0, 0]:
            return None
        if np.linalg.norm(back[0, 0] - p0[0, 0]) > FORWARD_BACKWARD_PX:
            return None
        p = p1[0, 0].astype(float)
        h, w = gray.shape
        if not (0 <= p[0] < w and 0 <= p[1] < h):
            return None
        return p


def _gray(rgb: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(np.ascontiguousarray(rgb[..., :3]), cv2.COLOR_RGB2GRAY)
