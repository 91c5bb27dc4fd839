"""The detector: ``Detector.load(path).detect(rgb) -> (N, 3)`` u, v, score, best first.

The first stage is a heatmap network at stride 4 with a sub-pixel offset per cell; its peaks are the
candidates, which the later stages move, verify and score (:mod:`~rebar_data.perception.inference.refine`,
:mod:`~rebar_data.perception.inference.checks`). Its ONNX files run in ONNX Runtime or OpenVINO
(:mod:`~rebar_data.perception.inference.model_file`). Coordinates are in the input image's pixels with COCO's
corner origin (the top-left corner of the top-left pixel is (0, 0)), as everywhere in the project.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import numpy as np

from rebar_data.errors import ConfigError
from rebar_data.perception.inference.checks import DepthCheck, LineCheck, as_depth_m
from rebar_data.perception.inference.image import (
    flatten_behind,
    focal_scale,
    resample,
    resampled_size,
    scaled_camera,
)
from rebar_data.perception.inference.model_file import (
    META_KEY,
    load_crossing_point,
    load_depth_check,
    load_refiner,
    onnx_session,
    resolve_runtime,
)
from rebar_data.perception.inference.refine import CrossingPoint, Refiner, check_point

STRIDE = 4
INPUT_MULTIPLE = 16  # the encoder halves the size four times
OPERATING_THRESHOLD = 0.5  # the score ``detect`` returns from by default, and the metrics' operating point


def ray_grid(
    height: int, width: int, camera: tuple[float, float, float, float], *, stride: int = STRIDE
) -> np.ndarray:
    """(2, H / stride, W / stride) viewing rays ((u - cx) / fx, (v - cy) / fy) at the centres of the
    stride x stride cells of an H x W image (COCO corner origin: cell j's centre is at stride * (j + 0.5))."""
    fx, fy, cx, cy = camera
    u = (stride * (np.arange(-(-width // stride), dtype=np.float64) + 0.5) - cx) / fx
    v = (stride * (np.arange(-(-height // stride), dtype=np.float64) + 0.5) - cy) / fy
    return np.stack(np.broadcast_arrays(u[None, :], v[:, None])).astype(np.float32)


def decode(
    heat_logit: np.ndarray,
    offset: np.ndarray,
    *,
    threshold: float,
    max_detections: int = 1000,
) -> np.ndarray:
    """Crossings from one output: local maxima (3x3) of the heatmap with a score of at least ``threshold``.

    Peaks are found on the logits, which do not saturate the way float32 probabilities do near 1, so two
    neighbouring cells never tie and give one crossing twice.

    Args:
        heat_logit: (H, W) heatmap logits.
        offset: (2, H, W) offsets in cells.
        threshold: Lowest score (probability) kept, in (0, 1).
        max_detections: Most crossings returned, best first.

    Returns:
        (N, 3) u, v, score in input pixels (COCO corner origin), sorted by score, best first.
    """
    heat_logit = np.ascontiguousarray(heat_logit, np.float32)
    t = np.clip(threshold, 1e-7, 1 - 1e-7)
    floor = np.log(t / (1 - t))
    peak = (heat_logit >= cv2.dilate(heat_logit, np.ones((3, 3), np.uint8))) & (heat_logit >= floor)
    i, j = np.nonzero(peak)
    logit = heat_logit[i, j].astype(np.float64)
    order = np.argsort(-logit, kind="stable")[:max_detections]
    i, j, logit = i[order], j[order], logit[order]
    u = STRIDE * (j + 0.5 + offset[0, i, j])
    v = STRIDE * (i + 0.5 + offset[1, i, j])
    return np.c_[u, v, 1.0 / (1.0 + np.exp(-logit))]


# how the stages read an image: "mirrored" (the first stage reads the image and its mirror image and takes
# the mean of the two, the second stage reads every pass in its int8 copy) or "single"
Reading = Literal["mirrored", "single"]
READINGS: tuple[str, ...] = get_args(Reading)
# the views the second stage's later passes read in the mirrored reading (the single one: the file's)
MIRRORED_LATER_VIEWS = 1


def check_reading(reading: str) -> str:
    """``reading`` if it names one of :data:`READINGS`; ConfigError otherwise."""
    if reading not in READINGS:
        raise ConfigError(f"reading = {reading!r} is not accepted; accepted: one of {', '.join(READINGS)}")
    return reading


def mirrored_camera(
    camera: tuple[float, float, float, float], width: int
) -> tuple[float, float, float, float]:
    """The intrinsics of an image ``width`` pixels wide turned left for right: the principal point mirrored
    (COCO corner origin: u becomes ``width`` - u)."""
    fx, fy, cx, cy = camera
    return fx, fy, width - cx, cy


def mean_with_mirror(out: np.ndarray, mirrored: np.ndarray) -> np.ndarray:
    """The mean of the first stage's output ``out`` (3, H, W: heatmap logit, column and row offsets) and its
    output for the mirror image ``mirrored``, already turned back cell for cell: a column offset read in the
    mirror image points the other way."""
    mean = 0.5 * (out + mirrored)
    mean[1] = 0.5 * (out[1] - mirrored[1])
    return mean


DEFAULT_FOCAL_PER_WIDTH = 525.0 / 640.0  # Kinect v1 colour camera, when neither caller nor model says
MODELS_DIR = Path(__file__).parent.parent / "models"
SHIPPED_MODEL = MODELS_DIR / "rebar_keypoint.onnx"
RUN_FILES = ("best.onnx", "best.pt", "last.pt")
DUPLICATE_PX = 3.0  # two detections placed nearer than this are one crossing


def resolve_model_path(path: str | Path | None) -> Path:
    """The model file meant by ``path``: None is the shipped model, a training run folder its best model."""
    if path is None:
        if not SHIPPED_MODEL.exists():
            raise ConfigError(
                f"no shipped detector at {SHIPPED_MODEL}; accepted: train and ship one with `make train`, "
                "or pass a model file (.onnx or .pt) or a training run folder"
            )
        return SHIPPED_MODEL
    p = Path(path)
    if p.is_dir():
        for name in RUN_FILES:
            if (p / name).exists():
                return p / name
        raise ConfigError(
            f"{p}: holds none of {', '.join(RUN_FILES)}; accepted: a training run folder or a model file"
        )
    if not p.exists():
        raise ConfigError(f"{p}: no such model file; accepted: a .onnx or .pt file written by `rebar train`")
    if p.suffix not in (".onnx", ".pt"):
        raise ConfigError(f"{p}: model files end in .onnx or .pt, not {p.suffix or 'nothing'}")
    return p


class Detector:
    """A loaded keypoint detector; set a stage to None to leave it out.

    Attributes:
        path: The file it was loaded from (None for a network in memory).
        meta: What the model file says about itself (training data, settings, scores).
        backend: What runs the first stage: ``onnxruntime``, ``openvino`` or ``torch``.
        score_bias: Logit shift of the heatmap that puts the operating point at score 0.5 (chosen on val).
        score_bias_without_depth: The same for a call without a depth image.
        refiner: The second stage: moves each detection onto its crossing and verifies it.
        depth_check: Lowers the score of a detection whose depth patch shows no crossing (given depth).
        depth_power: How hard the depth check counts.
        verify_power: How hard the second stage's verification counts (``verify_power_with_depth`` beside
            the depth check).
        crossing_point: Where each detection's 3D crossing point projects (``point="crossing"``).
        line_check: Weighs each score with the scores along the detection's two bars (without depth).
        reading: "mirrored" (the first stage also reads the mirror image and takes the mean) or "single".
        focal_px: The focal length (pixels) the first stage trained at (None: unknown).
        resample: Whether ``detect`` reads a frame at ``focal_px`` when its camera's focal length differs.
        flatten_behind: Whether ``detect``, given depth, first takes what lies far behind the front bars out
            of the colour image (off by default: it needs depth registered to colour within a pixel).
    """

    def __init__(
        self,
        run: Callable[[np.ndarray, np.ndarray], np.ndarray],
        *,
        meta: dict[str, Any],
        backend: str,
        path: Path | None,
    ):
        self._run = run
        # the first stage on a batch of two images and their rays, where the runtime takes one; None: two calls
        self._run_pair: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
        self.meta = meta
        self.reading: str = "single"
        self.score_bias = float(meta.get("score_bias", 0.0))
        self.score_bias_without_depth = float(meta.get("score_bias_without_depth", self.score_bias))
        self.verify_power = float((meta.get("refiner") or {}).get("verify_power", 1.0))
        self.verify_power_with_depth = float(
            (meta.get("refiner") or {}).get("verify_power_with_depth", self.verify_power)
        )
        self.backend = backend
        self.path = path
        self._rays: dict[tuple, np.ndarray] = {}
        self.refiner: Refiner | None = None
        self.depth_check: DepthCheck | None = None
        self.depth_power = float((meta.get("depth_check") or {}).get("power", 1.0))
        self.crossing_point: CrossingPoint | None = None
        self.line_check: LineCheck | None = None
        focal = meta.get("focal_px")
        self.focal_px: float | None = float(focal) if focal else None
        self.resample = True
        self.flatten_behind = False

    @classmethod
    def load(
        cls,
        path: str | Path | None = None,
        *,
        threads: int = 2,
        line_check: bool = True,
        runtime: str = "auto",
        reading: str = "mirrored",
    ) -> Detector:
        """Load a detector.

        Args:
            path: A ``.onnx`` or ``.pt`` file, or a training run folder (its ``best.onnx``); None loads the
                model shipped with the package.
            threads: CPU threads for inference.
            line_check: Load the file's line check; False leaves it out (to fit a new one, whatever the
                file holds).
            runtime: What runs an ``.onnx`` file's float stages (:mod:`~rebar_data.perception.inference.model_file`):
                "auto" (OpenVINO in bfloat16 where the CPU has it), "onnxruntime" or "openvino".
            reading: How the stages read an image: "mirrored" or "single" (the ``reading`` attribute).
        """
        check_reading(reading)
        p = resolve_model_path(path)
        if p.suffix != ".onnx":
            raise ConfigError(
                f"{p}: Detector.load reads .onnx files; accepted: a .onnx file, or a .pt checkpoint through "
                "rebar_data.perception.training.train.load_detector"
            )
        det = cls._load_onnx(p, threads, resolve_runtime(runtime))
        det.attach_line_check(line_check)
        det.reading = reading
        return det

    def attach_line_check(self, wanted: bool = True) -> None:
        """Load the line check the model's meta names (``wanted``: False leaves it out)."""
        entry = self.meta.get("line_check")
        if wanted and entry:
            self.line_check = LineCheck.from_meta(entry, str(self.path))

    @classmethod
    def _load_onnx(cls, path: Path, threads: int, runtime: str) -> Detector:
        sess = onnx_session(path, threads, runtime)
        raw = sess.get_modelmeta().custom_metadata_map.get(META_KEY)
        names = [i.name for i in sess.get_inputs()]

        def run_batch(images: np.ndarray, rays: np.ndarray) -> np.ndarray:
            feed = {names[0]: images}
            if len(names) > 1:
                feed[names[1]] = rays
            return sess.run(None, feed)[0]

        def run(image: np.ndarray, rays: np.ndarray) -> np.ndarray:
            return run_batch(image[None], rays[None])[0]

        det = cls(run, meta=json.loads(raw) if raw else {}, backend=runtime, path=path)
        # the files take one image a call; OpenVINO compiles them for two, ONNX Runtime does not
        det._run_pair = run_batch if runtime == "openvino" else None
        det.refiner = load_refiner(path, det.meta, threads, runtime)
        det.depth_check = load_depth_check(path, det.meta, threads, runtime)
        det.crossing_point = load_crossing_point(path, det.meta, threads, runtime)
        return det

    @contextmanager
    def first_stage_only(self) -> Iterator[Detector]:
        """Within the block, ``detect`` gives the heatmap network's positions alone (to measure what the
        later stages add or cost); they are back afterwards."""
        refiner, self.refiner = self.refiner, None
        depth_check, self.depth_check = self.depth_check, None
        line_check, self.line_check = self.line_check, None
        try:
            yield self
        finally:
            self.refiner, self.depth_check, self.line_check = refiner, depth_check, line_check

    @contextmanager
    def flattening(self, on: bool = True) -> Iterator[Detector]:
        """Within the block, ``flatten_behind`` is ``on`` (:mod:`rebar_data.perception.inference.image`); afterwards it
        is as it was."""
        before, self.flatten_behind = self.flatten_behind, on
        try:
            yield self
        finally:
            self.flatten_behind = before

    def default_camera(self, height: int, width: int) -> tuple[float, float, float, float]:
        """Intrinsics assumed when the caller gives none: principal point at the image centre and the
        training data's focal length for this image width."""
        f = float(self.meta.get("focal_per_width", DEFAULT_FOCAL_PER_WIDTH)) * width
        return f, f, width / 2.0, height / 2.0

    def _ray_grid(self, height: int, width: int, camera: tuple[float, float, float, float]) -> np.ndarray:
        key = (height, width, *camera)
        if key not in self._rays:
            if len(self._rays) > 8:
                self._rays.clear()
            self._rays[key] = ray_grid(height, width, camera)
        return self._rays[key]

    def raw(self, rgb: np.ndarray, *, camera: tuple[float, float, float, float] | None = None) -> np.ndarray:
        """The network's (3, ceil(H/4), ceil(W/4)) output for an RGB image: heatmap logit and offsets (in
        the mirrored reading, the mean of the image's and its mirror image's, turned back)."""
        image = _check_image(rgb)
        h, w = image.shape[:2]
        camera = tuple(float(c) for c in camera) if camera is not None else self.default_camera(h, w)
        ph, pw = -h % INPUT_MULTIPLE, -w % INPUT_MULTIPLE
        if ph or pw:
            image = np.pad(image, ((0, ph), (0, pw), (0, 0)))
        rays = self._ray_grid(h + ph, w + pw, camera)  # rays of the output cells
        if check_reading(self.reading) == "mirrored":
            out = self._read_with_mirror(image, rays, camera)
        else:
            out = self._run(image, rays)
        return out[:, : -(-h // STRIDE), : -(-w // STRIDE)]

    def _read_with_mirror(
        self, image: np.ndarray, rays: np.ndarray, camera: tuple[float, float, float, float]
    ) -> np.ndarray:
        """The mean of the network's outputs for the padded ``image`` (its cells' ``rays``) and for the image
        turned left for right, turned back: cell for cell with the image's own output (the padded width is
        a whole number of cells), the column offsets still measured in the mirror image's direction. The
        camera turns with the image (its principal point mirrored), so each cell's viewing ray is its own
        turned. Both go through the network in one call of two where the runtime takes a batch
        (``_run_pair``), in two calls otherwise: the same numbers either way."""
        hp, wp = image.shape[:2]
        mirror = cv2.flip(image, 1)
        mirror_rays = self._ray_grid(hp, wp, mirrored_camera(camera, wp))
        if self._run_pair is not None:
            out, mirrored = self._run_pair(np.stack([image, mirror]), np.stack([rays, mirror_rays]))
        else:
            out, mirrored = self._run(image, rays), self._run(mirror, mirror_rays)
        return mean_with_mirror(out, mirrored[:, :, ::-1])

    def detect(
        self,
        rgb: np.ndarray,
        *,
        threshold: float = OPERATING_THRESHOLD,
        camera: tuple[float, float, float, float] | None = None,
        depth: np.ndarray | None = None,
        max_detections: int = 1000,
        point: str = "sight",
    ) -> np.ndarray:
        """Crossings in an RGB image.

        Args:
            rgb: (H, W, 3) uint8 RGB image, any size.
            depth: The depth image registered to it, (H, W) float metres or uint16 millimetres (0 = no
                measurement), for the third stage when the model has one; None skips that stage.
            threshold: Lowest score returned; the default is the operating point the metrics report.
            camera: Intrinsics (fx, fy, cx, cy) in pixels, COCO corner origin; None assumes the principal
                point at the centre and the training data's focal length for this width (its field of
                view). A frame whose focal length is not the one the detector trained at is read resized
                to it (``resample``; :mod:`~rebar_data.perception.inference.image`).
            max_detections: Most crossings returned.
            point: What u, v stand for: ``"sight"``, where the image shows the two bars cross (the
                dataset's labels); ``"crossing"``, where the 3D crossing point (the centerlines' midpoint,
                inside the steel) projects, from the crossing-point stage (the model must have one).

        Returns:
            (N, 3) float64 array of u, v, score, best first; u, v in the image's pixels (COCO corner origin).
        """
        if not 0.0 < threshold < 1.0:
            raise ConfigError(f"threshold = {threshold} is not accepted; accepted: a score between 0 and 1")
        if check_point(point) == "crossing" and self.crossing_point is None:
            raise ConfigError(
                f"{self.path or 'this detector'}: has no crossing-point stage; accepted: point='sight', or a "
                "model trained with one (crossing_point: {enabled: true}, as `make train` ships)"
            )
        image = _check_image(rgb)
        h, w = image.shape[:2]
        camera = tuple(float(c) for c in camera) if camera is not None else self.default_camera(h, w)
        depth_m = as_depth_m(depth, (h, w)) if depth is not None else None
        scale = focal_scale(self.focal_px, camera) if self.resample else 1.0
        if scale == 1.0:
            return self._detect_as_is(image, camera, depth_m, threshold, max_detections, point)
        size = resampled_size(h, w, scale)
        sx, sy = size[1] / w, size[0] / h  # exact, once the sizes are rounded
        det = self._detect_as_is(
            resample(image, size),
            scaled_camera(camera, sx, sy),
            None if depth_m is None else resample(depth_m, size, nearest=True),
            threshold,
            max_detections,
            point,
        )
        det[:, 0] /= sx
        det[:, 1] /= sy
        return det

    def _detect_as_is(
        self,
        image: np.ndarray,
        camera: tuple[float, float, float, float],
        depth_m: np.ndarray | None,
        threshold: float,
        max_detections: int,
        point: str,
    ) -> np.ndarray:
        """``detect`` on ``image`` at the scale it comes in (``depth_m`` in metres, or None)."""
        h, w = image.shape[:2]
        checked = depth_m is not None and self.depth_check is not None
        as_it_comes = image  # what the crossing-point stage trained on
        if depth_m is not None and self.flatten_behind:
            image = flatten_behind(image, depth_m)
        out = self.raw(image, camera=camera)
        if self.line_check is not None and not checked:
            lc = self.line_check
            inputs = self._line_pass(
                image, out, lc.floor, lc.checked_from, lc, threshold=threshold, max_detections=max_detections
            )
            det = np.c_[inputs.placed, inputs.scores]
        else:
            det = self._rgb_and_depth(image, out, depth_m, threshold=threshold, max_detections=max_detections)
        det = det[det[:, 2] >= threshold]
        det = det[np.argsort(-det[:, 2], kind="stable")]
        inside = (det[:, 0] >= 0) & (det[:, 0] < w) & (det[:, 1] >= 0) & (det[:, 1] < h)
        # a crossing seen inside the frame stays, wherever its 3D point projects
        det = drop_duplicates(det[inside], DUPLICATE_PX)
        if point == "crossing" and len(det):
            det[:, :2] = self.crossing_point.points(as_it_comes, det[:, :2], camera)
        return det

    def _rgb_and_depth(
        self,
        image: np.ndarray,
        out: np.ndarray,
        depth_m: np.ndarray | None,
        *,
        threshold: float,
        max_detections: int,
    ) -> np.ndarray:
        """(N, 3) u, v, score of the first stage's output ``out`` read on: the second stage, then the depth
        check when ``depth_m`` is given and the model has one; unsorted, some under ``threshold``."""
        checked = depth_m is not None and self.depth_check is not None
        bias = self.score_bias if checked else self.score_bias_without_depth
        det = decode(out[0] + bias, out[1:], threshold=threshold, max_detections=max_detections)
        log_p = np.zeros(len(det))  # the second stage's log-probability of a crossing (0: no verification)
        if self.refiner is not None and len(det):
            det[:, :2], verify = self.refiner.refine_and_verify(
                image,
                det[:, :2],
                keep=lambda logit: self._may_reach(det[:, 2], logit, threshold, checked=checked, bias=bias),
                **self._refiner_reading(),
            )
            if verify is not None:
                log_p = log_probability(verify)
        power = np.full(len(det), self.verify_power)  # the verification's weight, per detection
        if checked and len(det):
            logit = self.depth_check.logits(depth_m, det[:, :2])
            measured = np.isfinite(logit)
            power[measured] = self.verify_power_with_depth
            det[measured, 2] = verified_score(det[measured, 2], logit[measured], power=self.depth_power)
            # no measurement to check (too near or far for the sensor): scored as without depth, with the
            # RGB stages' operating point and weight of the verification
            det[~measured, 2] = shifted_score(det[~measured, 2], self.score_bias_without_depth - bias)
        det[:, 2] = shifted_score(det[:, 2], power * log_p)
        return det

    def line_inputs(
        self,
        rgb: np.ndarray,
        floor: float,
        checked_from: float,
        *,
        camera: tuple[float, float, float, float] | None = None,
    ) -> LineInputs:
        """What a line check with these first-stage scores (``LineCheckConfig``) reads in an image without
        depth (:class:`LineInputs`; the second stage's later passes move every checked candidate); its
        ``scores`` are the RGB stages'. For fitting the check."""
        image = _check_image(rgb)
        h, w = image.shape[:2]
        camera = tuple(float(c) for c in camera) if camera is not None else self.default_camera(h, w)
        out = self.raw(image, camera=camera)
        return self._line_pass(image, out, floor, checked_from, None, threshold=floor, max_detections=1000)

    def _line_pass(
        self,
        image: np.ndarray,
        out: np.ndarray,
        floor: float,
        checked_from: float,
        check: LineCheck | None,
        *,
        threshold: float,
        max_detections: int,
    ) -> LineInputs:
        """The RGB stages and the line check ``check`` (None: none) on the first stage's output ``out``:
        every candidate it scores ``floor`` or more inside the frame is evidence, those it scores
        ``checked_from`` or more are verified by the second stage and checked; the later passes move those
        the check scores ``threshold`` or more (all of them without a check)."""
        det = decode(
            out[0] + self.score_bias_without_depth, out[1:], threshold=floor, max_detections=max_detections
        )
        h, w = image.shape[:2]
        det = det[(det[:, 0] >= 0) & (det[:, 0] < w) & (det[:, 1] >= 0) & (det[:, 1] < h)]
        evidence = det[:, 2].copy()
        checked = np.flatnonzero(evidence >= checked_from)
        scores: list[np.ndarray] = []

        def read(verify_logit: np.ndarray | None) -> np.ndarray:
            if verify_logit is not None:
                evidence[checked] = shifted_score(
                    det[checked, 2], self.verify_power * log_probability(verify_logit)
                )
            if check is None:
                scores.append(evidence[checked])
            else:
                scores.append(check.scores(image, det[:, :2], evidence, checked, threshold=threshold))
            return scores[-1]

        placed = det[checked, :2]
        if self.refiner is not None and len(checked):
            keep = None if check is None else (lambda logit: read(logit) >= threshold)
            placed, verify = self.refiner.refine_and_verify(
                image, placed, keep=keep, **self._refiner_reading()
            )
            if not scores:
                read(verify)
        elif not scores:
            read(None)
        return LineInputs(det[:, :2], evidence, checked, placed, scores[-1])

    def _refiner_reading(self) -> dict[str, Any]:
        """How the second stage reads in this detector's reading (``refine_and_verify``'s arguments)."""
        if check_reading(self.reading) == "mirrored":
            return {"later_views": MIRRORED_LATER_VIEWS, "int8_first_pass": True}
        return {}

    def _may_reach(
        self, score: np.ndarray, verify_logit: np.ndarray, threshold: float, *, checked: bool, bias: float
    ) -> np.ndarray:
        """Which of the first stage's detections (``score``, read with the score bias ``bias``) can still
        score ``threshold`` once the second stage's verification (``verify_logit``) counts: the highest
        final score each can reach, whatever the depth check says (it only lowers a score, and a detection
        it has no measurement for is scored as without depth). The later passes are spent on these alone;
        the others never reach the caller."""
        log_p = log_probability(verify_logit)
        best = self.verify_power * log_p
        if checked:
            best = np.maximum(
                self.verify_power_with_depth * log_p,
                self.score_bias_without_depth - bias + self.verify_power * log_p,
            )
        # a hair above the best: rounding never spares a detection that reaches the threshold
        return shifted_score(score, best + 1e-6) >= threshold


@dataclass(frozen=True)
class LineInputs:
    """One image's candidates as the line check reads them (``Detector.line_inputs``).

    Attributes:
        uv: (N, 2) every candidate the first stage scores the check's floor or more inside the frame, where it
            puts them.
        evidence: (N,) each one's score as evidence for the others: the RGB stages' score for the checked
            ones, the first stage's for the rest.
        checked: (K,) the indices of those the first stage scores the check's ``checked_from`` or more.
        placed: (K, 2) where the second stage places the checked ones.
        scores: (K,) their scores: the line check's, or the RGB stages' when there is none.
    """

    uv: np.ndarray
    evidence: np.ndarray
    checked: np.ndarray
    placed: np.ndarray
    scores: np.ndarray


def drop_duplicates(det: np.ndarray, radius_px: float) -> np.ndarray:
    """``det`` (N, 3) u, v, score, best first, without each detection nearer than ``radius_px`` to a
    better one (the better stays)."""
    if len(det) < 2:
        return det
    d = np.hypot(*(det[:, None, :2] - det[None, :, :2]).transpose(2, 0, 1))
    near = np.triu(d < radius_px, k=1)  # near[i, j]: j (worse) lies within the radius of i (better)
    keep = np.ones(len(det), bool)
    for i in range(len(det)):
        if keep[i]:
            keep[near[i]] = False
    return det[keep]


def verified_score(score: np.ndarray, verify_logit: np.ndarray, *, power: float = 1.0) -> np.ndarray:
    """A detection's score after the second stage's verification: sigmoid(logit(score) + power * log p),
    with p the second stage's probability that the patch shows a crossing (``RefineConfig.verify_power``
    and ``verify_power_with_depth`` say which powers ship, and why). It only lowers scores (p <= 1), so a
    threshold applied to the first stage's scores loses nothing, and a shift of the first stage's logits
    (the score bias) shifts the final logits alike."""
    return shifted_score(score, power * log_probability(verify_logit))


def log_probability(logit: np.ndarray) -> np.ndarray:
    """log sigmoid(``logit``), without overflow."""
    return -np.logaddexp(0.0, -np.asarray(logit, np.float64))


def shifted_score(score: np.ndarray, shift: float | np.ndarray) -> np.ndarray:
    """sigmoid(logit(score) + shift): a score read with a score bias ``shift`` higher."""
    s = np.clip(np.asarray(score, np.float64), 1e-12, 1.0 - 1e-12)
    return 1.0 / (1.0 + np.exp(-(np.log(s) - np.log1p(-s) + shift)))


def _check_image(rgb: np.ndarray) -> np.ndarray:
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ConfigError(f"image of shape {a.shape} is not accepted; accepted: an (H, W, 3) RGB array")
    if a.dtype != np.uint8:
        if np.issubdtype(a.dtype, np.floating) and a.size and a.max() <= 1.0:
            a = a * 255.0
        a = np.clip(np.rint(a), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(a)
