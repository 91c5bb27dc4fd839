"""Rebar-crossing keypoint detector: model, training loop, metrics, inference and plots.

The detector predicts a heatmap of crossings at stride 4 with a sub-pixel offset per cell
(CenterNet-like) from a compact depthwise-separable network, and returns (u, v, score) in the input
image's pixels with COCO's corner origin. It is trained from scratch on a dataset in the project's
layout; nothing is downloaded.
"""
