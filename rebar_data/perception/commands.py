"""`rebar train`, `adapt`, `add-crossing-point`, `detect` and `score`: train the detector, run it on images,
score it on a dataset."""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
from contextlib import ExitStack, contextmanager
from pathlib import Path
from typing import TYPE_CHECKING

from rebar_data import outputs
from rebar_data.arguments import bounded
from rebar_data.config import ConfigError
from rebar_data.perception.inference.detector import READINGS
from rebar_data.perception.inference.image import TOLERANCE
from rebar_data.perception.inference.model_file import RUNTIMES

if TYPE_CHECKING:
    import numpy as np

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp")
DETECT = "rebar detect"
SCORE = "rebar score"
ADAPT = "rebar adapt"
ADD_CROSSING_POINT = "rebar add-crossing-point"
SHIPPED = "shipped"  # `rebar train --init` without a model: the shipped one
WRITTEN_BY = "written_by"  # the key naming the command, in a Parquet file's metadata and a JSON record
PREDICTION_COLUMNS = ["image_id", "u", "v", "score"]
EPOCHS = bounded(int, 1)
THRESHOLD = bounded(float, 0, 1)
THREADS = bounded(int, 1, 256)


def _score_wrote_predictions(path: Path) -> bool:
    """``path`` is a predictions file `rebar score` wrote: its mark in the Parquet metadata."""
    import pyarrow.parquet as pq

    try:
        schema = pq.read_schema(path)
    except Exception:  # not a Parquet file at all
        return False
    return (schema.metadata or {}).get(WRITTEN_BY.encode()) == SCORE.encode()


def _score_wrote_metrics(path: Path) -> bool:
    """``path`` is a metrics file `rebar score` wrote: its mark in the record."""
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return False
    return isinstance(record, dict) and record.get(WRITTEN_BY) == SCORE


def _adapt_folder(folder: Path) -> bool:
    """``folder`` has the layout of an earlier `rebar adapt` (not a training run, which has config.json)."""
    made = any((folder / n).exists() for n in ("adapt_last.pt", "adapted.pt", "rebar_keypoint.onnx"))
    return (folder / "best.pt").is_file() and not (folder / "config.json").exists() and made


def _crossing_point_folder(folder: Path) -> bool:
    """``folder`` has the layout of an earlier `rebar add-crossing-point` (not a training run)."""
    made = any((folder / n).is_file() for n in ("crossing_last.pt", "best.crossing.pt"))
    return not (folder / "config.json").exists() and made


def run_train(args: argparse.Namespace) -> None:
    from rebar_data.config import read_yaml
    from rebar_data.perception.evaluation.data import check_dataset, read_info
    from rebar_data.perception.training.config import resolve_config
    from rebar_data.perception.training.train import check_run_folder, train

    root = check_dataset(args.dataset)
    if args.eval and not args.ship:
        raise ConfigError("--eval scores the model for its card; accepted: --eval together with --ship")
    for path in args.eval or ():  # scored after training: fail before it (train checks supplements itself)
        check_dataset(path)
    settings = read_yaml(args.config) if args.config else None
    config = resolve_config(settings, {}, source=str(args.config or "train settings"))
    init = None
    if args.init is not None:  # the model's settings, the file's laid over them
        from rebar_data.perception.training.init import read_model, settings_from

        init = read_model(None if args.init == SHIPPED else args.init)
        config = settings_from(init, settings, source=str(args.config or "train settings"))
    out = Path(args.out or Path("runs/train") / str(read_info(root).get("name") or root.parent.name))
    check_run_folder(out)
    inputs = [root, *(args.eval or ()), *(args.supplement or ()), *(args.refine_supplement or ())]
    outputs.outside_inputs(out, [*inputs, *(args.line_supplement or ())], arg="--out")
    result = train(
        root,
        out,
        config=config,
        epochs=args.epochs,
        supplements=args.supplement or (),
        refine_supplements=args.refine_supplement or (),
        line_supplements=args.line_supplement or (),
        resume=not args.fresh,
        progress=not args.quiet,
        init=init,
        stages=args.stages,
        device=args.device,
    )
    if args.ship:
        from rebar_data.perception.training.ship import ship

        model = ship(out, evaluate_on=args.eval or (), progress=not args.quiet)
        print(f"shipped {model}", file=sys.stderr)
    early = " (stopped early)" if result.stopped_early else ""
    if result.epochs_run:
        print(f"best epoch {result.best_epoch} of {result.epochs_run}{early}", file=sys.stderr)
    else:  # --init with the first stage kept
        print(f"first stage kept: the init model's (its epoch {result.best_epoch})", file=sys.stderr)
    print(out)


def _stage_inputs(args: argparse.Namespace, command: str, owned, datasets) -> tuple:
    """What `rebar adapt` and `rebar add-crossing-point` read, checked: ``--out`` (new, empty or the
    command's own, outside every input), the dataset, model file, ``--config`` (or None), every image of
    ``datasets``."""
    from rebar_data.config import read_yaml
    from rebar_data.perception.evaluation.data import check_dataset, load_split, read_info
    from rebar_data.perception.inference.detector import resolve_model_path
    from rebar_data.perception.training.config import resolve_config
    from rebar_data.perception.training.train import supplement_images

    outputs.outside_inputs(Path(args.out), [args.dataset, *datasets], arg="--out")
    out = outputs.output_folder(args.out, arg="--out", command=command, owned=owned)
    root = check_dataset(args.dataset)
    model = resolve_model_path(args.model)
    cfg = resolve_config(read_yaml(args.config), {}, source=str(args.config)) if args.config else None
    extra, meta = supplement_images(datasets, trained_on=read_info(root).get("name"))
    return out, load_split(root, "train"), model, cfg, extra, meta


@contextmanager
def _writing(out: Path, command: str, owned):
    """Hold ``out``'s one-writer lock, make the folder and leave ``command``'s mark in it."""
    with outputs.OutputLock(out, command=command):
        outputs.output_folder(out, arg="--out", command=command, owned=owned)  # again under the lock
        out.mkdir(parents=True, exist_ok=True)
        outputs.mark_output(out, command)
        yield out


def run_add_crossing_point(args: argparse.Namespace) -> None:
    from rebar_data.perception.training.config import resolve_config
    from rebar_data.perception.training.crossing_point import attach

    found = _stage_inputs(args, ADD_CROSSING_POINT, _crossing_point_folder, args.supplement or ())
    out, samples, model, cfg, extra, _ = found
    cfg, samples = cfg or resolve_config(None, {}), samples + extra
    with _writing(out, ADD_CROSSING_POINT, _crossing_point_folder):
        stage = attach(
            model, samples, out, cfg.crossing_point, cfg.augment, seed=cfg.seed, progress=not args.quiet
        )
    print(f"crossing-point stage beside {model}: {stage}", file=sys.stderr)
    print(stage)


def run_adapt(args: argparse.Namespace) -> None:
    from rebar_data.perception.training.adapt import adapt_model

    # cfg None: the settings the model trained with (adapt_model reads them from the file it loads)
    out, samples, model, cfg, extra, frames = _stage_inputs(args, ADAPT, _adapt_folder, args.frames)
    log = None if args.quiet else (lambda msg: print(msg, file=sys.stderr))
    with _writing(out, ADAPT, _adapt_folder):
        data = [str(f["path"]) for f in frames]
        out = adapt_model(model, samples, extra, out, cfg, data=data, log=log, progress=not args.quiet)
    print(f"adapted {model} on {len(extra)} frames: {out}", file=sys.stderr)
    print(out)


def forward_dataset_detect(argv: list[str]) -> list[str]:
    """``rebar detect DATASET ...`` as ``rebar score DATASET ...``, with a note on stderr: scripts and other
    tools wrote the dataset form before `rebar score` had its own name, and the acceptance checks still do.
    Only this one form is forwarded, whole; each command's parser keeps only its own flags."""
    if len(argv) >= 2 and argv[0] == "detect" and (Path(argv[1]) / "tables/samples.parquet").is_file():
        print(f"note: `rebar detect {argv[1]}` is `{SCORE} {argv[1]}`; running that", file=sys.stderr)
        return ["score", *argv[1:]]
    return argv


def run_detect(args: argparse.Namespace) -> int:
    from rebar_data.perception.inference.detector import resolve_model_path

    target = Path(args.input)
    accepted = "an image or a folder of images"
    if not target.exists():
        raise ConfigError(f"{target}: no such image or folder; accepted: {accepted}")
    (outputs.input_folder if target.is_dir() else outputs.input_file)(target, arg="input", what=accepted)
    if (target / "tables/samples.parquet").exists():
        raise ConfigError(
            f"{target}: is a dataset, which `{SCORE} {target}` scores; accepted: {accepted} to detect in"
        )
    files = _image_files(target)
    _images_out(target, args)
    camera = _camera_of(args.camera)
    resolve_model_path(args.model)  # a wrong --model is named before anything loads
    return _detect_images(_detector_of(args), target, files, camera, args)


def run_score(args: argparse.Namespace) -> int:
    from rebar_data.perception.evaluation.data import check_depth_source
    from rebar_data.perception.inference.detector import resolve_model_path

    root = _dataset_input(args.dataset)
    check_depth_source(args.depth_from, f"--depth-from {args.depth_from}")  # before anything is written
    if args.flatten_behind and args.no_depth:
        raise ConfigError(
            "--flatten-behind reads the depth images, which --no-depth leaves out; accepted: one of the two"
        )
    _score_outputs(root, args)
    resolve_model_path(args.model)  # a wrong --model is named before anything loads
    return _score_dataset(_detector_of(args, flatten_behind=args.flatten_behind), root, args)


def _dataset_input(path: str) -> Path:
    """`rebar score`'s dataset, checked: a folder you may read, with the dataset's tables."""
    from rebar_data.perception.evaluation.data import check_dataset

    root = Path(path)
    if root.exists():
        outputs.input_folder(root, arg="dataset", what="a dataset folder")
        if not (root / "tables/samples.parquet").exists():
            raise ConfigError(
                f"{root}: is not a dataset (it has no tables/samples.parquet); accepted: a dataset folder "
                f"written by `rebar dataset build`, or images to detect in with `{DETECT} {root}`"
            )
    return check_dataset(root)


def _detector_of(args: argparse.Namespace, *, flatten_behind: bool = False):
    """The detector ``--model`` names, read as the flags say."""
    from rebar_data.perception.inference.detector import Detector

    return Detector.load(
        args.model,
        threads=args.threads,
        runtime=args.runtime,
        reading=args.reading,
        resample=not args.no_resample,
        flatten_behind=flatten_behind,
        zoom=not args.no_zoom,
    )


def _camera_of(text: str | None) -> tuple[float, float, float, float] | None:
    """``--camera FX,FY,CX,CY`` as four numbers (None when not given)."""
    if text is None:
        return None
    try:
        camera = tuple(float(x) for x in text.split(","))
    except ValueError:
        camera = ()
    if len(camera) != 4 or not camera[0] > 0 or not camera[1] > 0:
        raise ConfigError(
            f"--camera {text}: is not accepted; accepted: FX,FY,CX,CY in pixels (COCO corner origin), focal "
            "lengths above 0, such as 1050,1050,640,480 for a 1280x960 camera"
        )
    return camera


def _score_outputs(root: Path, args: argparse.Namespace) -> tuple[Path, Path | None, Path | None]:
    """``--out``, ``--metrics`` and ``--coco-results`` of a dataset's predictions (the last two None when not
    asked for), each checked as `rebar score` may write it."""
    out = Path(args.out)
    if out.suffix != ".parquet":
        raise ConfigError(
            f"--out {out}: predictions on a dataset go to a .parquet file, such as pred.parquet"
        )
    outputs.outside_inputs(out, [root], arg="--out")
    what = "a new .parquet file, or one an earlier `rebar score` wrote"
    outputs.output_file(out, arg="--out", what=what, owned=_score_wrote_predictions)
    if args.oks_sigma is not None and not args.oks_sigma > 0:
        raise ConfigError(
            f"--oks-sigma {args.oks_sigma} is not accepted; accepted: a number above 0, such as 0.04"
        )
    metrics = None
    if args.metrics:
        outputs.outside_inputs(Path(args.metrics), [root], arg="--metrics")
        what = "a new JSON file, or one an earlier `rebar score` wrote"
        metrics = outputs.output_file(args.metrics, arg="--metrics", what=what, owned=_score_wrote_metrics)
        if metrics.resolve() == out.resolve():
            raise ConfigError(f"--metrics {metrics}: is --out as well; accepted: another file than --out")
    return out, metrics, _coco_results_output(root, args, [out, metrics])


def _coco_results_output(root: Path, args: argparse.Namespace, others: list[Path | None]) -> Path | None:
    """``--coco-results``, checked: a .json file outside the dataset and the model, not another output, for
    one split's sight points (what ``annotations/<split>.json`` holds); None when not asked for."""
    from rebar_data.perception.evaluation.coco_results import is_coco_results

    if not args.coco_results:
        return None
    path = Path(args.coco_results)
    given = f"--coco-results {path}"
    if path.suffix != ".json":
        raise ConfigError(f"{given}: COCO results go to a .json file; accepted: a file such as results.json")
    if args.split == "all":
        raise ConfigError(
            f"{given}: COCO results are scored against one split's annotations/<split>.json; accepted: "
            "--coco-results with --split train, val or test"
        )
    if (args.point or args.truth) != "sight":
        raise ConfigError(
            f"{given}: the COCO annotations hold the sight points, not the 3D crossing points; accepted: "
            "--coco-results with --point sight and --truth sight (the defaults)"
        )
    outputs.outside_inputs(path, [root, *([args.model] if args.model else [])], arg="--coco-results")
    what = "a new JSON file, or COCO results an earlier `rebar score` wrote"
    path = outputs.output_file(path, arg="--coco-results", what=what, owned=is_coco_results)
    for other, flag in zip(others, ("--out", "--metrics"), strict=True):
        if other is not None and path.resolve() == Path(other).resolve():
            raise ConfigError(f"{given}: is {flag} as well; accepted: another file than {flag}")
    return path


def _write_coco_results(path: Path, image_ids: list[int], preds: list) -> None:
    """The detections as COCO keypoint results, of the images with these COCO ``image_ids``."""
    from rebar_data.perception.evaluation.coco_results import coco_results

    results = coco_results(image_ids, preds)
    text = json.dumps(results, separators=(",", ":")) + "\n"
    outputs.replace_file(path, lambda tmp: tmp.write_text(text))
    if not results:  # COCO.loadRes indexes the first result: an empty list raises IndexError there
        print(f"note: {path}: no detections, an empty list (COCO.loadRes refuses it)", file=sys.stderr)


def _write_marked_predictions(path: Path, image_ids: list[str], preds: list, *, command: str) -> None:
    """The predictions file, with ``command``'s mark in its Parquet metadata."""
    import pyarrow.parquet as pq

    from rebar_data.perception.evaluation.evaluate import write_predictions

    def write(tmp: Path) -> None:
        table = pq.read_table(write_predictions(tmp, image_ids, preds))
        meta = {**(table.schema.metadata or {}), WRITTEN_BY.encode(): command.encode()}
        pq.write_table(table.replace_schema_metadata(meta), tmp)

    outputs.replace_file(path, write)


def _score_dataset(detector, root: Path, args: argparse.Namespace) -> int:
    from rebar_data.perception.evaluation.bench import runtime_description
    from rebar_data.perception.evaluation.coco_results import coco_image_ids
    from rebar_data.perception.evaluation.data import SPLITS, stated_oks_sigma
    from rebar_data.perception.evaluation.evaluate import LOW_THRESHOLD, load_splits, predict, score
    from rebar_data.perception.evaluation.false_detections import false_detection_census, format_census
    from rebar_data.perception.evaluation.metrics import format_summary

    samples = load_splits(root, SPLITS if args.split == "all" else (args.split,), truth=args.truth)
    if not samples:
        raise ConfigError(f"{root}: the {args.split} split has no images; accepted: a split with images")
    threshold = args.threshold if args.threshold is not None else LOW_THRESHOLD
    point = args.point or args.truth
    with ExitStack() as held:
        out, metrics_path, coco_path = _score_outputs(root, args)
        held.enter_context(outputs.OutputLock(out, command=SCORE))
        if metrics_path is not None:
            held.enter_context(outputs.OutputLock(metrics_path, command=SCORE, arg="--metrics"))
        coco_ids: list[int] = []
        if coco_path is not None:
            held.enter_context(outputs.OutputLock(coco_path, command=SCORE, arg="--coco-results"))
            # each image's id in annotations/<split>.json, read before any work: a bad file writes nothing
            files = [s.path.relative_to(root).as_posix() for s in samples]
            coco_ids = coco_image_ids(root, args.split, files)
        _score_outputs(root, args)  # again under the locks: another writer may have finished meanwhile
        depth, progress = not args.no_depth, not args.quiet
        preds = predict(
            detector,
            samples,
            threshold=threshold,
            depth=depth,
            depth_from=args.depth_from,
            progress=progress,
            point=point,
        )
        _write_marked_predictions(out, [s.image_id for s in samples], preds, command=SCORE)
        if coco_path is not None:
            _write_coco_results(coco_path, coco_ids, preds)
        sigma = args.oks_sigma if args.oks_sigma is not None else stated_oks_sigma(root)
        metrics = score(samples, preds, sigma=sigma)
        against = "" if args.truth == "sight" else " (against the projected 3D crossing points)"
        found = "" if point == args.truth else f", the detector's {point} points"
        print(f"{args.split}{against}{found}: {format_summary(metrics)}", file=sys.stderr)
        # where the confident false detections lie (against the labels alone: most miss the 3D points' gate)
        census = false_detection_census(root, samples, preds) if args.truth == "sight" else None
        if census is not None:
            print(format_census(census), file=sys.stderr)
        if metrics_path is not None:
            # what ran the first stage: its figures may move a little with the runtime
            torch = detector.backend == "torch"
            runtime = "PyTorch, float32" if torch else runtime_description(detector.backend)
            record = dict(split=args.split, dataset=str(root), truth=args.truth, point=point, runtime=runtime)
            record |= dict(reading=detector.reading, resample=detector.resample)
            record |= {WRITTEN_BY: SCORE, **metrics}
            if census is not None:
                record["false_detections"] = census
            text = json.dumps(record, indent=2) + "\n"
            outputs.replace_file(metrics_path, lambda tmp: tmp.write_text(text))
    print(out)
    return 0


def _image_files(target: Path) -> list[Path]:
    """The images to read: ``target`` itself, or every image file in the folder ``target``."""
    if not target.is_dir():
        return [target]
    files = sorted(p for p in target.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if not files:
        raise ConfigError(
            f"{target}: holds no images ({', '.join(IMAGE_SUFFIXES)}); accepted: an image or a folder of them"
        )
    return files


def _images_out(target: Path, args: argparse.Namespace) -> Path:
    """``--out`` for images: a folder, new, empty or `rebar detect`'s own earlier one, outside the input."""
    out = Path(args.out)
    if out.suffix == ".parquet":
        raise ConfigError(
            f"--out {out}: for images, --out is a folder for the overlays and detections.parquet"
        )
    outputs.outside_inputs(out, [target], arg="--out")
    outputs.output_folder(out, arg="--out", command=DETECT, swapped=True)
    if target.is_file() and out.resolve() == target.parent.resolve():
        raise ConfigError(
            f"--out {out}: is the folder of the input {target}, whose files would be overwritten; accepted: "
            "a folder outside every input"
        )
    return out


def _detect_images(detector, target: Path, files: list[Path], camera, args: argparse.Namespace) -> int:
    """Overlays, detections.parquet and cameras.json of every image, in a folder swapped in whole at the
    end; an image that cannot be read is named and skipped, and the command then ends with status 1."""
    from rebar_data.perception.evaluation.data import read_image
    from rebar_data.perception.inference.detector import OPERATING_THRESHOLD

    threshold = args.threshold if args.threshold is not None else OPERATING_THRESHOLD
    final = Path(args.out)
    unread: list[Path] = []
    with outputs.OutputLock(final, command=DETECT):
        _images_out(target, args)  # again under the lock: another writer may have finished meanwhile
        outputs.remove_stale(final.parent, f".{final.name}.tmp-*")  # a killed run's (the lock proves it dead)
        with tempfile.TemporaryDirectory(dir=final.parent, prefix=f".{final.name}.tmp-") as tmp:
            out = Path(tmp) / "detect"
            out.mkdir()
            preds, ids, cameras = [], [], {}
            for f in files:
                try:
                    rgb = read_image(f)
                except ConfigError as e:
                    unread.append(f)
                    print(f"skipped {e}", file=sys.stderr)
                    continue
                det, cameras[f.stem] = _detect_image(detector, f, rgb, out, camera, threshold, args)
                preds.append(det)
                ids.append(f.stem)
            _write_marked_predictions(out / "detections.parquet", ids, preds, command=DETECT)
            # the intrinsics each image was read with, beside its detections (COCO corner origin, pixels)
            (out / "cameras.json").write_text(json.dumps(cameras, indent=2) + "\n")
            outputs.mark_output(out, DETECT)
            outputs.replace_folder(out, final)
    print(final)
    if unread:
        print(f"error: {len(unread)} of {len(files)} images could not be read", file=sys.stderr)
        return 1
    return 0


def _detect_image(detector, f: Path, rgb: np.ndarray, out: Path, camera, threshold: float, args) -> tuple:
    """Detect in one image and draw its overlay into ``out``; returns the detections and the camera it was
    read with: ``camera``, else its EXIF 35 mm equivalent's, else None (the training field of view)."""
    import cv2

    from rebar_data.perception.evaluation.plots import draw_overlay
    from rebar_data.perception.photo import photo_camera

    used, how = camera, "--camera"
    if camera is None:
        found = photo_camera(f, *rgb.shape[:2]) if not args.no_exif else None
        used, how = None, "the training camera's field of view" + (", --no-exif" if args.no_exif else "")
        if found is not None:
            used, how = found.camera, f"EXIF {found.focal_35mm:g} mm equivalent, fx {found.camera[0]:.0f} px"
    det = detector.detect(rgb, threshold=threshold, camera=used, point=args.point)
    overlay = draw_overlay(rgb, det, threshold=threshold, scale=2 if max(rgb.shape[:2]) <= 1024 else 1)
    cv2.imwrite(str(out / f"{f.stem}.png"), cv2.cvtColor(overlay, cv2.COLOR_RGB2BGR))
    h, w = rgb.shape[:2]
    k = detector.default_camera(h, w)
    fx, fy, cx, cy = used if used is not None else (k.fx, k.fy, k.cx, k.cy)
    print(f"{f.name}: {len(det)} crossings (camera: {how})", file=sys.stderr)
    return det, {"file": f.name, "width": w, "height": h, "fx": fx, "fy": fy, "cx": cx, "cy": cy, "from": how}


def register(sub: argparse._SubParsersAction) -> None:
    quiet = "no progress bars or per-epoch lines"
    shipped = "the model's .onnx file (default: the shipped model)"
    repeatable = dict(action="append", metavar="DATASET")
    t = sub.add_parser("train", help="train the crossing detector on a dataset (CPU; resumable)")
    t.add_argument("dataset", help="dataset folder ROOT/<name>/v<version>/, as `rebar dataset build` prints")
    t.add_argument("--out", help="run folder (default runs/train/<dataset name>; an earlier run resumes)")
    t.add_argument("--config", help="YAML of training settings (TrainConfig's fields: epochs, ...)")
    t.add_argument("--epochs", type=EPOCHS, help=f"epochs, {EPOCHS} (overrides the config)")
    t.add_argument("--supplement", **repeatable, help="another dataset whose every image also trains")
    t.add_argument(
        "--refine-supplement",
        **repeatable,
        help="another renderer's dataset whose every image trains the adapt epochs and the second stage "
        "(and the first epochs, other_renderer_repeats times)",
    )
    t.add_argument("--line-supplement", **repeatable, help="a dataset the line check is also fitted on")
    t.add_argument("--fresh", action="store_true", help="start afresh instead of resuming the run in --out")
    t.add_argument(
        "--init",
        nargs="?",
        const=SHIPPED,
        metavar="MODEL",
        help="start every stage from this model's weights (.onnx or run folder; the shipped model when none "
        "is named), with its settings and the init section's epochs",
    )
    t.add_argument(
        "--stages",
        metavar="LIST",
        help="with --init: the stages to train, of first,refine,depth_check,crossing_point (default all); "
        "the others are the model's",
    )
    t.add_argument(
        "--ship", action="store_true", help="then copy the best model and its card into the package"
    )
    t.add_argument(
        "--device",
        choices=("auto", "cpu", "cuda"),
        default="auto",
        help="where the networks train: auto (default) is the GPU where PyTorch sees one, else the CPU",
    )
    t.add_argument("--eval", **repeatable, help="with --ship: also score the model on this dataset")
    t.add_argument("--quiet", action="store_true", help=quiet)
    t.set_defaults(func=run_train)

    a = sub.add_parser("add-crossing-point", help="train the crossing-point stage alone, for a model")
    a.add_argument("dataset", help="the dataset the model trained on (its train split trains the stage)")
    a.add_argument("--model", help=shipped)
    a.add_argument("--out", required=True, help="folder for the stage's checkpoint (an earlier one resumes)")
    a.add_argument("--supplement", **repeatable, help="as for `rebar train`")
    a.add_argument("--config", help="YAML of training settings (its crossing_point and seed)")
    a.add_argument("--quiet", action="store_true", help=quiet)
    a.set_defaults(func=run_add_crossing_point)

    p = sub.add_parser("adapt", help="train a model's first stage more epochs on another camera's frames")
    p.add_argument("dataset", help="the dataset the model trained on (its train split stays in the mix)")
    p.add_argument("--frames", **repeatable, required=True, help="a dataset of the other camera's frames")
    p.add_argument("--model", help=shipped)
    p.add_argument("--out", required=True, help="folder for rebar_keypoint.onnx (an earlier one resumes)")
    p.add_argument("--config", help="YAML of training settings (default: the model's; its adapt and seed)")
    p.add_argument("--quiet", action="store_true", help=quiet)
    p.set_defaults(func=run_adapt)

    d = sub.add_parser("detect", help="detect crossings in images: overlays and their detections")
    d.add_argument("input", metavar="IMAGES", help="an image, or a folder of images")
    d.add_argument(
        "--out", required=True, help="folder for the overlays, detections.parquet and cameras.json"
    )
    _model_flags(d)
    d.add_argument("--threshold", type=THRESHOLD, help=f"lowest score written, {THRESHOLD} (default 0.5)")
    points = ("sight", "crossing")
    point = "each detection's u, v: the sight point (default) or where the 3D crossing point projects"
    d.add_argument("--point", choices=points, default="sight", help=point)
    d.add_argument(
        "--camera",
        metavar="FX,FY,CX,CY",
        help="the intrinsics in pixels (default: from EXIF, else the training field of view); a frame whose "
        f"focal length differs over {TOLERANCE * 100:.0f}%% is read resized to the model's",
    )
    d.add_argument("--no-exif", action="store_true", help="leave the EXIF focal length unread")
    d.add_argument("--quiet", action="store_true", help="no progress bar")
    d.set_defaults(func=run_detect)

    s = sub.add_parser("score", help="detect crossings in a dataset split and score them against its labels")
    s.add_argument("dataset", help="dataset folder ROOT/<name>/v<version>/, as `rebar dataset build` prints")
    s.add_argument("--out", required=True, help="PRED.parquet: one row a detection")
    s.add_argument("--split", default="test", choices=("train", "val", "test", "all"), help="default test")
    _model_flags(s)
    s.add_argument("--threshold", type=THRESHOLD, help=f"lowest score written, {THRESHOLD} (default 0.05)")
    s.add_argument("--metrics", help="also write the split's metrics to this JSON file")
    s.add_argument(
        "--coco-results",
        metavar="FILE.json",
        help="also write the detections as COCO keypoint results (image_id the split's id in "
        "annotations/<split>.json) for pycocotools' COCO.loadRes and COCOeval",
    )
    s.add_argument("--no-depth", action="store_true", help="leave the dataset's depth images out")
    depth_from = (
        "the depth read: sensor, the dataset's depth sensor (default; its exact depth before 2.3.0), exact, or "
        "structured_light, active_stereo or time_of_flight, that model's image of the exact depth"
    )
    s.add_argument("--depth-from", default="sensor", metavar="SOURCE", help=depth_from)
    behind = "take what lies far behind the front bars (lower mat, ground) out of each image"
    s.add_argument("--flatten-behind", action="store_true", help=behind)
    s.add_argument("--oks-sigma", type=float, help="score OKS AP at this sigma (above 0)")
    truth = "score against the labels' sight points (default) or the projected 3D crossing points"
    s.add_argument("--truth", default="sight", choices=points, help=truth)
    point = "each detection's u, v: sight or 3D crossing point (default: as --truth)"
    s.add_argument("--point", choices=points, help=point)
    s.add_argument("--quiet", action="store_true", help="no progress bar")
    s.set_defaults(func=run_score)


def _model_flags(parser: argparse.ArgumentParser) -> None:
    """The flags `rebar detect` and `rebar score` share: the model and how it runs."""
    parser.add_argument("--model", help="model file (.onnx, .pt) or run folder (default: the shipped model)")
    parser.add_argument("--threads", type=THREADS, default=2, help=f"CPU threads, {THREADS} (default 2)")
    runtime = "auto (OpenVINO in bfloat16 where the CPU has it, else ONNX Runtime), onnxruntime or openvino"
    parser.add_argument("--runtime", choices=RUNTIMES, default="auto", help=runtime)
    reading = "mirrored (the image and its mirror image, the mean; the default) or single (once, faster)"
    parser.add_argument("--reading", choices=READINGS, default="mirrored", help=reading)
    parser.add_argument(
        "--no-resample", action="store_true", help="read every frame at its own scale (no zoom either)"
    )
    once = "read every frame once: not again larger where its crossings are seen small, smaller where large"
    parser.add_argument("--no-zoom", action="store_true", help=once)
