"""Run the detector on an image: ``Detector.load(path).detect(rgb) -> (N, 3)`` u, v, score.

``.onnx`` files (the shipped model is one; several times faster than eager PyTorch on a CPU) run in OpenVINO
in bfloat16 where the CPU has it and in ONNX Runtime otherwise (:mod:`~rebar_data.perception.inference.runtime`);
``.pt`` checkpoints run in PyTorch. Coordinates are in the input image's pixels with COCO's corner
origin (the top-left corner of the top-left pixel is (0, 0)), as everywhere in the project.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from rebar_data.errors import ConfigError
from rebar_data.perception.inference.behind import flatten_behind
from rebar_data.perception.inference.crossing_point import CrossingPoint, check_point
from rebar_data.perception.inference.depth_check import DepthCheck, as_depth_m
from rebar_data.perception.inference.focal import focal_scale, resample, resampled_size, scaled_camera
from rebar_data.perception.inference.heatmap import (
    INPUT_MULTIPLE,
    OPERATING_THRESHOLD,
    STRIDE,
    decode,
    ray_grid,
)
from rebar_data.perception.inference.line_check import LineCheck
from rebar_data.perception.inference.model_file import (
    META_KEY,
    load_crossing_point,
    load_depth_check,
    load_refiner,
)
from rebar_data.perception.inference.reading import (
    MIRRORED_LATER_VIEWS,
    check_reading,
    mean_with_mirror,
    mirrored_camera,
)
from rebar_data.perception.inference.refine import Refiner
from rebar_data.perception.inference.runtime import onnx_session, resolve_runtime

DEFAULT_FOCAL_PER_WIDTH = 525.0 / 640.0  # Kinect v1 colour camera, when neither caller nor model says
MODELS_DIR = Path(__file__).parent.parent / "models"
SHIPPED_MODEL = MODELS_DIR / "rebar_keypoint.onnx"
RUN_FILES = ("best.onnx", "best.pt", "last.pt")
# two detections placed nearer than this are one crossing (the second stage's passes can move two
# detections of one crossing onto it); no two visible crossings of paper-tunnel's test split lie nearer
# than 7.5 px
DUPLICATE_PX = 3.0


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
    """A loaded keypoint detector.

    Attributes:
        path: The file it was loaded from (None when built from a network in memory).
        meta: What the model file says about itself (training data, settings, scores).
        backend: what runs the first stage: ``onnxruntime``, ``openvino`` or ``torch``.
        score_bias: Logit shift applied to the heatmap before scores are read (``meta["score_bias"]``,
            chosen on the validation split so that score 0.5 is the operating point; 0 when absent).
        score_bias_without_depth: The same for a call without a depth image, when the model has a depth
            check (it removes false detections, so its operating point lies elsewhere).
        refiner: The second stage, which moves each detection to the crossing its full-resolution patch
            shows (:mod:`rebar_data.perception.inference.refine`); loaded with the model when the file names one.
            Set it to None to get the heatmap network's positions alone.
        depth_check: The third stage, which lowers the scores of detections whose depth patch shows no
            crossing (:mod:`rebar_data.perception.inference.depth_check`); used when ``detect`` gets a depth image.
        depth_power: How hard the third stage counts (``meta["depth_check"]["power"]``).
        verify_power: How hard the second stage's verification counts without the depth check
            (``RefineConfig.verify_power``); ``verify_power_with_depth`` beside it.
        crossing_point: The stage that gives where each detection's 3D crossing point projects
            (:mod:`rebar_data.perception.inference.crossing_point`); used when ``detect`` is asked for
            ``point="crossing"``.
        line_check: Weighs each detection's score with the scores along its two bars
            (:mod:`rebar_data.perception.inference.line_check`; ``meta["line_check"]``); used when ``detect`` gets
            no depth image. Set it to None to get the RGB stages' scores alone.
        reading: How the stages read an image, "mirrored" or "single" (:mod:`rebar_data.perception.inference.reading`;
            ``Detector.load``'s default is "mirrored", a network in memory's "single").
        focal_px: The focal length (pixels) its first stage trained at (``meta["focal_px"]``; None for a file
            written before it was stored).
        resample: Whether ``detect`` resizes a frame taken with another focal length to ``focal_px`` before
            reading it (:mod:`rebar_data.perception.inference.focal`; on by default). Positions come back in the
            caller's pixels either way.
        flatten_behind: Whether ``detect``, given a depth image, first takes what lies far behind the bars
            in front out of the colour image (:mod:`rebar_data.perception.inference.behind`). Off by default: it
            places crossings better on every held-out set, but needs the depth image registered to the
            colour one within about a pixel, and doubled the paper servo run's worst PBVS error (the module
            text has the figures).
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
        # the first stage on a batch of two images and their rays, where the runtime takes one (a frame and
        # its mirror image in one call: 1.03-1.06 times as fast on 2 cores, the same numbers); None: two calls
        self._run_pair: Callable[[np.ndarray, np.ndarray], np.ndarray] | None = None
        self.meta = meta
        self.reading: str = "single"
        self.score_bias = float(meta.get("score_bias", 0.0))
        # the operating point of the RGB stages alone, when a depth check changed the other one
        self.score_bias_without_depth = float(meta.get("score_bias_without_depth", self.score_bias))
        # how hard the second stage's verification counts (files written before it was stored: fully), and
        # how hard beside the depth check (files written before it was stored: as without)
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
        # the focal length its first stage trained at (files written before it was stored: unknown), and
        # whether ``detect`` reads a frame taken with another at that one (:mod:`~rebar_data.perception.inference.focal`)
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
            runtime: What runs an ``.onnx`` file's float stages (:mod:`~rebar_data.perception.inference.runtime`):
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
        """Within the block, ``flatten_behind`` is ``on`` (:mod:`rebar_data.perception.inference.behind`); afterwards it
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
                to it (``resample``; :mod:`~rebar_data.perception.inference.focal`).
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
