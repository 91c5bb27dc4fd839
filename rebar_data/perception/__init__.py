"""Rebar-crossing keypoint detector: ``Detector.load().detect(rgb) -> (N, 3)`` u, v, score.

- :mod:`~rebar_data.perception.inference`: the run time (numpy, OpenCV, ONNX Runtime or OpenVINO).
- :mod:`~rebar_data.perception.networks`: the PyTorch networks and the one writer of their model files.
- :mod:`~rebar_data.perception.training`: training every stage, its data and settings; shipping a model.
- :mod:`~rebar_data.perception.evaluation`: metrics, the model card's rows, the gate, the bench and plots.
- :mod:`~rebar_data.perception.commands`: the ``rebar train|detect|score|adapt|add-crossing-point`` commands."""

from rebar_data.perception.inference.detector import Detector

__all__ = ["Detector"]
