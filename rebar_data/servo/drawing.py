"""Overlays drawn with OpenCV on camera images: the annotated views of a run's report."""

from __future__ import annotations

import numpy as np


def annotate(rgb: np.ndarray, *, detections=None, targets=None, track=None, desired=None) -> np.ndarray:
    """A copy of a camera image with detections (white), numbered targets (orange), the tracked point
    (green) and the desired point (magenta cross) drawn on it."""
    import cv2

    img = np.ascontiguousarray(rgb.copy())
    for u, v, _ in np.asarray(detections if detections is not None else np.zeros((0, 3))).reshape(-1, 3):
        cv2.circle(img, (round(u), round(v)), 5, (255, 255, 255), 1, cv2.LINE_AA)
    for i, (u, v) in enumerate(targets if targets is not None else []):
        cv2.circle(img, (round(u), round(v)), 9, (255, 150, 0), 2, cv2.LINE_AA)
        cv2.putText(
            img,
            f"T{i + 1}",
            (round(u) + 10, round(v) - 10),
            cv2.FONT_HERSHEY_SIMPLEX,
            0.7,
            (255, 150, 0),
            2,
            cv2.LINE_AA,
        )
    if desired is not None:
        cv2.drawMarker(
            img, (round(desired[0]), round(desired[1])), (255, 0, 255), cv2.MARKER_CROSS, 28, 2, cv2.LINE_AA
        )
    if track is not None:
        cv2.circle(img, (round(track[0]), round(track[1])), 6, (40, 230, 90), 2, cv2.LINE_AA)
    return img
