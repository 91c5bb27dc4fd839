"""Settings of the detector's training run, one line each; a bad value is one ConfigError naming the field.

Why each default is what it is, with the figures measured for it, is in ``docs/detector/experiments.md``
under the setting's name."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field, ValidationError, field_validator, model_validator

from rebar_data.config import (
    ConfigError,
    Fraction,
    NonNegative,
    NonNegativeInt,
    Positive,
    PositiveInt,
    Strict,
    format_validation_error,
)
from rebar_data.perception.networks.keypoint_net import ModelConfig

PatchPx = Annotated[int, Field(ge=16, multiple_of=8)]
Power = Annotated[float, Field(gt=0.0, le=1.0)]
Between = Annotated[float, Field(gt=0.0, lt=1.0)]
Widths = tuple[PositiveInt, PositiveInt, PositiveInt, PositiveInt]
DepthModel = Literal["exact", "structured_light", "active_stereo", "time_of_flight"]


class AugmentConfig(Strict):
    """Training-time augmentation; geometric changes move the keypoints with the pixels."""

    mosaic_epochs: NonNegativeInt = 3  # epochs at the start with mosaics (four images in one crop)
    mosaic_probability: Fraction = 0.5  # share of the crops that are mosaics in those epochs
    scale: tuple[Positive, Positive] = (0.7, 1.4)  # range of the random zoom
    rotation_deg: NonNegative = 180.0  # random rotation up to this, either way
    flip_lr: Fraction = 0.5  # probability of a left-right flip
    flip_ud: Fraction = 0.5  # probability of an up-down flip
    brightness: Fraction = 0.3  # brightness scaled by 1 +- this
    contrast: Fraction = 0.3  # contrast scaled by 1 +- this
    saturation: Fraction = 0.4  # saturation scaled by 1 +- this
    hue_deg: NonNegative = 10.0  # hue shifted by up to this, either way
    hue_full_probability: Fraction = 0.15  # share of the crops whose hue turns anywhere on the colour wheel
    white_balance: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.15  # each colour channel scaled by 1 +- this
    gamma: Fraction = 0.3  # gamma in 1 +- this
    blur_probability: Fraction = 0.3  # share of the crops blurred
    blur_sigma_px: tuple[NonNegative, NonNegative] = (0.3, 1.5)  # the blur's Gaussian sigma range
    noise_probability: Fraction = 0.5  # share of the crops given sensor noise
    noise_std: tuple[NonNegative, NonNegative] = (1.0, 8.0)  # the noise's standard deviation range (0-255)
    distractor_gain: tuple[Positive, Positive] = (0.85, 1.5)  # the distractors' pixels scaled, log-uniform
    distractor_gain_probability: Fraction = 0.8  # share of the images whose distractors are scaled

    @field_validator("distractor_gain")
    @classmethod
    def _gain_range(cls, v: tuple[float, float]) -> tuple[float, float]:
        if v[0] > v[1]:
            raise ValueError(f"{list(v)} is not accepted; accepted: [low, high] with low <= high")
        return v

    @property
    def scales_distractors(self) -> bool:
        """Whether ``distractor_gain`` acts at all (its share above 0)."""
        return self.distractor_gain_probability > 0


class RefineConfig(Strict):
    """The second stage (:mod:`rebar_data.perception.inference.refine`): moves each detection onto the
    crossing its full-resolution patch shows, and verifies it."""

    enabled: bool = True  # train and ship the second stage
    patch_px: PatchPx = 32  # side of the patch it reads
    widths: Widths = (24, 32, 48, 64)  # convolution widths at full resolution and each halving
    blocks: tuple[NonNegativeInt, NonNegativeInt, NonNegativeInt] = (1, 1, 1)  # convolutions after halvings
    hidden: PositiveInt = 128  # width of the fully connected layer
    epochs: PositiveInt = 11  # training epochs
    batch_size: PositiveInt = 256  # patches a step
    lr: Positive = 2e-3  # peak learning rate
    weight_decay: NonNegative = 1e-4  # AdamW weight decay
    loss_beta_px: Positive = 0.5  # smooth-L1 transition of the offset loss
    jitter_px: NonNegative = 1.5  # Gaussian error of the training patches' centres
    jitter_uniform_px: NonNegative = 5.0  # uniform error of a share of them, up to this
    jitter_uniform_fraction: Fraction = 0.3  # that share
    scale: tuple[Positive, Positive] = (0.8, 1.25)  # random scale of the training patches
    iterations: PositiveInt = 2  # passes at inference (stored in the model file)
    step: Power = 0.5  # share of the way each later pass moves the point
    threads: PositiveInt = 2  # CPU threads while it trains
    quantize: Literal["later", "none"] = "later"  # later: the passes after the first read an int8 copy
    calibration_patches: PositiveInt = 2048  # patches that set the int8 copy's value ranges
    verify: bool = True  # also output the logit that the patch shows a crossing
    negative_score: Between = 0.1  # lowest first-stage score mined as a negative
    negative_gate_px: Positive = 6.0  # a mined negative lies farther than this from every crossing
    verify_weight: Positive = 1.0  # weight of the verification loss against the offset loss
    verify_power: Power = 1.0  # how hard the verification counts in a score
    border_fraction: Fraction = 0.1  # share of the training patches given an image border of their own
    border_reach_px: NonNegative = 8.0  # that border lies within this of the crossing
    supplement_repeats: PositiveInt = 6  # times each second-stage supplement image is listed
    views: Literal[1, 2, 4, 8] = 2  # turned and flipped views averaged in the later passes
    first_pass_views: Literal[1, 2, 4, 8] = 1  # views of the first pass
    size: bool = True  # also output each crossing's size, which picks the later passes' resolution
    size_weight: Positive = 1.0  # weight of the size loss
    shrink_above_px: tuple[Positive, Positive] = (50.0, 90.0)  # crossings larger are read shrunk to 0.75, 0.5

    @model_validator(mode="after")
    def _size_needs_verify(self) -> RefineConfig:
        if self.size and not self.verify:
            raise ValueError(
                "size: true needs verify: true (the size is the column after the verification's)"
            )
        if self.shrink_above_px[0] > self.shrink_above_px[1]:
            raise ValueError(
                f"shrink_above_px {self.shrink_above_px} is not accepted; accepted: two sizes, the smaller "
                "first"
            )
        return self


class DepthCheckConfig(Strict):
    """The depth check (:mod:`rebar_data.perception.inference.checks`): lowers the score of a detection
    whose depth patch shows, with confidence, no crossing; it never raises one."""

    enabled: bool = True  # train and ship the depth check
    patch_px: PatchPx = 32  # side of the depth patch it reads
    scale_m: Positive = 0.05  # depth relative to the patch centre's, in these units
    clip: Positive = 4.0  # relative depth clipped to +- this
    widths: Widths = (16, 24, 32, 48)  # convolution widths at full resolution and each halving
    hidden: PositiveInt = 64  # width of the fully connected layer
    epochs: PositiveInt = 6  # training epochs
    batch_size: PositiveInt = 512  # patches a step
    lr: Positive = 2e-3  # peak learning rate
    weight_decay: NonNegative = 1e-4  # AdamW weight decay
    jitter_px: NonNegative = 1.5  # Gaussian error of the training patches' centres
    gain: tuple[Positive, Positive] = (0.7, 1.4)  # random scale of the relative depth
    threads: PositiveInt = 2  # CPU threads while it trains
    veto_power: Power = 0.5  # how hard its doubt lowers a score
    veto_margin: NonNegative = 2.0  # logit above which it lowers no score
    lower_mat_negatives: NonNegativeInt = 16  # lower-mat crossings a training image gives as negatives
    # depth models drawn anew (random parameters) for an image's depth each epoch; none: the dataset's alone
    drawn_sensors: tuple[DepthModel, ...] = ("exact", "structured_light", "active_stereo", "time_of_flight")
    dataset_share: Fraction = 0.4  # share of the images an epoch that give their dataset's sensor depth


class CrossingPointConfig(Strict):
    """The crossing-point stage (:mod:`rebar_data.perception.inference.refine`): where each
    detection's 3D crossing point projects."""

    enabled: bool = True  # train and ship the crossing-point stage
    patch_px: PatchPx = 48  # side of the patch it reads
    context_px: Annotated[int, Field(ge=16, multiple_of=2)] = 72  # side of the square a patch is cut from
    scale: tuple[Positive, Positive] = (0.75, 1.35)  # random scale of the training patches
    widths: Widths = (16, 32, 48, 64)  # convolution widths at full resolution and each halving
    hidden: PositiveInt = 128  # width of the fully connected layer
    epochs: PositiveInt = 6  # training epochs
    batch_size: PositiveInt = 256  # patches a step
    lr: Positive = 2e-3  # peak learning rate
    weight_decay: NonNegative = 1e-4  # AdamW weight decay
    jitter_px: NonNegative = 1.0  # Gaussian error of the training patches' centres
    max_per_image: PositiveInt = 20  # most crossings a training image gives
    threads: PositiveInt = 2  # CPU threads while it trains


class LineCheckConfig(Strict):
    """The line check (:mod:`rebar_data.perception.inference.checks`): a score without depth read again
    with the scores along the detection's two bars."""

    enabled: bool = True  # fit and ship the line check
    regularization: Positive = 1.0  # the logistic regression's C
    floor: Fraction = 0.05  # candidates the first stage scores this or more are evidence
    checked_from: Fraction = 0.3  # those it scores this or more are verified and checked

    @model_validator(mode="after")
    def _checked_above_floor(self) -> LineCheckConfig:
        if not 0.0 < self.floor <= self.checked_from < 1.0:
            raise ValueError(
                f"floor = {self.floor} and checked_from = {self.checked_from} are not accepted; accepted: "
                "0 < floor <= checked_from < 1 (the checked candidates are among the evidence)"
            )
        return self


class AdaptConfig(Strict):
    """The first stage's adapt epochs (:mod:`rebar_data.perception.training.adapt`): after its best epoch,
    more on its images and the second-stage supplements, batch norms frozen."""

    epochs: NonNegativeInt = 3  # adapt epochs (0: none)
    lr: Positive = 1e-3  # peak learning rate
    warmup_epochs: NonNegative = 0.05  # linear warm-up
    supplement_repeats: PositiveInt = 10  # times each supplement image is listed


class InitConfig(Strict):
    """Training that starts from a model's weights (``rebar train --init``): fewer epochs at a lower rate,
    the batch norms frozen (:mod:`rebar_data.perception.training.init`)."""

    epochs: PositiveInt = 4  # first-stage epochs from the model's weights
    lr: Positive = 1e-3  # their peak learning rate
    warmup_epochs: NonNegative = 0.05  # their linear warm-up
    stage_epochs: PositiveInt = 3  # each later stage's epochs from its weights
    stage_lr_scale: Positive = 0.25  # the later stages' peak learning rates, times their own


class TrainConfig(Strict):
    """One training run (``rebar train --config``)."""

    epochs: PositiveInt = 16  # first-stage epochs
    batch_size: PositiveInt = 8  # crops a step
    crop_px: Annotated[int, Field(ge=32, multiple_of=16)] = 384  # side of the square training crops
    crops_per_image: PositiveInt = 2  # crops of each image an epoch
    lr: Positive = 3e-3  # peak learning rate
    weight_decay: NonNegative = 1e-4  # AdamW weight decay
    warmup_epochs: NonNegative = 1.0  # linear warm-up
    patience: PositiveInt = 12  # epochs without a better validation AP before it stops
    heatmap_sigma_cells: Positive = 1.0  # the heatmap target's Gaussian sigma
    offset_weight: Positive = 1.0  # weight of the offset loss
    occluded: Literal["ignore", "negative"] = "ignore"  # occluded crossings: out of the loss, or negatives
    val_every: PositiveInt = 2  # epochs between validations
    val_max_images: PositiveInt = 60  # validation images scored during training
    threads: PositiveInt = 1  # the network's CPU threads (the loader process takes another core)
    seed: NonNegativeInt = 0  # seed of every random draw
    cache_images: bool = True  # keep the decoded training images in memory
    loader_workers: Literal[0, 1] = 1  # 1: batches made in a second process (the same batches)
    model: ModelConfig = ModelConfig()  # the first stage's network
    augment: AugmentConfig = AugmentConfig()  # augmentation
    other_renderer_repeats: NonNegativeInt = 2  # times each second-stage supplement joins the first epochs
    adapt: AdaptConfig = AdaptConfig()  # the adapt epochs
    refine: RefineConfig = RefineConfig()  # the second stage
    depth_check: DepthCheckConfig = DepthCheckConfig()  # the depth check
    crossing_point: CrossingPointConfig = CrossingPointConfig()  # the crossing-point stage
    line_check: LineCheckConfig = LineCheckConfig()  # the line check
    init: InitConfig = InitConfig()  # training from a model's weights (--init)


def resolve_config(
    config: TrainConfig | dict | None, overrides: dict[str, Any], *, source: str = "train settings"
) -> TrainConfig:
    """Settings from a TrainConfig or dict with keyword overrides applied (None values are left out);
    ``source`` names where they came from in an error (the settings file, for ``rebar train --config``)."""
    base = config.model_dump() if isinstance(config, TrainConfig) else dict(config or {})
    base.update({k: v for k, v in overrides.items() if v is not None})
    try:
        return TrainConfig.model_validate(base)
    except ValidationError as e:
        raise ConfigError(format_validation_error(e, source, base, TrainConfig)) from None
