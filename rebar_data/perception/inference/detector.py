"""The detector: ``Detector.load(path).detect(rgb) -> (N, 3)`` u, v, score, best first (COCO's corner origin).

A heatmap network at stride 4 gives the candidates, the second stage (:mod:`.refine`) moves and verifies them,
the checks (:mod:`.checks`) score them again.

:meth:`Detector.load` is the one way in for every caller (the CLI, the servo, the gate, training). It reads an
``.onnx`` model itself; a ``.pt`` checkpoint runs in PyTorch through training code, which the run time may not
import, so :data:`READERS` names that reader as a string and imports it only when such a file is loaded. Why
by name and not a registry that training fills in: a registry would be empty until some caller had imported
training, so ``Detector.load("best.pt")`` would work or not by what ran before it; by name it works for every
caller, and loading an ``.onnx`` file still imports neither torch nor training (``tests/integration/test_imports.py``)."""

from __future__ import annotations

import importlib
import json
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Literal, get_args

import cv2
import numpy as np

from rebar_data.camera import Intrinsics
from rebar_data.errors import ConfigError
from rebar_data.perception.inference import model_file
from rebar_data.perception.inference.checks import DepthCheck, LineCheck, as_depth_m
from rebar_data.perception.inference.image import flatten_behind, focal_scale, resample
from rebar_data.perception.inference.refine import CrossingPoint, Refiner, accepted

STRIDE = 4
INPUT_MULTIPLE = 16  # the encoder halves the size four times
OPERATING_THRESHOLD = 0.5  # the score ``detect`` returns from by default, and the metrics' operating point
# "mirrored": the first stage also reads the mirror image and takes the mean, the second stage reads its int8
# copy in every pass and its later passes in one view; "single": each reads the image once
Reading = Literal["mirrored", "single"]
READINGS: tuple[str, ...] = get_args(Reading)
POINTS = ("sight", "crossing")  # what a detection's pixel stands for
DEFAULT_FOCAL_PER_WIDTH = 525.0 / 640.0  # Kinect v1 colour camera, when neither caller nor model says
MODELS_DIR = Path(__file__).parent.parent / "models"
SHIPPED_MODEL = MODELS_DIR / "rebar_keypoint.onnx"
RUN_FILES = ("best.onnx", "best.pt", "last.pt")
# the readers of the model files the run time does not read itself, by suffix: "module:function", imported
# when such a file is loaded (why by name: the module's docstring)
READERS = {".pt": "rebar_data.perception.training.checkpoint:read_detector_checkpoint"}
DUPLICATE_PX = 3.0  # two detections placed nearer than this are one crossing
Run = Callable[[np.ndarray, np.ndarray], np.ndarray]  # the first stage: images and rays to its output


@dataclass(frozen=True)
class Zoom:
    """Reading a frame whose crossings are seen small a second time, larger, and one whose crossings are seen
    large a second time, smaller. The first reading's detections (those the RGB stages score at the operating
    point or more, at least ``min_detections``) give their box sides from the second stage's size output
    (four bar diameters, in the pixels of the frame as read). Where their median is under ``below_px``, the
    frame is read again at ``to_px`` over that median times its scale, at most ``at_most`` times; where it is
    over ``above_px`` (None: never), at ``shrink_to_px`` over it, at least ``at_least`` times. Measured in
    docs/detector/experiments.md ("Far, thin bars read larger", "Heavy bars read smaller"):

    - The size output reads small crossings large and large ones small (it learnt from crossings of about
      25-100 px): on far-light-bars' frames (labelled medians 11.5-20.5 px) it gives 16-30.5 px, on the gate
      set's (34.6-72 px) 33.6-73 px, on the tests' rendered frame (31.5 px) 29 px and drawn frame (25.6 px)
      25.1 px, on heavy-bars' (43-300 px) 41-113 px. So it cannot part a frame of 20 px crossings from one of
      25 px: under 24 px are most of far-light-bars' frames, and none whose crossings the first stage reads
      well.
    - Far thin bars (8-10 mm at 1.0-1.5 m) read 1.6 times larger are found and placed as near ones are:
      recall@P0.99 0.55 to 0.85 with sensor depth. Past 1.6 times the gain in placement comes with
      confident false detections.
    - Heavy bars near (25-40 mm at 0.3-1.5 m) read smaller: PCK@2px 0.822 to 0.867, recall@P0.99 0.809 to
      0.833; the gate set, a tenth of whose frames this reads smaller, 0.967 to 0.970.

    A frame read twice costs the second reading again (1.6 times larger: 2.6 times the pixels)."""

    below_px: float = 24.0
    to_px: float = 40.0
    at_most: float = 1.6
    min_detections: int = 3
    above_px: float | None = 60.0
    shrink_to_px: float = 45.0
    at_least: float = 0.5

    def factor(self, box: np.ndarray | None) -> float:
        """How much larger (or, under 1, smaller) to read the frame again (1: not again), from the first
        reading's box sides."""
        if box is None or len(box) < self.min_detections:
            return 1.0
        median = float(np.median(box))
        if 0.0 < median < self.below_px:
            return float(min(self.at_most, self.to_px / median))
        if self.above_px is not None and median > self.above_px:
            return float(max(self.at_least, self.shrink_to_px / median))
        return 1.0


def first_stage_rays(camera: Intrinsics) -> np.ndarray:
    """(2, ceil(H / 4), ceil(W / 4)) float32 viewing rays ((u - cx) / fx, (v - cy) / fy) of the output cells'
    centres: what the first stage reads beside the image."""
    return camera.ray_grid(STRIDE).astype(np.float32)


def decode(
    heat_logit: np.ndarray, offset: np.ndarray, *, threshold: float, max_detections: int = 1000
) -> np.ndarray:
    """(N, 3) u, v, score of the 3x3 local maxima of the heatmap logits (H, W) scoring ``threshold`` or more,
    moved by their offsets (2, H, W; in cells), best first. Peaks are found on logits, which never tie."""
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


def score_bias_of(meta: dict[str, Any]) -> float:
    """The operating point's heatmap logit shift a model file's ``meta`` gives (0 for a model without one)."""
    return float(meta.get("score_bias", 0.0))


class Detector:
    """A loaded keypoint detector: its model file's ``meta``, the ``backend`` running the first stage
    (onnxruntime, openvino or torch) and its later stages (None: left out). ``reading`` is one of
    :data:`READINGS`; ``resample`` reads a frame resized to the trained ``focal_px`` (off: every frame at its
    own scale, the zoom too); ``flatten_behind``, given depth, takes what lies far behind the front bars out
    of the image first; ``zoom`` reads a frame whose crossings are seen small (or large) again, larger (or
    smaller) (None: never)."""

    def __init__(self, run: Run, *, meta: dict[str, Any], backend: str, path: Path | None):
        self._run = run
        self._run_pair: Run | None = None  # reads a batch of two
        self.meta = meta
        self.backend = backend
        self.path = path
        self.reading: str = "single"
        # the heatmap logit shift that puts the operating point at 0.5
        self.score_bias = score_bias_of(meta)
        # how hard the verification counts in a score
        self.verify_power = float((meta.get("refiner") or {}).get("verify_power", 1.0))
        self.refiner: Refiner | None = None
        self.depth_check: DepthCheck | None = None
        self.crossing_point: CrossingPoint | None = None
        self.line_check = (
            LineCheck.from_meta(meta["line_check"], str(path)) if meta.get("line_check") else None
        )
        self.focal_px: float | None = float(meta["focal_px"]) if meta.get("focal_px") else None
        self.resample = True
        self.flatten_behind = False
        self.zoom: Zoom | None = Zoom()  # None: every frame read once, at the trained scale

    @classmethod
    def load(
        cls,
        path: str | Path | None = None,
        *,
        threads: int = 2,
        runtime: str = "auto",
        reading: str = "mirrored",
        resample: bool = True,
        flatten_behind: bool = False,
        zoom: bool = True,
    ) -> Detector:
        """The one way to load a detector: ``path`` a ``.onnx`` model file with its later stages beside it, a
        ``.pt`` checkpoint (run in PyTorch, :data:`READERS`), a training run folder (its best model) or None
        (the shipped model). ``runtime`` runs an ``.onnx`` file: "auto", "onnxruntime" or "openvino"
        (:mod:`.model_file`); ``reading``, ``resample`` and ``flatten_behind`` as the attributes say; ``zoom``
        False reads every frame once (:class:`Zoom`)."""
        accepted("reading", reading, READINGS)
        p = resolve_model_path(path)
        read = _reader(p) if p.suffix in READERS else cls._read_onnx
        det = read(p, threads=threads, runtime=runtime)
        det.reading, det.resample, det.flatten_behind = reading, resample, flatten_behind
        det.zoom = det.zoom if zoom else None
        return det

    @classmethod
    def _read_onnx(cls, p: Path, *, threads: int, runtime: str) -> Detector:
        """The detector in the ``.onnx`` file ``p`` with its later stages."""
        runtime = model_file.resolve_runtime(runtime)
        sess = model_file.onnx_session(p, threads, runtime)
        raw = sess.get_modelmeta().custom_metadata_map.get(model_file.META_KEY)
        run_batch = model_file.session_run(sess)  # images, and rays where the first stage reads them
        meta = model_file.check_format(json.loads(raw) if raw else {}, p)
        det = cls(
            lambda image, rays: run_batch(image[None], rays[None])[0], meta=meta, backend=runtime, path=p
        )
        det._run_pair = run_batch if runtime == "openvino" else None  # compiled for two; ONNX Runtime: one
        det.refiner, det.depth_check, det.crossing_point = model_file.load_stages(
            p, det.meta, threads, runtime
        )
        return det

    def default_camera(self, height: int, width: int) -> Intrinsics:
        """The principal point at the centre and the training data's focal length for this width."""
        f = float(self.meta.get("focal_per_width", DEFAULT_FOCAL_PER_WIDTH)) * width
        return Intrinsics(width, height, f, f, width / 2.0, height / 2.0)

    def _camera(self, image: np.ndarray, camera: Intrinsics | Sequence[float] | None) -> Intrinsics:
        h, w = image.shape[:2]
        if camera is None:
            return self.default_camera(h, w)
        if isinstance(camera, Intrinsics):
            if (camera.width, camera.height) != (w, h):
                raise ConfigError(
                    f"camera: intrinsics of a {camera.width}x{camera.height} image for a {w}x{h} one; "
                    "accepted: the image's own, or (fx, fy, cx, cy)"
                )
            camera = (camera.fx, camera.fy, camera.cx, camera.cy)
        fx, fy, cx, cy = (float(c) for c in camera)
        return Intrinsics(w, h, fx, fy, cx, cy)

    def raw(self, rgb: np.ndarray, *, camera: Intrinsics | Sequence[float] | None = None) -> np.ndarray:
        """The first stage's (3, ceil(H/4), ceil(W/4)) output: heatmap logit and offsets (mirrored reading:
        the mean of the image's and its mirror image's, turned back). ``camera`` as :meth:`detect` takes it."""
        accepted("reading", self.reading, READINGS)
        image = _check_image(rgb)
        h, w = image.shape[:2]
        camera = self._camera(image, camera)
        ph, pw = -h % INPUT_MULTIPLE, -w % INPUT_MULTIPLE
        if ph or pw:
            image = np.pad(image, ((0, ph), (0, pw), (0, 0)))
        padded = replace(camera, width=w + pw, height=h + ph)  # the padding adds pixels, moves none
        rays = first_stage_rays(padded)
        if self.reading == "mirrored":
            mirror = cv2.flip(image, 1)
            mirror_rays = first_stage_rays(padded.mirrored())
            if self._run_pair is not None:
                out, mirrored = self._run_pair(np.stack([image, mirror]), np.stack([rays, mirror_rays]))
            else:
                out, mirrored = self._run(image, rays), self._run(mirror, mirror_rays)
            mirrored = mirrored[:, :, ::-1]
            mean = 0.5 * (out + mirrored)
            # a column offset read in the mirror image points the other way
            mean[1] = 0.5 * (out[1] - mirrored[1])
            out = mean
        else:
            out = self._run(image, rays)
        return out[:, : -(-h // STRIDE), : -(-w // STRIDE)]

    def detect(
        self,
        rgb: np.ndarray,
        *,
        threshold: float = OPERATING_THRESHOLD,
        camera: Intrinsics | Sequence[float] | None = None,
        depth: np.ndarray | None = None,
        point: str = "sight",
    ) -> np.ndarray:
        """(N, 3) float64 u, v, score of the crossings in an (H, W, 3) uint8 RGB image, best first, scoring
        ``threshold`` or more. ``camera``: the image's :class:`~rebar_data.camera.Intrinsics` or its
        (fx, fy, cx, cy) in pixels, None: :meth:`default_camera`. ``depth``: the registered depth image,
        (H, W) float metres or uint16 millimetres (0 = none): the depth check then lowers the scores it
        doubts, and raises none. ``point``: "sight", where the image shows the bars cross, or "crossing",
        where the 3D crossing point projects."""
        if not 0.0 < threshold < 1.0:
            raise ConfigError(f"threshold = {threshold} is not accepted; accepted: a score between 0 and 1")
        accepted("point", point, POINTS)
        if point == "crossing" and self.crossing_point is None:
            raise ConfigError(
                f"{self.path or 'this detector'}: has no crossing-point stage; accepted: point='sight', or a "
                "model trained with one (crossing_point: {enabled: true}, as `make train` ships)"
            )
        image = _check_image(rgb)
        camera = self._camera(image, camera)
        depth_m = as_depth_m(depth, image.shape[:2]) if depth is not None else None
        scale = focal_scale(self.focal_px, camera) if self.resample else 1.0
        zoom = self.zoom if self.resample else None
        det, factor = self._detect_at(
            image, camera, depth_m, scale, threshold=threshold, point=point, zoom=zoom
        )
        if det is None:  # the crossings are seen small (or large): read the frame again, larger (or smaller)
            det, _ = self._detect_at(image, camera, depth_m, scale * factor, threshold=threshold, point=point)
        return det

    def _detect_at(
        self,
        image: np.ndarray,
        camera: Intrinsics,
        depth_m: np.ndarray | None,
        scale: float,
        *,
        threshold: float,
        point: str,
        zoom: Zoom | None = None,
    ) -> tuple[np.ndarray | None, float]:
        """:meth:`detect` on the frame resized by ``scale``, in the frame's own pixels, and 1.0; or, where
        ``zoom`` would read the frame again, None and its factor, as soon as the RGB stages have sized the
        crossings (the depth check and the crossing-point stage then run on the second reading only)."""
        h, w = image.shape[:2]
        sx = sy = 1.0
        if scale != 1.0:
            h, w = max(1, round(h * scale)), max(1, round(w * scale))
            sx, sy = w / image.shape[1], h / image.shape[0]
            image, camera = resample(image, (h, w)), camera.resized(w, h)
            depth_m = None if depth_m is None else resample(depth_m, (h, w), nearest=True)
        as_it_comes = image  # what the crossing-point stage trained on
        if depth_m is not None and self.flatten_behind:
            image = flatten_behind(image, depth_m)
        lc = self.line_check
        floor, checked_from = (lc.floor, lc.checked_from) if lc else (threshold, threshold)
        seen = self.line_pass(
            image, self.raw(image, camera=camera), floor, checked_from, check=lc, threshold=threshold
        )
        if zoom is not None:
            # the sizes of the crossings found at the operating point, whatever the caller's threshold (a
            # score's low threshold would size every faint candidate)
            factor = zoom.factor(None if seen.box is None else seen.box[seen.scores >= OPERATING_THRESHOLD])
            if factor != 1.0:
                return None, factor
        det = np.c_[seen.placed, seen.scores]
        det = det[det[:, 2] >= threshold]  # the depth check only lowers: it reads only these
        if depth_m is not None and self.depth_check is not None and len(det):
            det[:, 2] = shifted_score(det[:, 2], self.depth_check.veto(depth_m, det[:, :2]))
            det = det[det[:, 2] >= threshold]
        det = det[np.argsort(-det[:, 2], kind="stable")]
        inside = (det[:, 0] >= 0) & (det[:, 0] < w) & (det[:, 1] >= 0) & (det[:, 1] < h)
        det = drop_duplicates(det[inside], DUPLICATE_PX)
        if point == "crossing" and len(det):
            det[:, :2] = self.crossing_point.points(as_it_comes, det[:, :2], camera)
        det[:, :2] /= (sx, sy)
        return det, 1.0

    def line_pass(
        self,
        image: np.ndarray,
        out: np.ndarray,
        floor: float,
        checked_from: float,
        *,
        check: LineCheck | None = None,
        threshold: float = 0.0,
    ) -> LineInputs:
        """The RGB stages and the line check ``check`` (None: none) on the first stage's output ``out`` for
        ``image``: the candidates scoring ``floor`` or more inside the frame are evidence, those scoring
        ``checked_from`` or more are verified and checked; the later passes move those scoring ``threshold``
        or more. Without a check, what a line check with these first-stage scores reads (to fit one)."""
        det = decode(out[0] + self.score_bias, out[1:], threshold=floor)
        h, w = image.shape[:2]
        det = det[(det[:, 0] >= 0) & (det[:, 0] < w) & (det[:, 1] >= 0) & (det[:, 1] < h)]
        evidence = det[:, 2].copy()
        checked = np.flatnonzero(evidence >= checked_from)
        placed, verify, box = det[checked, :2], None, None
        refiner, mirrored = self.refiner if len(checked) else None, self.reading == "mirrored"
        if refiner is not None:
            placed, verify, box = refiner.first_pass(image, placed, mirrored=mirrored)
        if verify is not None:
            evidence[checked] = shifted_score(det[checked, 2], self.verify_power * log_probability(verify))
        if check is None:
            scores = evidence[checked]
        else:
            scores = check.scores(image, det[:, :2], evidence, checked, threshold=threshold)
        if refiner is not None:  # the later passes spare what can no longer reach the threshold
            moving = scores >= threshold if verify is not None else slice(None)
            placed[moving] = refiner.later_passes(
                image, placed[moving], None if box is None else box[moving], mirrored=mirrored
            )
        return LineInputs(det[:, :2], evidence, checked, placed, scores, box)


@dataclass(frozen=True)
class LineInputs:
    """One image's candidates as the line check reads them: ``uv`` (N, 2) and ``evidence`` (N,) of every
    candidate, the indices ``checked`` (K,) of those checked, where the second stage ``placed`` them (K, 2),
    and their ``scores`` (K,): the line check's, or the RGB stages' without one; ``box`` (K,) the box sides
    the second stage gave them (None without a size output, or without a second stage)."""

    uv: np.ndarray
    evidence: np.ndarray
    checked: np.ndarray
    placed: np.ndarray
    scores: np.ndarray
    box: np.ndarray | None = None


def drop_duplicates(det: np.ndarray, radius_px: float) -> np.ndarray:
    """``det`` (N, 3), best first, without each detection nearer than ``radius_px`` to a better one."""
    if len(det) < 2:
        return det
    d = np.hypot(*(det[:, None, :2] - det[None, :, :2]).transpose(2, 0, 1))
    near = np.triu(d < radius_px, k=1)
    keep = np.ones(len(det), bool)
    for i in range(len(det)):
        if keep[i]:
            keep[near[i]] = False
    return det[keep]


def log_probability(logit: np.ndarray) -> np.ndarray:
    """log sigmoid(``logit``), without overflow."""
    return -np.logaddexp(0.0, -np.asarray(logit, np.float64))


def shifted_score(score: np.ndarray, shift: float | np.ndarray) -> np.ndarray:
    """sigmoid(logit(score) + shift)."""
    s = np.clip(np.asarray(score, np.float64), 1e-12, 1.0 - 1e-12)
    return 1.0 / (1.0 + np.exp(-(np.log(s) - np.log1p(-s) + shift)))


def _reader(p: Path) -> Callable[..., Detector]:
    """The function :data:`READERS` names for ``p``'s suffix, imported now."""
    module, _, name = READERS[p.suffix].partition(":")
    try:
        return getattr(importlib.import_module(module), name)
    except ImportError as e:
        raise ConfigError(
            f"{p}: a {p.suffix} file runs in PyTorch, which cannot be imported here ({e}); accepted: the "
            "model's .onnx file"
        ) from None


def _check_image(rgb: np.ndarray) -> np.ndarray:
    a = np.asarray(rgb)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ConfigError(f"image of shape {a.shape} is not accepted; accepted: an (H, W, 3) RGB array")
    if a.dtype != np.uint8:
        if np.issubdtype(a.dtype, np.floating) and a.size and a.max() <= 1.0:
            a = a * 255.0
        a = np.clip(np.rint(a), 0, 255).astype(np.uint8)
    return np.ascontiguousarray(a)
