"""The dataset pipeline config: the mesh sections plus camera, scene, render, labels and dataset sections."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator

from rebar_data.config import Fraction, NonNegative, Positive, Strict, read_yaml, semver, validate
from rebar_data.geometry.config import MeshConfig
from rebar_data.scene.config import CameraConfig, RenderConfig, SceneConfig

# OKS sigma for the single "intersection" keypoint. With COCO's OKS = exp(-d^2 / (2 s^2 k^2)), k = 2 sigma
# and s^2 the keypoint's box area, OKS = 0.5 at d = 1.177 k s = 2.35 sigma s. sigma = 0.04 puts that at
# 2.4 px for the 25 px boxes typical at 640x640 (1.9 px at 20 px, 3.8 px at 40 px). Ultralytics' default
# for one keypoint is 1.0, which accepts errors of about 1.7 box sizes.
DEFAULT_OKS_SIGMA = 0.04


class SplitConfig(Strict):
    """How images are assigned to train/val/test.

    ``scene`` (default) keeps every frame of a scene (mesh, lights, materials, surroundings) in one split,
    so no near-duplicate frame crosses splits; ``trajectory`` does the same per camera trajectory;
    ``random`` is the paper's frame-level split (80:20 there), which leaks near-duplicates.
    """

    rule: Literal["scene", "trajectory", "random"] = "scene"
    train: Fraction = 0.8
    val: Fraction = 0.1
    test: Fraction = 0.1

    @model_validator(mode="after")
    def _sum_to_one(self) -> SplitConfig:
        total = self.train + self.val + self.test
        if abs(total - 1.0) > 1e-9:
            raise ValueError(f"train + val + test = {total:g}; accepted: fractions that sum to 1")
        return self


class LabelConfig(Strict):
    """Box and visibility rules (see rebar_data/labels/keypoints.py)."""

    box_bar_diameters: Positive = 4.0
    min_box_px: NonNegative = 8.0
    near_diameters: Positive = 3.0


class DatasetSection(Strict):
    split: SplitConfig = SplitConfig()
    oks_sigma: Positive = DEFAULT_OKS_SIGMA
    store_depth: bool = True
    store_instances: bool = True


class PipelineConfig(MeshConfig):
    """A whole dataset pipeline file (``pipelines/<name>.yaml``)."""

    name: Annotated[str, Field(pattern=r"^[a-z0-9][a-z0-9_-]*$", max_length=64)]
    version: str
    description: str = ""
    camera: CameraConfig
    scene: SceneConfig = SceneConfig()
    render: RenderConfig = RenderConfig()
    labels: LabelConfig = LabelConfig()
    dataset: DatasetSection = DatasetSection()

    @field_validator("version")
    @classmethod
    def _semver(cls, v: str) -> str:
        return semver(v)

    def mesh_config(self) -> MeshConfig:
        return MeshConfig(seed=self.seed, mesh=self.mesh, realism=self.realism, pose=self.pose)

    def resolved(self) -> dict:
        """The config with every default filled in, as plain JSON types."""
        return self.model_dump(mode="json")

    def config_hash(self) -> str:
        return hashlib.sha256(json.dumps(self.resolved(), sort_keys=True).encode()).hexdigest()


def load_pipeline(path: str | Path) -> PipelineConfig:
    """Read and check a pipeline file; every problem is one ConfigError naming the field. A relative
    ``mesh.ifc_path`` is resolved against the file's folder, so every command reads the same model."""
    cfg = validate(PipelineConfig, read_yaml(path), str(path))
    if cfg.mesh.kind == "ifc" and not Path(cfg.mesh.ifc_path).expanduser().is_absolute():
        ifc = str(cfg.mesh.path(Path(path).parent).resolve())
        cfg = cfg.model_copy(update={"mesh": cfg.mesh.model_copy(update={"ifc_path": ifc})})
    return cfg


def load_mesh_config(path: str | Path) -> MeshConfig:
    """The mesh part of a pipeline file, read after the whole file is checked: a command that needs only
    the mesh (``rebar mesh``, the servo world) accepts and refuses exactly the files a build does."""
    return load_pipeline(path).mesh_config()
