from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from rebar_data.perception.training.config import AugmentConfig
from tests.perception.synthetic import SyntheticSpec, write_synthetic_dataset

# every colour, blur and noise change off: augmentation is geometry only, so pixels can be compared
COLOUR_OFF = dict(
    brightness=0,
    contrast=0,
    saturation=0,
    hue_deg=0,
    hue_full_probability=0,
    white_balance=0,
    gamma=0,
    blur_probability=0,
    noise_probability=0,
)
STILL = AugmentConfig(**COLOUR_OFF)


def render_one_frame(tmp_path: Path):
    """One frame of a small tunnel piece, rendered and labelled as a dataset build would, with the servo
    camera (640x480 Kinect v1): a scene and pose the shipped model has never seen."""
    import yaml

    from rebar_data.dataset.plan import make_plan
    from rebar_data.dataset.worker import FrameWorker
    from rebar_data.geometry.build import build_rebar_mesh
    from rebar_data.perception.evaluation.data import read_depth, read_image
    from rebar_data.pipeline import PipelineConfig

    smoke = yaml.safe_load((Path(__file__).parents[2] / "pipelines/smoke.yaml").read_text())
    cfg = PipelineConfig.model_validate(
        {
            **smoke,
            "seed": 424242,
            "camera": {
                "intrinsics": "kinect_v1",
                "trajectories": [{"kind": "approach", "count": 1, "frames": 1, "edge_margin_m": 0.2}],
            },
            "render": {"texture_size_px": 256, "cache_dir": str(tmp_path / "textures")},
        }
    )
    rm = build_rebar_mesh(cfg.mesh_config())
    plan = make_plan(cfg, rm)
    worker = FrameWorker(cfg, tmp_path, rm)
    try:
        sample = plan.samples[0]
        labels = worker.run(plan.scenes[0], [sample])[0].labels
    finally:
        worker.close()
    k = worker.intrinsics
    visible = labels.visibility == 2
    truth = np.c_[labels.u[visible], labels.v[visible]]
    rgb = read_image(tmp_path / f"images/{sample.split}/{sample.image_id}.png")
    depth = read_depth(tmp_path / f"depth/{sample.split}/{sample.image_id}.png")
    return rgb, truth, labels.box_size_px[visible], (k.fx, k.fy, k.cx, k.cy), depth


@pytest.fixture(scope="session")
def _rendered(tmp_path_factory):
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("EGL_PLATFORM", "surfaceless")
        return render_one_frame(tmp_path_factory.mktemp("rendered"))


@pytest.fixture(scope="session")
def rendered_frame(_rendered):
    """:func:`render_one_frame`, rendered once for every test that reads it: (rgb, visible crossings (N, 2),
    their box sides, camera). Tests read it and do not change it."""
    return _rendered[:4]


@pytest.fixture(scope="session")
def rendered_depth(_rendered):
    """The depth image registered to :func:`rendered_frame`'s (float32 metres, 0 = no measurement)."""
    return _rendered[4]


def shipped_model_copy(folder: Path) -> Path:
    """The shipped model's files copied into ``folder`` (a test that changes a model file in place works on
    this); skips the test when no model is shipped yet."""
    from rebar_data.perception.inference import detector as infer

    if not infer.SHIPPED_MODEL.exists():
        pytest.skip("no model shipped yet (make train ships one)")
    for f in infer.MODELS_DIR.glob(f"{infer.SHIPPED_MODEL.stem}.*onnx"):
        shutil.copy(f, folder / f.name)
    return folder / infer.SHIPPED_MODEL.name


def refined(refiner, image: np.ndarray, uv: np.ndarray, *, keep=None, mirrored: bool = False):
    """The second stage's (N, 2) positions and first-pass verification logits for points ``uv``, the later
    passes moving those ``keep`` (logits -> bool) names (None: all)."""
    uv = np.asarray(uv, float).reshape(-1, 2)
    if not len(uv):
        return uv.copy(), np.zeros(0)
    placed, logit, box = refiner.first_pass(image, uv, mirrored=mirrored)
    moving = np.ones(len(uv), bool) if keep is None or logit is None else keep(logit)
    box = None if box is None else box[moving]
    placed[moving] = refiner.later_passes(image, placed[moving], box, mirrored=mirrored)
    return placed, logit


TINY_MODEL = {"channels": (8, 8, 16, 16), "blocks": (0, 1, 1)}
TINY_TRAIN = {
    "batch_size": 4,
    "crop_px": 64,
    "crops_per_image": 1,
    "lr": 5e-3,
    "val_max_images": 4,
    "threads": 1,
    "loader_workers": 0,
    "patience": 50,
    "model": TINY_MODEL,
    "augment": {"mosaic_epochs": 1},
    # the second-stage supplements wait for the adapt epochs, so the tests may add them when a run resumes
    "other_renderer_repeats": 0,
    "adapt": {"epochs": 1, "supplement_repeats": 2},
    "refine": {
        "patch_px": 16,
        "widths": (4, 4, 8, 8),
        "hidden": 8,
        "epochs": 1,
        "batch_size": 32,
        "threads": 1,
    },
    "depth_check": {
        "patch_px": 16,
        "widths": (4, 4, 8, 8),
        "hidden": 8,
        "epochs": 1,
        "batch_size": 64,
        "threads": 1,
    },
    "crossing_point": {
        "patch_px": 16,
        "context_px": 24,
        "widths": (4, 4, 8, 8),
        "hidden": 8,
        "epochs": 1,
        "batch_size": 64,
        "threads": 1,
    },
}


@pytest.fixture(autouse=True)
def _one_thread():
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)


@pytest.fixture(scope="session")
def drawn_dataset(tmp_path_factory):
    """A small drawn dataset in the contract layout: 12 frames of 192x144 from 6 trajectories."""
    spec = SyntheticSpec(width=192, height=144, focal_px=157.5, trajectories=6, frames=2)
    return write_synthetic_dataset(tmp_path_factory.mktemp("data"), spec, seed=11)


@pytest.fixture(scope="session")
def trained_run(drawn_dataset, tmp_path_factory):
    """A tiny model trained for two epochs on the drawn dataset."""
    from rebar_data.perception.training.train import train

    before = torch.get_num_threads()
    out = tmp_path_factory.mktemp("runs") / "tiny"
    result = train(drawn_dataset, out, config={**TINY_TRAIN, "epochs": 2}, progress=False)
    torch.set_num_threads(before)
    return result
