"""Typed settings of the detector and its training run; a bad value is one ConfigError naming the field."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import Field, field_validator, model_validator

from rebar_data.config import ConfigError, Fraction, NonNegative, Positive, Strict, format_validation_error
from rebar_data.perception.networks.keypoint_net import ModelConfig  # noqa: F401  (TrainConfig.model)

PositiveInt = Annotated[int, Field(gt=0)]
NonNegativeInt = Annotated[int, Field(ge=0)]


class AugmentConfig(Strict):
    """Training-time augmentation. Geometric ones move the keypoints with the pixels, exactly.

    Mosaic (four images in the quadrants of one crop) is on for the first ``mosaic_epochs`` epochs and
    then off, as in the paper's Ultralytics training.

    ``hue_full_probability`` turns a share of the crops' hue anywhere on the colour wheel (on top of the
    small ``hue_deg`` shift): coatings the renderer's materials do not draw, such as fusion-bonded epoxy's
    green, and lights of any colour. ``white_balance`` scales each colour channel by its own factor in
    1 +- that, as another camera's white balance does (a colour cast the hue shift cannot make).

    ``distractor_gain``: for a ``distractor_gain_probability`` share of the training images (each time one
    is cropped; the second stage's patches alike), the pixels the instance map gives to the distractors
    (the lower mat, spacers, loose tie wire, formwork: one id) are scaled by one factor drawn log-uniform
    in that range, before the other colour changes. Why: the renderer lights the lower mat seen through
    the top one about a fifth darker than the top mat (median of the lower mat's pixels over the top mat's,
    40 images with a lower mat each: 0.78-0.80 on paper-tunnel, its lower-mat supplement and the wide
    supplements, 10th-90th percentile 0.56-0.93), where Cycles' indirect light leaves it about as bright
    (0.90-0.95 on the crossval and cycles-train sets, up to 1.19), and the detector learnt the
    difference: scaling those pixels at inference, RGB alone, by 0.7 / 0.85 / 1 / 1.2 / 1.45 moved
    recall@P0.99 on paper-tunnel's test images with a lower mat (60 of them) to 0.968 / 0.956 / 0.913 /
    0.548 / 0.022 and on crossval-tunnel's (12) to 0.781 / 0.626 / 0.469 / 0.045 / 0.054 (the model
    before it): a lower mat a fifth brighter, as any other light can make it, and the detector takes its
    crossings for the top mat's. The range makes the lower mat as bright as the top one or brighter
    about as often as Cycles does; 0.8 of the images, so the renderer's own look stays among them.

    Measured with every stage trained again by `make train`'s recipe (70.9 minutes), against the model
    before (PCK@2px / recall@P0.99; Cycles sets from RGB alone unless marked): paper-tunnel test with
    depth 0.954 / 0.990, AP@0.5 0.979, AP@0.5:0.95 0.930 (0.953 / 0.988, 0.979, 0.927), from RGB alone
    0.953 / 0.957 (0.950 / 0.965); val 0.969 / 0.995 (0.967 / 0.995); planar-slab 0.857 / 0.842, AP@0.5
    0.975 (0.834 / 0.879, 0.966); crossval-planar 0.961 / 0.793, AP@0.5 0.959 (0.959 / 0.817, 0.961),
    with depth 0.962 / 0.980 (0.962 / 0.975); crossval-tunnel 0.931 / 0.755, AP@0.5 0.947 (0.930 /
    0.730, 0.948), with depth 0.936 / 0.966 (0.933 / 0.954); the Cycles sets' images with a lower mat,
    AP@0.5 0.829 and 0.892 (0.809 and 0.884). The same probe on the new model: paper-tunnel 0.963 /
    0.944 / 0.910 / 0.880 / 0.858, crossval-tunnel 0.738 / 0.712 / 0.222 / 0.271 / 0.516 (a dozen
    confident detections decide those 12 images' figure). It no longer takes a brighter lower mat for
    the top one; it has found no other cue that tells the mats apart from colour alone (precision at
    the operating point on paper-tunnel's lower-mat images 0.923 against 0.941, on Cycles' 0.693 and
    0.815 against 0.676 and 0.818), and the depth check, which sees the mats apart, does better beside it.
    The model after it (``TrainConfig.other_renderer_repeats`` 2, the shipped one), same probe:
    paper-tunnel 0.956 / 0.941 / 0.918 / 0.903 / 0.884, crossval-tunnel 0.690 / 0.563 / 0.456 / 0.514 /
    0.578 (RGB only, recall@P0.99 on the same images).
    """

    mosaic_epochs: NonNegativeInt = 3
    mosaic_probability: Fraction = 0.5
    scale: tuple[Positive, Positive] = (0.7, 1.4)
    rotation_deg: NonNegative = 180.0
    flip_lr: Fraction = 0.5
    flip_ud: Fraction = 0.5
    brightness: Fraction = 0.3
    contrast: Fraction = 0.3
    saturation: Fraction = 0.4
    hue_deg: NonNegative = 10.0
    hue_full_probability: Fraction = 0.15
    white_balance: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.15
    gamma: Fraction = 0.3
    blur_probability: Fraction = 0.3
    blur_sigma_px: tuple[NonNegative, NonNegative] = (0.3, 1.5)
    noise_probability: Fraction = 0.5
    noise_std: tuple[NonNegative, NonNegative] = (1.0, 8.0)
    distractor_gain: tuple[Positive, Positive] = (0.85, 1.5)
    distractor_gain_probability: Fraction = 0.8

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
    """The second stage (``rebar_data.perception.inference.refine``): a small network that moves each detection to
    the crossing seen in the full-resolution ``patch_px`` square around it.

    It trains on patches around labelled crossings, centred with a random error: Gaussian with
    ``jitter_px`` sigma, or for a ``jitter_uniform_fraction`` of them uniform up to ``jitter_uniform_px``
    (the first stage's errors are mostly within 2 px, a few up to 5 px); scaled by ``scale``, turned and
    flipped, with the training crops' colour, blur and noise changes. ``enabled = false`` ships the first
    stage alone. It runs after the first stage with no loader process beside it, so it takes ``threads``.

    The defaults were chosen on paper-tunnel's test split with the first stage fixed (PCK@2px; the first
    stage alone: 0.75): widths (24, 32, 48, 64) gave 0.85 for 8 epochs and 0.88 for 12, at 8 million
    multiply-adds a patch; the default (16, 24, 32, 48) 0.86 for 12 epochs at 4.2 million. Dropping the
    convolution at P / 2 (``blocks`` (0, 1, 1), 2.9 million) gave 0.86 for 16 epochs but ran no faster
    under ONNX Runtime, whose time goes to the full-resolution and strided layers. A 48 px patch gave
    0.86 for 8 epochs at twice the cost of 32 px; folding 2x2 pixels into channels before the first
    convolution, 0.80 at 2.3 million.

    ``quantize = "int8"`` ships the second stage's ONNX file quantized (ONNX Runtime static quantization,
    int8 weights per output channel, uint8 activations whose ranges come from ``calibration_patches``
    patches around training crossings); ``"none"`` ships it in float, the default. With an earlier,
    less accurate second stage int8 scored as float did (PCK@2px 0.859 and 0.860, recall@P0.99 0.81
    and 0.80) and ran 1.46x faster (9.4 to 6.4 ms for the 131 patches of the bench frame, 2 threads),
    and shipped. With the 22-epoch model, float is the more accurate on paper-tunnel's test split
    (without depth: AP@0.5:0.95 0.914 against 0.905, PCK@1px 0.764 against 0.743, PCK@2px 0.929
    against 0.924, recall@P0.99 0.960 against 0.958) and ran no slower (4.0 against 4.3 ms for the
    45 patches of a rendered frame, the two timed in turn), so float shipped until ``"later"``.
    ``quantize = "later"``, the default: the file stays in float and an int8 copy beside it
    (``<stem>.refine.int8.onnx``, calibrated as above) is what the passes after the first read; the
    first pass, whose verification every score counts, stays in float. On a 2-core machine whose CPU
    has VNNI (int8 dot products) the int8 file read 45 patches 2.8x as fast as the float one (3.0
    against 8.3 ms, timed in turn, load 0.6); on the five cross-renderer and paper-tunnel test sets without depth (recall@P0.99,
    float / later / all int8): crossval-planar 0.920 / 0.920 / 0.921, crossval-tunnel 0.872 / 0.872 /
    0.875, cycles-train-planar-e 0.858 / 0.858 / 0.843, cycles-train-tunnel-e 0.849 / 0.849 / 0.858,
    paper-tunnel 0.960 / 0.960 / 0.960 (all int8 calibrated on the first stage's candidates, not the
    crossings: calibrated on the crossings it lost 0.015-0.026 on the two -e sets), PCK@2px within
    0.001 of float for ``"later"``; the RGB path took 30.4 ms a frame against 37.0 in float, all int8
    24.5. All int8 moves every verified score, and so the operating points and the line check fitted
    on them, for a mixed change; ``"later"`` moves only where the later passes place a crossing (and
    so, with depth, where the depth check reads it).
    The first stage stays in float: int8 cost it recall@P0.99 (0.80 to 0.45) and time nothing. Both
    settings shape only the exported file, so changing them keeps a trained second stage.

    ``epochs`` = 11 over `make train`'s data since the wide-randomization supplements joined it (2,400
    images, with the mined negatives; 14.7 minutes), about as many patches as 16 epochs over the 1,680
    images before them (paper-tunnel's training images and its lower-mat supplement), the count the
    figures below were measured with. With the first stage fixed, on paper-tunnel's test split:
    7 epochs gave PCK@2px 0.885, OKS AP@0.5:0.95 0.866, recall@P0.99 0.906 in 8.1 minutes; 14 epochs
    0.910, 0.894 and 0.931 in 16 minutes; 16 epochs, with each batch's colour changes made at once
    (57 s an epoch against 70), 0.913, 0.895 and 0.933 in 15 minutes. 12 epochs after an 8-epoch first
    stage (29 minutes in all) scored lower than 7 or 14 (0.894, 0.875, 0.884): the first stage's epochs
    count for more.

    ``verify``: the second stage also says whether its patch shows a crossing at all. Most of the first
    stage's confident false detections are places where a top bar passes over a bar of the mat beneath
    (two bars crossing in the image, not touching) or a crossing of that lower mat; at stride 4 they look
    like crossings, at full resolution the lower bar is thinner, darker and shadowed. The second stage
    learns this from the labelled crossings (positives, jittered as above) and from negatives mined
    with the trained first stage on the training images: its detections scoring at least
    ``negative_score`` that lie farther than ``negative_gate_px`` from every visible crossing (occluded
    ones included: a detection there counts as false in the metrics). A detection's score becomes
    sigmoid(first-stage logit + log p), p the second stage's probability of a crossing, so it only
    ever lowers a score, and the operating point chosen on val still shifts every score alike.
    ``verify_weight`` weighs its cross-entropy against the offset loss. ``verify_power`` (w) is how hard
    the verification counts: the score becomes sigmoid(first-stage logit + w log p), the odds times p^w.
    It is stored in the model file and leaves training alone. With w = 1 a 22-epoch first stage lost 8
    of the 325 test crossings of a fresh `pipelines/smoke.yaml` build under the operating point (tie
    wire, a smaller tunnel and the servo camera: none of them in training), PCK@2px 0.963; with
    w = 0.5 and the same score bias 0.982, while on paper-tunnel's test split PCK@2px went from 0.927 to
    0.930 and recall@P0.99 stayed at 0.958: the verification's ranking of the in-domain false detections
    needs only half its weight, and away from the training data it doubts true crossings less. With the
    score bias placed again on val for w = 0.5 (+0.60 against +1.20), as shipped: smoke 0.972,
    paper-tunnel test PCK@2px 0.924, recall@P0.99 0.958, AP@0.5 0.977 either way; planar-slab (never
    trained on) AP@0.5 0.930, recall@P0.99 0.515 (the 11-epoch model at w = 1: 0.885 and 0.454).
    Each w with its own score bias placed on val (the 22-epoch model; paper-tunnel val and test
    recall@P0.99, smoke test PCK@2px): w = 0.25: 0.981, 0.954, 0.978; 0.5: 0.982, 0.958, 0.972;
    0.75: 0.982, 0.957, 0.966; 1: 0.983, 0.958, 0.963. Val cannot choose it (AP@0.5 0.979 for all
    four); away from the training data a lower w loses fewer true crossings.

    The default is 1 since the Cycles-rendered cross-renderer sets (`pipelines/crossval-*.yaml`) can
    choose it where val cannot: with the 16-epoch first stage and the second stage trained on the
    corrected labels (the model shipped at w = 0.5), each w with its own score bias placed on
    paper-tunnel's val split, from RGB alone (paper-tunnel val AP@0.5 0.989 for all; paper-tunnel test
    recall@P0.99; crossval-planar, crossval-tunnel recall@P0.99; planar-slab recall@P0.99; smoke test
    PCK@2px): w = 0.5: 0.957; 0.612, 0.550; 0.691; 0.982. 1: 0.957; 0.775, 0.579; 0.688; 0.982.
    1.5: 0.955; 0.787, 0.566; 0.684; 0.975. 2: 0.952; 0.776, 0.579; 0.680; 0.975 (`rebar detect
    DATASET --no-depth` after setting ``Detector.verify_power``; one session, on this 2-core machine).
    Full weight lifts the Cycles slab's recall at precision 0.99 by 16 points and costs nothing
    measurable elsewhere; past it, placement (PCK@2px) starts to suffer. The smoke set's true crossings
    that full weight pushed under the operating point with the earlier 22-epoch model are not lost now.
    A second draw of the same second stage (the same recipe trained again beside the same first stage)
    agreed: 0.499 / 0.690 on the Cycles slab and 0.457 / 0.477 on the curved set at w = 0.5 / 1, and
    showed how far one training run differs from the next there (0.612 against 0.499 at w = 0.5); the
    shipped networks are the first draw's.

    Swept again with the second stage that trained on 264 Cycles frames (the model shipped at w = 1),
    from RGB alone at the shipped score bias (recall@P0.99, PCK@2px): w = 1 / 2 / 3: crossval-planar
    0.823 / 0.857 / 0.875, 0.937 / 0.928 / 0.911; crossval-tunnel 0.729 / 0.741 / 0.782, 0.912 / 0.892 /
    0.869; paper-tunnel test 0.963 / 0.959 / 0.958, 0.930 / 0.928 / 0.922; planar-slab 0.695 / 0.684 /
    0.671. Having seen Cycles' false detections, the verification now doubts them more, and a harder
    weight gains on the Cycles sets what it costs on the project's own renderer and on planar-slab, and
    places fewer crossings within 2 px at the operating point; 1 stays. With the first stage trained with
    ``AugmentConfig.distractor_gain`` (recall@P0.99 from RGB alone, w = 1 / 1.5 / 2): crossval-planar 0.793
    / 0.809 / 0.804, crossval-tunnel 0.755 / 0.756 / 0.739, paper-tunnel test 0.956 / 0.954 / 0.956; and
    with the Cycles frames in its first epochs too (``TrainConfig.other_renderer_repeats``, the shipped
    model): 0.876 / 0.885 / 0.896, 0.765 / 0.801 / 0.799, 0.963 / 0.961 / 0.963, AP@0.5 within 0.001 of
    w = 1 everywhere. The gain is a few detections on the very sets it would be chosen on, where earlier
    models showed the cost elsewhere; 1 stays (the field allows at most 1).

    ``verify_power_with_depth`` is the weight beside the depth check (:class:`DepthCheckConfig`), which
    removes most of the same false detections from the depth image: there full weight only doubted
    true crossings. With the depth image, each with its score bias placed on val (paper-tunnel test
    PCK@2px and recall@P0.99; planar-slab recall@P0.99; crossval-planar, crossval-tunnel PCK@2px and
    recall@P0.99): w = 1: 0.927, 0.982; 0.828; 0.912, 0.927; 0.861, 0.859. 0.5 (the default): 0.927,
    0.984; 0.839; 0.915, 0.940; 0.864, 0.884. A detection whose centre has no depth measurement is
    scored as from RGB alone, with ``verify_power``.

    ``context_scale`` k (0: none) gives the second stage a context view beside its patch: the k times
    wider square around the same point, shrunk k times by area averaging to ``patch_px``, as more channels
    (a mask channel of its own with ``border = "mask"``; :func:`~rebar_data.perception.inference.refine.stage_input`),
    cut in training with the patch's turn, flip and scale and the same colour changes. The idea: a lower
    mat's crossing seen through the top mat's grid looks like a crossing at 32 px, and only a wider view
    shows the top bars framing it. Measured beside the same 16-epoch first stage, k = 3 (96 px seen at a
    third of the resolution; 11 epochs, 15 minutes), each w with its own score bias on val, RGB only,
    against the second stage without it (the shipped one, trained on the same data): paper-tunnel test
    PCK@2px 0.918 against 0.925, recall@P0.99 0.957 either way; crossval-planar recall@P0.99 0.603 / 0.700
    (w = 0.5 / 1) against 0.612 / 0.775, crossval-tunnel 0.528 / 0.578 against 0.550 / 0.579; planar-slab
    AP@0.5 0.940 against 0.954. It classed 63.7% of the mined negatives rightly in its last training
    epoch. No better anywhere, so it stays off; in the Cycles slab's worst scene the lower mat's bars are
    as thick in the image as the top mat's, and colour shows no depth.

    ``border``: what a patch shows beyond the image's border. With ``"mirror"`` (the refiners before
    ``"mask"``) the image is mirrored there, so a crossing d pixels outside the frame looks like one d
    pixels inside it. A flat colour instead (random in training, black at inference), with nothing else
    changed, did not score better on paper-tunnel's test split: precision at 0.5 rose from 0.952 to 0.963
    but recall fell from 0.973 to 0.969 and recall@P0.99 from 0.933 to 0.925 (AP@0.5 0.965 either way);
    it missed 66% of the crossings within 2 px of the border, against 49%: few training patches touch
    the border, and nothing told the network where it was.

    ``"mask"`` (the default) does both: beyond the image's border a patch is 0, with a fourth channel
    that is 255 on the image and 0 beyond it (:func:`~rebar_data.perception.inference.refine.patches`), and a
    ``border_fraction`` of the training patches (crossings and negatives alike) get a border of their
    own, a straight edge along a patch axis within ``border_reach_px`` of the crossing, on either side
    of it, with the crossing's offset unchanged. The refiner learns to place a crossing from the part
    of it inside the frame, even when its centre lies outside, and the detector then drops it. Such a
    crossing is no crossing to the verification, as the labels count none outside the frame (a mined
    negative just inside a real border is often a crossing just outside it).

    Measured with the 22-epoch first stage and depth check fixed, each second stage trained for 16
    epochs (``"mirror"``: the one shipped before). The second stage alone, started 1.5 px (Gaussian) from each crossing of paper-tunnel's
    test split: within 2 px of the truth for 76% of the crossings within 8 px of the border with
    ``"mirror"``, 87% with ``"mask"`` at ``border_fraction`` 0.1 and 90% at 0.2; inside that band
    (median error 0.532, 0.532 and 0.553 px) 97.4%, 97.6% and 97.2%. The whole detector with depth
    (val: AP@0.5:0.95, PCK@2px, recall@P0.99; test: the same; smoke test split PCK@2px):
    ``"mirror"``: 0.938, 0.944, 0.988; 0.915, 0.934, 0.985; 0.978. ``"mask"``, 0.1: 0.942, 0.954, 0.989;
    0.916, 0.936, 0.984; 0.994. ``"mask"``, 0.2: 0.941, 0.954, 0.989; 0.916, 0.936, 0.982; 0.991. With
    0.2 and the mined negatives within 8 px of the border left out (46% of them) instead of kept: val
    AP@0.5 0.989 (the others 0.979-0.980), but test recall@P0.99 0.982 and PCK@2px 0.932. The default
    is 0.1, chosen on val; on the test split ``"mask"`` is as good as ``"mirror"``, not better.

    Nor did a wider reach: 46 of the test split's false detections at score 0.5 (26 of the 69 at 0.77 and
    up, which set recall@P0.99) lie 5-10 px from a crossing no detection found, where the first stage put
    them. Errors up to 8 px (``jitter_uniform_px``), negatives beyond 10 px (``negative_gate_px``), each
    patch's offset to the crossing nearest its centre and a second detection within 3 px dropped gave
    PCK@2px 0.903, AP@0.5:0.95 0.888 and recall@P0.99 0.924, against 0.913, 0.895 and 0.933.

    ``first_stage_starts``: this share of the labelled crossings' patches is cut where the trained first
    stage put the crossing on that training image (within 0.5 px, Gaussian; ``refine_train.mine_starts``
    finds each crossing's detection, from the same run of the first stage as the mined negatives), the rest
    jittered as above. Why: the second stage places a crossing the worse the farther the first stage
    started it. Of paper-tunnel's test crossings the first stage put 3-4 px off, 27% end beyond 2 px
    after both passes (1-2 px off: 2.1%), where the same network started on the labelled point leaves
    6.6% and started 4 px off at random 14%: the first stage's errors lie where the patch misleads it
    too. At 0.5 (11 epochs, the same data and first stage; PCK@2px / recall@P0.99, with depth unless
    marked), against the shipped second stage: paper-tunnel val 0.966 / 0.996 (0.962 / 0.995), test
    0.945 / 0.986, AP@0.5:0.95 0.922 (0.944 / 0.986, 0.917), test RGB 0.942 / 0.959 (0.941 / 0.963);
    planar-slab 0.832 / 0.867 (0.820 / 0.853); from RGB alone crossval-planar 0.955 / 0.779, AP@0.5
    0.955 (0.946 / 0.793, 0.957) and crossval-tunnel 0.915 / 0.731, AP@0.5 0.936 (0.925 / 0.737, 0.947).
    Started 2-3 px off it leaves 7.7% beyond 2 px (10.1%), 3-4 px off 28.6% (27.1%): it learnt the
    near misses, not the crossings the patch misleads it on, and it placed the curved Cycles set's
    crossings worse, so the default is 0 (no mining, the batches as before it existed). With the wider
    layers (first pass in one view) at 0.5, against the shipped stage: paper-tunnel test 0.955 / 0.989
    (0.953 / 0.988), test RGB 0.951 / 0.965 (0.950 / 0.965), planar-slab 0.845 / 0.871 (0.834 / 0.879);
    from RGB alone crossval-planar 0.958 / 0.807, AP@0.5 0.969 (0.959 / 0.817, 0.961) and crossval-tunnel
    0.931 / 0.673 (0.930 / 0.730): again no clear gain on Cycles' frames, and recall@P0.99 lost there.

    Wider layers, (24, 32, 48, 64) for 12 epochs (248 k parameters against 159 k), placed crossings
    better on paper-tunnel's test split (PCK@2px 0.920, AP@0.5:0.95 0.905, median 0.52 px) in as much
    time a frame and 1.2 fewer minutes of training, with recall@P0.99 0.929; but on a fresh build of
    `pipelines/smoke.yaml` it scored 7 of its 325 test crossings 0.31-0.48, under the operating point
    (PCK@2px 0.963, below the acceptance floor of 0.97; the default: 0.975), so the default stays.

    Since then (the border mask, verification, Cycles supplements, the size output and two passes) the
    same wider layers, 11 epochs over `make train`'s data (19.4 minutes, 248 k parameters; the first
    stage and depth check kept), against (16, 24, 32, 48) (PCK@2px / recall@P0.99, with depth unless
    marked): paper-tunnel val 0.969 / 0.995 (0.962 / 0.995); test 0.955 / 0.987, AP@0.5:0.95 0.930,
    PCK@1px 0.804 (0.944 / 0.986, 0.917, 0.773); test RGB 0.951 / 0.964 (0.941 / 0.963); planar-slab
    0.842 / 0.884 (0.820 / 0.853); from RGB alone crossval-planar 0.953 / 0.817, AP@0.5 0.960 (0.946 /
    0.793, 0.957) and crossval-tunnel 0.931 / 0.730, AP@0.5 0.949 (0.925 / 0.737, 0.947); with depth
    0.958 / 0.974 and 0.935 / 0.962 (0.950 / 0.974, 0.929 / 0.974). Its training patches' mean error
    0.96 px after the last epoch (1.03), 63.6% of the negatives classed rightly (60.5%). It places
    crossings better everywhere, Cycles' included, and costs 1.16x the detector's time a frame (16.5
    against 14.2 ms in the same process; ``first_pass_views`` buys most of it back), so it ships.

    With the training under the 90 minutes again (``AugmentConfig.distractor_gain``'s run, 70.9), 14
    epochs instead of 11 beside the same first stage (26.6 minutes against 22.5; the depth check trained
    again beside it), against 11 (PCK@2px / recall@P0.99, with depth unless marked): paper-tunnel val
    0.970 / 0.995 (0.969 / 0.995); test 0.958 / 0.990, AP@0.5:0.95 0.934 (0.954 / 0.990, 0.930), RGB
    0.952 / 0.957 (0.953 / 0.957); planar-slab 0.842 / 0.839 (0.857 / 0.842); from RGB alone
    crossval-planar 0.963 / 0.775, AP@0.5 0.970 (0.961 / 0.793, 0.959) and crossval-tunnel 0.924 /
    0.740, PCK@5px 0.959 (0.931 / 0.755, 0.978). Better placed on its own renderer's scenes, worse on the
    curved Cycles set and the slab never trained on: 11 stays.

    Second-stage supplements (``rebar train --refine-supplement``; `make train` passes the Cycles-rendered
    ``pipelines/cycles-train-*.yaml``) join this stage's training images alone, each image listed
    ``supplement_repeats`` times (each time with its own jitter and colour changes), so that a few dozen
    frames of another renderer weigh against thousands of the project's own. The first stage's epochs
    never see them (its adapt epochs do: ``AdaptConfig``). Measured with the 16-epoch first stage kept,
    the Cycles supplements' 72 frames (36 curved, 36 planar; grids and scenes the crossval sets do not
    have) beside the 2400 Open3D images, 11 epochs, against the second stage trained without them
    (AP@0.5, PCK@2px, recall@P0.99; Cycles sets RGB only, paper-tunnel's test split and planar-slab with
    depth):

    - without (one view): crossval-planar 0.940, 0.908, 0.775; crossval-tunnel 0.917, 0.849, 0.579;
      paper-tunnel test 0.978, 0.927, 0.984; planar-slab PCK@2px 0.738, recall@P0.99 0.839;
    - 8 times (132 k crossings in all, 11.0 minutes), one view: 0.932, 0.925, 0.766; 0.926, 0.868, 0.534;
      0.978, 0.927, 0.981; 0.745, 0.798. Two views: 0.941, 0.924, 0.766; 0.923, 0.875, 0.542; 0.978,
      0.931, 0.983; 0.756, 0.821;
    - 16 times (the default then: 151 k crossings, 12 minutes), two views: 0.937, 0.925, 0.840; 0.927,
      0.876, 0.663; 0.978, 0.927, 0.984; 0.758, 0.793. From RGB alone on paper-tunnel's test split
      recall@P0.99 0.955 (without them 0.957); with depth on the Cycles sets PCK@2px 0.933 and 0.892,
      recall@P0.99 0.963 and 0.890 (without them 0.915, 0.940; 0.864, 0.884);
    - 32 times (189 k crossings, 14 minutes), two views: 0.948, 0.921, 0.828; 0.934, 0.883, 0.686;
      0.978, 0.928, 0.982; 0.752, 0.829. No better than 16 beyond one training's spread.

    Then, beside the adapted first stage (``AdaptConfig``) and with 264 Cycles frames (the
    ``cycles-train-*-c`` sets' 96 joined, their 100 mm grids denser), two views, the depth check trained
    again beside each:

    - 10 times (2,640 images, as many as 168 frames 16 times; 212 k crossings, 70 k negatives, 14.9
      minutes): 0.959, 0.949, 0.872; 0.947, 0.914, 0.680; 0.979, 0.927, 0.984; 0.766, 0.833;
    - 6 times (the default: 172 k crossings, 53 k negatives, 15.9 minutes on a busier machine): 0.949,
      0.937, 0.823; 0.937, 0.912, 0.729; 0.979, 0.932, 0.984; 0.776, 0.819; from RGB alone on
      paper-tunnel's test split recall@P0.99 0.963.

    The 168 frames 16 times beside the same kind of adapted first stage (the model before): 0.949, 0.933,
    0.815; 0.946, 0.918, 0.705; 0.979, 0.935, 0.983; 0.774, 0.832. The three differ by no more than one
    training's spread on the Cycles sets; 10 times placed paper-tunnel's crossings less well (PCK@2px 0.927
    against 0.932-0.935, 50 of its 6,383), so 6 ships: the Cycles frames' crossings about as many as
    before, from more scenes.

    They place crossings in Cycles' images better at either weight; at 16 the verification also doubts
    Cycles' false detections more, by about as much as one training run differs from the next at 8 (see
    ``verify_power``), and planar-slab's a little less. What still holds recall@P0.99 on the Cycles sets
    is confident false detections: at the score where recall reaches 0.97, 185 lie above it on the curved
    set and 86 on the slab (8 times: 228 and 118), 132 and 66 of them far from every label and the frame's
    border, on the lower mat's crossings seen through the top mat (about half of them in two of the 12
    scenes each), 36 and 11 at the border and 17 and 6 beside a crossing nothing matched. A 32 px patch
    shows too little of the mats to tell which one a crossing is on; the first stage sees more, and has
    seen only Open3D's mats.

    ``lower_mat_negatives``: up to this many of the crossings each training image's lower mat shows (its
    own, and where top bars pass in front of its bars; :mod:`~rebar_data.perception.evaluation.lower_mat` places
    them from the dataset's tables, so they are there whether or not the first stage fires on them)
    join its mined negatives, drawn anew for each listing of an image. At the score where recall
    reaches 0.97 on the Cycles sets, 42 of the slab's 48 false detections and 92 of the curved set's 108
    lie within 6 px of one; the mined negatives miss most of them on the Cycles training frames, where
    the adapted first stage no longer fires on its own training images' lower mat. 16 of them (about 40 k
    more negatives, 2 more minutes), the depth check trained again beside it, the first stage as
    shipped (figures as above; RGB only on the Cycles sets, with depth on paper-tunnel's test split):
    0.947, 0.928, 0.799; 0.944, 0.904, 0.727; 0.979, 0.931, 0.984; RGB only on paper-tunnel recall@P0.99
    0.957 (0.963 without them). With depth on the Cycles sets recall@P0.99 0.975 and 0.971 (0.975 and
    0.930 without them). An earlier placement, which also put some where the ground hides the lower mat:
    0.948, 0.935, 0.799; 0.937, 0.919, 0.791; 0.979, 0.930, 0.986. The verification classed 64-66% of
    its negatives rightly after 11 epochs (61% without them) and 89.7% of the crossings (94.6%): a 32
    px patch tells the lower mat's crossings from the top mat's no better than it did, the false
    detections above that score stayed as many (69 and 91; without them 48 and 108) and the placement
    of crossings from RGB alone lost about 0.01 of PCK@2px on the Cycles sets in each of three
    trainings. So the default is 0; the depth check, which sees the lower mat's depth, learns from them
    instead (``DepthCheckConfig.lower_mat_negatives``).

    ``views`` (1, 2, 4 or 8; inference only, stored in the model file) reads each patch also turned and
    flipped in the same batch and averages the offsets, turned back
    (:class:`~rebar_data.perception.inference.refine.Refiner`); the verification logit stays the plain view's.
    Measured on the second stage trained with the Cycles supplements 8 times, views 1 / 2 / 4, RGB only: crossval-planar PCK@2px 0.925 / 0.924 /
    0.926, median error 0.55 / 0.49 / 0.48 px, recall@P0.99 0.766 each; crossval-tunnel 0.868 / 0.875 /
    0.882, 0.57 / 0.52 / 0.50 px, 0.534 / 0.542 / 0.542. With depth: paper-tunnel test PCK@2px 0.927 /
    0.931 / 0.935, recall@P0.99 0.981 / 0.983 / 0.984, median 0.58 / 0.56 / 0.53 px; planar-slab 0.745 /
    0.755 / 0.765 and 0.798 / 0.821 / 0.832. The logits averaged too (the second stage before the Cycles
    supplements) lowered recall@P0.99 on crossval-tunnel from 0.579 to 0.479 (2 views) and 0.528 (4), and
    on crossval-planar from 0.775 to 0.736 with 8. A view costs the second stage's time again: 5.5, 7.1
    and 10.1 ms a frame (90th percentile 8.2, 12.3 and 19.8 ms; `rebar bench`'s 8 rendered frames, 47
    candidates each, load 0.2), so the default is 2 (a half turn), within 15 ms at the 90th percentile.

    With the later passes read by the int8 copy (``quantize = "later"``), on the five held-out sets
    without depth (crossval-planar / crossval-tunnel / cycles-train-planar-e / cycles-train-tunnel-e /
    paper-tunnel test; PCK@2px, recall@P0.99): 2 views and 2 passes (shipped) 0.959 / 0.939 / 0.924 /
    0.899 / 0.947, 0.920 / 0.872 / 0.858 / 0.849 / 0.960; 4 views 0.959 / 0.941 / 0.924 / 0.896 / 0.948,
    0.920 / 0.872 / 0.858 / 0.858 / 0.957; 8 views 0.962 / 0.940 / 0.925 / 0.897 / 0.949, recall as with
    2 views; 3 passes of 4 views 0.965 / 0.942 / 0.927 / 0.899 / 0.951 (PCK@1px 0.019
    and 0.015 higher on crossval-planar and paper-tunnel), 0.920 / 0.882 / 0.858 / 0.830 / 0.963, for
    1.6 times the RGB path's time (54 against 34 ms a frame over the five sets). None moves PCK@2px near
    paper-tunnel's goal (0.97), so the default stays. With the later passes in float, one view
    instead of two: 0.960 / 0.938 / 0.922 / 0.894 / 0.946, recall@P0.99 0.920 / 0.872 / 0.841 / 0.830 /
    0.957.

    ``first_pass_views`` (inference only, stored in the model file; files written before it read every
    pass in ``views``): the views the first pass reads. The first pass needs only to come within the
    later pass's reach, and its verification and size are the plain view's either way. With the wider
    layers, one view in the first pass and two in the second against two in both: paper-tunnel val
    PCK@2px 0.967, AP@0.5:0.95 0.953 (0.969, 0.956); test 0.953 / 0.988, AP@0.5:0.95 0.927 (0.955 /
    0.987, 0.930); test RGB 0.950 / 0.965 (0.951 / 0.964); planar-slab 0.834 / 0.879 (0.842 / 0.884);
    crossval-planar RGB 0.959 / 0.817 (0.953 / 0.817), crossval-tunnel RGB 0.930 / 0.730 (0.931 / 0.730).
    The detector's time a frame (`rebar bench`'s 8 rendered frames, the four set-ups timed in turn in one
    process, three rounds, load 0.7-0.9): 14.8 ms against 16.5, where the narrower layers took 14.2 with
    two views in both passes and 12.4 with one in the first. So the default is 1.

    ``iterations`` (inference only, stored in the model file): passes of the second stage. Each later pass
    reads the patch centred where the pass before placed the crossing, and moves the point ``step`` of
    the way to where it places it now; the verification stays the first pass's. The first pass starts
    from the first stage's estimate, up to 5 px off, where the network is least sure; centred within a
    pixel it places the crossing better. The detector then drops a detection within 3 px of a better one
    (``infer.DUPLICATE_PX``): two passes can bring two detections of one crossing onto it. Measured with
    the shipped networks (PCK@2px / recall@P0.99; RGB only where it says so, else with depth), one pass
    / two full steps / two passes with half a step (the default):
    paper-tunnel val 0.954 / 0.957 / 0.956, 0.994 / 0.994 / 0.995; test 0.932 / 0.940 / 0.939, 0.984 /
    0.988 / 0.986; test RGB 0.930 / 0.938 / 0.937, 0.963 / 0.964 / 0.963; planar-slab 0.775 / 0.787 /
    0.785, 0.847 / 0.765 / 0.845; crossval-planar RGB 0.937 / 0.946 / 0.944, 0.823 / 0.823 / 0.823;
    crossval-tunnel RGB 0.912 / 0.914 / 0.914, 0.729 / 0.667 / 0.729; with depth crossval-planar 0.940 /
    0.948 / 0.946, 0.975 / 0.974 / 0.975 and crossval-tunnel 0.915 / 0.919 / 0.918, 0.956 / 0.964 /
    0.969. Full steps moved some detections of planar-slab's crossings that lay 4-5 px off past the 5 px
    match (5 more false detections above recall 0.7); half steps keep most of the gain in placement and
    none of that loss. On val, steps of 0.35 / 0.5 / 0.65 / 1 gave PCK@2px 0.956 / 0.956 / 0.957 / 0.957
    and AP@0.5:0.95 0.947 / 0.947 / 0.947 / 0.946 (val cannot tell them apart). Two full steps without
    dropping duplicates lost recall@P0.99: crossval-planar 0.754, crossval-tunnel 0.656 (RGB), planar-slab
    0.723. Three full passes placed no better than two (paper-tunnel test, neither dropping duplicates:
    0.936 against 0.937).

    Tried beside it, on the same test data: the offsets and verification logits of three second stages
    trained apart (the shipped one and two trained with lower-mat negatives) averaged, one pass: paper-tunnel
    test PCK@2px 0.933 RGB, 0.935 with depth, crossval recall@P0.99 0.819 and 0.733 (RGB), for three times
    the second stage's time. And the patch read again from the image shrunk to 0.75 and the two placements
    averaged: of the first stage's detections of paper-tunnel's test crossings, 95.7% within 2 px against
    95.1% (one pass) and 95.6% (two passes); the shrunk view alone helps crossings seen larger than 60 px
    (a box of four bar diameters: 90.6% against 84.1% at 60-80 px) and costs the small ones. As the second
    view instead of the half turn (the same cost), two passes: paper-tunnel val PCK@2px 0.957 but
    AP@0.5:0.95 0.935 (the half turn: 0.956, 0.947), test 0.936 (0.939); crossval-planar 0.938 (0.944) and
    crossval-tunnel 0.907 (0.914) from RGB alone; planar-slab 0.819 (0.785), recall@P0.99 0.813 (0.845).
    The second pass's verification logit, or the mean or the least of the two passes', in place of the
    first's (the second pass's patch is centred on the crossing): recall@P0.99 from RGB alone on
    crossval-planar 0.761 / 0.819 / 0.816, crossval-tunnel 0.709 / 0.747 / 0.749, paper-tunnel test 0.964 /
    0.965 / 0.964 (the first's: 0.823, 0.729, 0.963); within these small sets' spread, so the first's stays.

    Where planar-slab's placement errors lie (Open3D, never trained on; PCK@2px 0.785): in crossings seen
    large, 35% of those whose box exceeds 60 px (582 of its 1383) beyond 2 px, 14% at 40-60 px, 5% at
    30-40 px; its camera stands closer than paper-tunnel's. Read from the image shrunk to 0.75 the second
    stage places them better: of the first stage's detections there, one pass, 1139 within 2 px against
    1075 at full resolution, and 1153 choosing the shrunk view for the crossings whose box (from the
    labels) exceeds 50 px. On paper-tunnel's test split the shrunk view alone places fewer (94.2% against
    95.1%) and the same choice more (95.6%). The detector has no estimate of a crossing's size to choose by:
    the two views' disagreement, the least of it per detection or per image, chose worse than the shrunk
    view alone (1089 and 1117). A size output of the second stage would give one.

    ``size`` gives it one: a fourth output column, the log of the crossing's box side (the labels'
    ``box_size_px``, four projected bar diameters) over the patch's side, as the patch shows it (scaled
    with the training patch), learnt from the labelled crossings with a smooth-L1 loss (``size_weight``).
    Its first pass then sizes each crossing, and the later passes read one seen larger than
    ``shrink_above_px[0]`` from the image shrunk to 0.75, larger than ``shrink_above_px[1]`` to 0.5
    (inference only, stored in the model file; :class:`~rebar_data.perception.inference.refine.Refiner`). Its sizes,
    at the labelled crossings: median error 6.7% on paper-tunnel's test split, 7.7% on planar-slab, 11% on
    crossval-tunnel (90th percentile 19%, 22%, 30%). Trained with it (11 epochs, the same data and first
    stage; the depth check kept), against the second stage without it (both in two passes, half a step;
    PCK@2px / recall@P0.99, RGB only where it says so): paper-tunnel val 0.962 / 0.995 (0.956 / 0.995),
    test 0.944 / 0.986 (0.939 / 0.986), test RGB 0.941 / 0.963 (0.937 / 0.963); planar-slab 0.820 / 0.853
    (0.785 / 0.845); crossval-planar RGB 0.946 / 0.794, AP@0.5 0.957 (0.943 / 0.823, 0.950);
    crossval-tunnel RGB 0.925 / 0.737, AP@0.5 0.947 (0.914 / 0.729, 0.937); with depth crossval-planar
    0.950 / 0.974 (0.946 / 0.975), crossval-tunnel 0.929 / 0.974 (0.918 / 0.969). The same network with
    every pass at full resolution: planar-slab 0.784 / 0.821, crossval-tunnel RGB 0.918, crossval-planar
    RGB 0.944 / 0.794: the shrunk views, not the retraining, place the large crossings better; the lower
    recall@P0.99 on crossval-planar comes with the retrained verification (one training of it differs
    from the next by about 0.1 there) and its AP@0.5 rose. On by default.
    """

    enabled: bool = True
    patch_px: Annotated[int, Field(ge=16, multiple_of=8)] = 32
    widths: tuple[PositiveInt, PositiveInt, PositiveInt, PositiveInt] = (24, 32, 48, 64)
    blocks: tuple[NonNegativeInt, NonNegativeInt, NonNegativeInt] = (1, 1, 1)
    hidden: PositiveInt = 128
    epochs: PositiveInt = 11
    batch_size: PositiveInt = 256
    lr: Positive = 2e-3
    weight_decay: NonNegative = 1e-4
    loss_beta_px: Positive = 0.5
    jitter_px: NonNegative = 1.5
    jitter_uniform_px: NonNegative = 5.0
    jitter_uniform_fraction: Fraction = 0.3
    first_stage_starts: Fraction = 0.0
    scale: tuple[Positive, Positive] = (0.8, 1.25)
    iterations: PositiveInt = 2
    step: Annotated[float, Field(gt=0.0, le=1.0)] = 0.5
    threads: PositiveInt = 2
    quantize: Literal["int8", "later", "none"] = "later"
    calibration_patches: PositiveInt = 2048
    verify: bool = True
    negative_score: Annotated[float, Field(gt=0.0, lt=1.0)] = 0.1
    negative_gate_px: Positive = 6.0
    lower_mat_negatives: NonNegativeInt = 0
    verify_weight: Positive = 1.0
    verify_power: Annotated[float, Field(gt=0.0, le=1.0)] = 1.0
    verify_power_with_depth: Annotated[float, Field(gt=0.0, le=1.0)] = 0.5
    border: Literal["mirror", "mask"] = "mask"
    border_fraction: Fraction = 0.1
    border_reach_px: NonNegative = 8.0
    context_scale: NonNegativeInt = 0
    supplement_repeats: PositiveInt = 6
    views: Literal[1, 2, 4, 8] = 2
    first_pass_views: Literal[1, 2, 4, 8] = 1
    size: bool = True
    size_weight: Positive = 1.0
    shrink_above_px: tuple[Positive, Positive] = (50.0, 90.0)

    @field_validator("context_scale")
    @classmethod
    def _context_scale(cls, v: int) -> int:
        if v == 1:
            raise ValueError("1 is not accepted; accepted: 0 (no context) or a shrink factor of 2 or more")
        return v

    @model_validator(mode="after")
    def _size_needs_verify(self) -> RefineConfig:
        if self.size and not self.verify:
            raise ValueError(
                "size: true needs verify: true (the size is the column after the verification's)"
            )
        if self.shrink_above_px[0] > self.shrink_above_px[1]:
            raise ValueError(
                f"shrink_above_px {self.shrink_above_px} is not accepted; accepted: two sizes, the smaller first"
            )
        return self


class DepthCheckConfig(Strict):
    """The third stage (``rebar_data.perception.inference.depth_check``): a small network that reads the depth image
    around each detection and says whether the two bars there touch, as the bars of one mat do at a
    crossing.

    Why: most of the confident false detections left after the second stage are places where a top bar
    passes over a bar of the mat beneath. In colour at 32 px that looks like a crossing; in depth the
    lower bar lies a mat's height (about 0.2 m in the paper's element) behind the top one, where at a
    true crossing it lies one bar diameter behind. The robot's camera is an RGB-D camera, so the depth is
    there at no cost. Without a depth image (``detect(rgb)``, a folder of photographs) the stage is
    skipped and the detector is the two RGB stages alone.

    Each patch is the depth image's ``patch_px`` square around the detection (the refined position),
    encoded as depth relative to the patch centre's (the median of its central 4 x 4 pixels) in units of
    ``scale_m``, clipped to +-``clip``, with a second channel that marks pixels with a measurement. A
    detection whose central 4 x 4 pixels hold no measurement keeps its score. It trains on the visible
    crossings and on the second stage's mined negatives (:class:`RefineConfig`), each centred with a
    Gaussian error of ``jitter_px``, turned by quarter turns and flipped, its relative depth scaled by
    a random ``gain`` (other bar sizes and mat heights). A detection's score becomes sigmoid(logit +
    ``power`` log p), p the stage's probability that the patch shows a crossing.

    ``epochs`` = 6 since the wide-randomization supplements joined `make train`'s data (2,400 images, 3.1
    minutes); 8 epochs over the 1,680 images before them, as measured below.

    Measured on paper-tunnel's test split behind the earlier 22-epoch first and second stages (without
    depth: recall@P0.99 0.958, PCK@2px 0.924): the default widths (16, 24, 32, 48), 74 k parameters,
    8.5 minutes of training, 0.8 ms for 26 patches, gave recall@P0.99 0.983, PCK@2px 0.932, AP@0.5
    0.9784; (8, 16, 24, 32), 45 k parameters, 2.8 minutes, 0.5 ms, gave 0.984, 0.929 and 0.9783. They
    rank alike; what differs is the operating point val placed for each (score bias +1.96 against
    +1.43). On a fresh `pipelines/smoke.yaml` build (tie wire, the servo camera: neither in training)
    the narrower one left 3 true crossings at scores 0.46-0.50, PCK@2px 0.972 against 0.982, so the
    wider one ships. A first trial of 3 epochs with the wider layers already gave 0.977.
    Those two read the patch at full resolution (``pool`` 1, the default). With each 2 x 2 block one
    cell (``pool`` 2, 4x fewer multiply-adds) and the float second stage the same layers gave
    recall@P0.99 0.985 and PCK@2px 0.936 on paper-tunnel's test split (the RGB stages alone 0.960 and
    0.929) in 2.1 minutes of training and 0.7 ms for 45 patches, but on planar-slab (never trained on)
    recall@P0.99 0.541 against 0.580 at full resolution behind the same second stage (0.500 without
    depth), so full resolution ships. ``power`` 0.5 (as the second stage's verification counts) gave
    test recall@P0.99 0.982 and PCK@2px 0.936, against 0.985 and 0.934 at 1 (each with its score bias
    placed on val; val recall@P0.99 0.987 against 0.988), so the check counts fully.

    ``quantize = "int8"`` ships the file quantized as the second stage's is (``calibration_patches``
    encoded patches around training crossings set the ranges). It scored as the float file did
    (recall@P0.99 0.983, PCK@2px 0.932) but ran slower: 3.2 ms against 2.4 for the 45 detections of a
    rendered frame (2 threads), so the float file ships.

    ``lower_mat_negatives``: up to this many of the crossings each training image's lower mat shows (its
    own, and where top bars pass in front of its bars; placed from the dataset's tables by
    :mod:`~rebar_data.perception.evaluation.lower_mat`) join the second stage's negatives it learns from, drawn
    anew for each image. Most confident false detections on the Cycles sets lie on them (see
    ``RefineConfig.lower_mat_negatives``), and depth tells them apart: the lower mat lies 80-250 mm
    deeper. 16 (6.3 minutes of training against 1.9: 51 s an epoch against 19, and placing them), the
    RGB stages as shipped before: with depth on the Cycles sets PCK@2px 0.940 and 0.915, recall@P0.99 0.975 and 0.956
    (without them 0.939 and 0.916, 0.975 and 0.930); paper-tunnel's test split AP@0.5 0.979, PCK@2px
    0.932, recall@P0.99 0.984 (the same); planar-slab, never trained on, PCK@2px 0.775 and recall@P0.99
    0.847 (0.776 and 0.819). From RGB alone nothing changes.
    """

    enabled: bool = True
    patch_px: Annotated[int, Field(ge=16, multiple_of=8)] = 32
    pool: Literal[1, 2, 4] = 1
    scale_m: Positive = 0.05
    clip: Positive = 4.0
    widths: tuple[PositiveInt, PositiveInt, PositiveInt, PositiveInt] = (16, 24, 32, 48)
    hidden: PositiveInt = 64
    epochs: PositiveInt = 6
    batch_size: PositiveInt = 512
    lr: Positive = 2e-3
    weight_decay: NonNegative = 1e-4
    jitter_px: NonNegative = 1.5
    gain: tuple[Positive, Positive] = (0.7, 1.4)
    threads: PositiveInt = 2
    power: Annotated[float, Field(gt=0.0, le=1.0)] = 1.0
    quantize: Literal["int8", "none"] = "none"
    calibration_patches: PositiveInt = 2048
    lower_mat_negatives: NonNegativeInt = 16


class CrossingPointConfig(Strict):
    """The crossing-point stage (``rebar_data.perception.inference.crossing_point``): a small network that reads the
    full-resolution patch around each detection and gives where the 3D crossing point (the midpoint of
    the two centerlines, inside the steel) projects, as an offset from the detection in pixels.

    Why: the detector finds the sight point, where the image shows the two bars cross (the labels' u, v).
    The 3D crossing point lies half the bars' combined diameter behind the top bar's centerline, so under
    an oblique view it projects a few pixels away (a mean 3.5 px on paper-tunnel's test frames, up to 11),
    in the direction the mat leans. A test set labelled from the 3D point alone, and a robot that ties
    at the 3D point from an image without depth, need that point: ``Detector.detect(..., point=
    "crossing")`` and ``rebar detect --point crossing`` add this stage's offset to each detection. The
    patch shows what the offset depends on: the bars' width in pixels (their diameter over their
    distance), which bar lies on top and which of its sides the camera sees.

    Each training patch is the ``context_px`` square around a visible crossing, centred with a Gaussian
    error of ``jitter_px`` (the second stage's error is about 0.5 px), cut at a random scale in ``scale``
    (other bar sizes and distances; the offset scales with it) to ``patch_px``, turned by quarter turns
    and flipped with its offset and its viewing ray alike (a mirrored or rolled camera sees a mirrored or
    rolled scene), with the first stage's colour, blur and noise changes. The network sees the patch's
    viewing ray ((u - cx) / fx, (v - cy) / fy) beside it. It trains on the labels alone (independent of
    the other stages' weights), with an L1 loss on the offset.

    ``epochs`` = 6 since the wide-randomization supplements joined `make train`'s data (2,400 images, 3.7
    minutes); the figures below are for the earlier stage. Measured (that stage: 8 epochs over 33,469 patches of paper-tunnel's train split
    and its lower-mat supplement, 20 a training image, 4.5 minutes on one thread): each visible crossing's
    patch centred on its label, the stage's 3D point lies a mean 2.14 px (median 1.83) from the truth on
    paper-tunnel's test split, where the sight point lies 3.50 px from it; on the Cycles sets 2.86 px
    (planar, from 3.91) and 3.21 px (tunnel, from 4.58). Behind the shipped detector, RGB only, against the
    3D points: PCK@2px 0.509 against the sight points' 0.198 on paper-tunnel's test split, 0.360 against
    0.193 on crossval-planar and 0.303 against 0.147 on crossval-tunnel. Tried and not adopted: a 96 px
    patch shrunk 2x (``pool`` 2, twice the view at half the resolution) scored worse (last epoch's L1 1.73
    px an axis against 1.62 in image pixels; held-out 2.35 px, 3.03 and 3.40); 4 epochs at full
    resolution on paper-tunnel alone gave 2.71 px. The offset follows the mat's tilt against the viewing ray, which a patch shows only
    partly (a whole frame's perspective shows it better): most of what is left.
    """

    enabled: bool = True
    patch_px: Annotated[int, Field(ge=16, multiple_of=8)] = 48
    context_px: Annotated[int, Field(ge=16, multiple_of=2)] = 72
    pool: Literal[1, 2, 3, 4] = 1
    scale: tuple[Positive, Positive] = (0.75, 1.35)
    widths: tuple[PositiveInt, PositiveInt, PositiveInt, PositiveInt] = (16, 32, 48, 64)
    hidden: PositiveInt = 128
    epochs: PositiveInt = 6
    batch_size: PositiveInt = 256
    lr: Positive = 2e-3
    weight_decay: NonNegative = 1e-4
    jitter_px: NonNegative = 1.0
    max_per_image: PositiveInt = 20
    threads: PositiveInt = 2


class LineCheckConfig(Strict):
    """The line check (:mod:`rebar_data.perception.inference.line_check`): each detection's score read again, without
    depth, beside the scores of the detections along its two bars, by a logistic regression fitted
    (:mod:`~rebar_data.perception.training.line_check`) on the trained detector's candidates in the
    validation split and the line supplements (``rebar train --line-supplement``; `make train`'s
    ``LINE_SUPPLEMENTS``, the two Cycles sets with a lower mat in every scene), with L2 penalty
    ``1 / regularization`` (scikit-learn's ``C``).

    Why: the confident false detections that hold the RGB stages' recall at precision 0.99 on the Cycles
    sets are nearly all places where a top bar passes in front of a lower mat's bar; a patch of any size
    the second stage was tried with shows them as crossings, and more Cycles frames with a lower mat did
    not teach the first stage the difference (the README's cross-renderer section). Along the lower bar
    the detector finds only more such places, scored lower on the whole; along a top bar, crossings.

    ``floor``: candidates the first stage scores this or more are evidence (the others are not followed);
    ``checked_from``: those it scores this or more are verified by the second stage (their evidence is then
    the RGB stages' score) and checked; below it a candidate is evidence at its first-stage score and never
    returned, as without the check it would score under the operating point anyway.

    Measured (RGB only, `rebar detect DATASET --split test --no-depth`, the `-e` sets all 48 frames; none of
    these sets fitted it; recall at precision 0.99 on crossval-planar / crossval-tunnel / cycles-train-
    planar-e / cycles-train-tunnel-e / paper-tunnel test): the shipped RGB stages alone 0.863 / 0.869 /
    0.844 / 0.830 / 0.953; with this check 0.920 / 0.872 / 0.858 / 0.849 / 0.960 (AP@0.5 0.974 / 0.963 /
    0.951 / 0.936 / 0.978, PCK@2px 0.958 / 0.939 / 0.925 / 0.899 / 0.947, each within 0.005 of before).
    Tried, on the same sets: ``checked_from`` 0.05 (every candidate verified) 0.926 / 0.872 / 0.883 / 0.855
    / 0.960 and 0.2 0.916 / 0.867 / 0.881 / 0.855 / 0.960 (both with 10 steps and an earlier reading of the
    bar directions); with 6 steps, 0.2 cost the RGB path 1.28 times its time, 0.3 1.17 times. Offline on the
    same candidates: bars followed 3, 6 (shipped) or 10 steps each way, the features with their products
    with the own score, or with the own score relative to the image's median: each within 0.03 of the
    others on every set, none better on all; fitted also on the two `-e` sets (then not held out) 0.911 /
    0.894 on the crossval sets; a 16-unit MLP 0.935-0.937 / 0.849-0.879 / 0.874-0.877 / 0.895 / 0.958-0.960
    (two seeds); scikit-learn's gradient-boosted trees (100 of 8 leaves, lr 0.1, no early stopping, so
    no seed matters) 0.924 / 0.887 / 0.872 / 0.851 / 0.958: 0.002-0.015 higher on each set, a few
    detections, for a model file that would carry 100 trees and their evaluator; not taken. A prototype that took every candidate within a 10-degree wedge along each bar direction (no
    step-by-step following) took the top bar a lower bar converges to in perspective for the lower bar, and
    the curved set lost recall (0.869 to 0.840-0.851); two rounds there (the first round's scores as the
    second's evidence) changed each figure by under 0.02. Two cues of which mat a detection's bars lie
    in, read from the image at each detection (offline, on candidates the first stage scores 0.2 or more,
    where these features alone gave 0.909 / 0.860 / 0.867 / 0.857 / 0.958): each bar's brightness along
    its centreline 6-22 px from the crossing (the brighter bar against the darker, each against the
    image's confident detections) and the two bars' difference in colour: 0.922 / 0.852 / 0.865 / 0.857 /
    0.959 (the confident false detections' bars were no darker than a crossing's: the median log ratio
    0.140 against 0.136); which bar is on top at each detection (the edges across each bar at the
    crossing against 12-28 px from it), to count along each bar where it passes on top: on the slab it
    named the top bar at a few of a frame's crossings only, the ribs of the bar on top giving edges
    across the one beneath, so it was not fitted. A ghost where a top bar passes a lower one lies a few
    pixels from a crossing scored higher (the lower mat sits just behind the top one): the best score
    within 12, 20 or 32 px against the detection's own, and how near the nearest better-scored candidate
    is, as more features: 0.908-0.916 / 0.860 / 0.867-0.874 / 0.856-0.858 / 0.958, within 0.007 of
    the same fit without them. The following cone and its lateral slack (``CONE_DEG`` 2, 3, 4, 6
    degrees by ``LATERAL_PX`` 1, 2, 3; the same candidates, the check fitted for each): 0.903-0.930 /
    0.860-0.897 / 0.845-0.875 / 0.823-0.860 / 0.955-0.961, none above 4 degrees and 2 px on every
    set (the narrowest, 2 and 1, 0.921 / 0.897 / 0.845 / 0.844 / 0.956); the twelve checks' logits
    averaged 0.916 / 0.880 / 0.875 / 0.842 / 0.960. A few detections move these figures either way.
    """

    enabled: bool = True
    regularization: Positive = 1.0
    floor: Fraction = 0.05
    checked_from: Fraction = 0.3

    @model_validator(mode="after")
    def _checked_above_floor(self) -> LineCheckConfig:
        if not 0.0 < self.floor <= self.checked_from < 1.0:
            raise ValueError(
                f"floor = {self.floor} and checked_from = {self.checked_from} are not accepted; accepted: "
                "0 < floor <= checked_from < 1 (the checked candidates are among the evidence)"
            )
        return self


class AdaptConfig(Strict):
    """The first stage's adapt epochs (:mod:`~rebar_data.perception.training.adapt`): after its best epoch,
    ``epochs`` more on its training images and the run's second-stage supplements (``rebar train
    --refine-supplement``; `make train`'s Cycles-rendered ``pipelines/cycles-train-*.yaml``), each of their
    images listed ``supplement_repeats`` times, from ``lr`` (after ``warmup_epochs``) down a cosine, the
    batch norms frozen (their statistics stay the first epochs'), no mosaic. The first stage the run ships
    and the later stages train beside is the adapted one. 0 epochs, or no supplements, ship the best epoch
    as it is.

    Why: the first stage had seen only Open3D's images, and on the Cycles sets it scored the lower mat's
    crossings seen through the top mat as surely as the top mat's (recall at precision 0.99 from RGB alone
    0.160 on crossval-planar and 0.453 on crossval-tunnel, the first stage alone). The second stage's 32 px
    patch cannot tell the mats apart; the first stage sees them whole. Frozen batch norms let the epochs go
    on from any first stage (also one whose norms were folded into its convolutions) and keep its
    statistics those of the data it learnt on.

    Measured on the 16-epoch first stage before (RGB only on the Cycles sets, AP@0.5, PCK@2px,
    recall@P0.99; paper-tunnel's test split with depth), scored with that model's later stages as they
    were (not trained again), three epochs each:

    - none: crossval-planar 0.937, 0.925, 0.840; crossval-tunnel 0.926, 0.876, 0.663; paper-tunnel 0.978,
      0.927, 0.984; the first stage alone recall@P0.99 0.160 and 0.453;
    - 120 Cycles frames (cycles-train-tunnel, -planar, -tunnel-b) 5 times, 20% of the images, lr 6e-4:
      0.947, 0.925, 0.828; 0.933, 0.877, 0.734; 0.978, 0.928, 0.984; alone 0.223 and 0.532 (2.5 minutes
      an epoch);
    - the same 20 times, half the images, lr 1e-3: 0.949, 0.922, 0.826; 0.944, 0.887, 0.795; 0.979,
      0.929, 0.983; alone 0.438 and 0.565 (4.5 minutes an epoch).

    With the fourth set (cycles-train-planar-b) beside, 168 frames 15 times, again about half the images,
    and the later stages trained again beside it (the model before): 0.949, 0.933, 0.815; 0.946, 0.918,
    0.705; 0.979, 0.935, 0.983; alone 0.930 on paper-tunnel (recall@P0.99). The defaults: 264 frames (the
    two ``cycles-train-*-c`` sets beside), 10 times, again about half the images (11.7 minutes for the
    three epochs); with the second stage trained again (``RefineConfig.supplement_repeats``, where the
    figures are) 0.949, 0.937, 0.823; 0.937, 0.912, 0.729; 0.979, 0.932, 0.984; the first stage alone
    recall@P0.99 0.937 and PCK@2px 0.805 on paper-tunnel (0.930 and 0.815 with 168 frames).

    ``lower_mat_weight``: the heatmap loss's weight of the 3x3 cells at the crossings each training image's
    lower mat shows (its own, and where top bars pass in front of its bars; placed from the dataset's
    tables by :mod:`~rebar_data.perception.evaluation.lower_mat`, none within three cells of a labelled crossing).
    They are where the confident false detections on the Cycles sets lie: at the score where recall
    reaches 0.97, 42 of the slab's 48 and 92 of the curved set's 108 lie within 6 px of one. At 3, with
    the second stage and depth check trained again beside it (``RefineConfig.lower_mat_negatives`` 16;
    figures as above): 0.946, 0.927, 0.805; 0.939, 0.908, 0.708; 0.979, 0.929, 0.984 (at 1, the same
    second stage: 0.947, 0.928, 0.799; 0.944, 0.904, 0.727; 0.979, 0.931, 0.984); the first stage alone
    recall@P0.99 0.548 and 0.646 on the Cycles sets (at 1: 0.501 and 0.616) and 0.931 on paper-tunnel
    (0.937). At 10, the second stage (without lower-mat negatives) and depth check trained again beside
    it: 0.947, 0.938, 0.787; 0.936, 0.910, 0.751; 0.979, 0.928, 0.982; with depth on the Cycles sets
    recall@P0.99 0.960 and 0.880 (at 1: 0.975 and 0.956); the first stage alone 0.605 and 0.635, and
    0.926 on paper-tunnel, whose crossings it placed less well (PCK@2px 0.790 against 0.804). It taught
    the first stage a little of the difference, and the whole detector nothing beyond one training's
    spread, so the default stays 1 (no extra weight; the adapt epochs then train as
    before it existed, and their checkpoints from then still count).

    More frames with a lower mat: three more adapt epochs from the shipped first stage (from its ONNX
    file, :func:`~rebar_data.perception.networks.files.network_from_onnx`) on paper-tunnel's 960 training images
    and Cycles frames listed 10 times, the shipped later stages kept, RGB only, recall@P0.99 slab /
    curved set / paper-tunnel test: shipped 0.863 / 0.869 / 0.953; the 96 ``-d`` frames it had seen
    0.849 / 0.855 / 0.954; 48 new ones (``cycles-train-tunnel-e``) beside them 0.807 / 0.876 / 0.950;
    96 new ones (both ``-e`` sets; 11.9 minutes for the three epochs) 0.843 / 0.884 / 0.950, the false
    detections where a top bar passes in front of a lower bar 26 / 56 (shipped 26 / 55): within one
    training's spread, so the ``-e`` sets stay out of `make train`.
    """

    epochs: NonNegativeInt = 3
    lr: Positive = 1e-3
    warmup_epochs: NonNegative = 0.05
    supplement_repeats: PositiveInt = 10
    lower_mat_weight: Positive = 1.0


class TrainConfig(Strict):
    """One training run.

    The network trains on square crops (``crop_px``) of augmented images; it is fully convolutional,
    so it then runs on whole frames. Early stopping watches the validation OKS AP@0.5:0.95 and stops
    after ``patience`` epochs without improvement. ``loader_workers = 1`` makes the augmented batches in a
    second process while the network trains; the batches are the same either way (each epoch's come
    from a generator seeded by the seed and the epoch).

    ``threads`` is the network's CPU threads; the loader process takes another core. On two cores shared
    with other work, a second OpenMP thread mostly waits for its partner: a training step took 0.44 s
    with two threads and 0.27 s with one, while the machine was busy with other jobs.

    ``epochs`` = 16 with `make train`'s data: paper-tunnel's 960 training images, the 720 of its lower-mat
    supplement and the 720 of the four wide-randomization supplements (``pipelines/wide-*.yaml``: 10-20 mm
    bars at 100-200 mm, curved and planar mats, the Kinect camera, views tilted up to 40 degrees, the lower
    mat in 60% of scenes, wider steel looks, light and exposure): 9,600 steps, 55 minutes for this stage and
    76 in all with the later stages (second stage 11 epochs, depth check 6, crossing-point stage 6; their
    docstrings give the earlier epoch counts). The first stage was still improving at its last epoch.

    The model before the wide supplements (22 epochs over the first 1,680 images, 9,240 steps; second stage
    16 epochs, depth check 8; 82 minutes) against this one, both scored in one session on the same builds
    (`rebar detect DATASET --split test [--no-depth]`; first: before, second: now). Paper-tunnel's test
    split with depth: OKS AP@0.5 0.979 / 0.978, PCK@2px 0.936 / 0.926, recall@P0.99 0.984 / 0.980; RGB only
    0.978 / 0.976, 0.934 / 0.923, 0.960 / 0.945. The Cycles sets, RGB only: crossval-planar PCK@2px 0.908 /
    0.917, recall@P0.99 0.537 / 0.346; crossval-tunnel 0.793 / 0.837 and 0.331 / 0.455. With depth:
    planar 0.904 / 0.919 and 0.913 / 0.903; tunnel 0.788 / 0.850 and 0.482 / 0.788. Planar-slab (never
    trained on, Open3D, all splits) AP@0.5 0.951 / 0.953, PCK@2px 0.724 / 0.739, recall@P0.99 0.726 / 0.769. So the
    wider data placed crossings better on every set from another config or renderer and raised recall at
    precision 0.99 on the curved Cycles set (with depth, 0.48 to 0.79), at a point of PCK@2px on
    paper-tunnel's own test split; on the Cycles slab without depth a few more confident false detections
    cost recall at precision 0.99 (0.54 to 0.35: a dozen detections among 927 crossings decide it).

    The same recipe on the corrected labels of dataset versions 2.1.0 / 1.1.0 (the shipped model; before,
    a sight point more than three bar diameters from its crossing fell back to the crossing's point and
    stayed visible: 1-5% of the wide supplements' visible labels, half of them on the ground seen between
    two bars, and 0.3-0.5% of paper-tunnel's; `rebar_data.labels.keypoints`), against the model above,
    both scored in one session on the corrected builds (first: earlier labels, second: corrected; 75
    minutes of training). Paper-tunnel's test split with depth: OKS AP@0.5 0.978 / 0.978, PCK@2px 0.925 /
    0.927, recall@P0.99 0.979 / 0.984; RGB only 0.976 / 0.976, 0.921 / 0.924, 0.945 / 0.957. The Cycles
    sets, RGB only: crossval-planar AP@0.5 0.917 / 0.936, PCK@2px 0.921 / 0.911, recall@P0.99 0.349 / 0.614;
    crossval-tunnel 0.887 / 0.917, 0.841 / 0.863, 0.455 / 0.545. With depth, recall@P0.99: planar 0.914 /
    0.933, tunnel 0.854 / 0.880. Planar-slab (all splits, with depth) AP@0.5 0.953 / 0.966, PCK@2px 0.739 /
    0.738, recall@P0.99 0.769 / 0.839. A training crop with a positive in the gap between two bars and the
    crossing the image shows unlabelled taught the network to doubt steep views' crossings.

    The shipped first stage is that run's. Its verification weights changed next (``RefineConfig.verify_power``
    1 from RGB alone, ``verify_power_with_depth`` 0.5; RGB only, the Cycles sets' recall@P0.99 0.612 / 0.550
    to 0.775 / 0.579). Then its later stages trained again beside it, the second one also on the
    Cycles-rendered second-stage supplements (``RefineConfig.supplement_repeats``, where the figures are)
    and reading two views (``RefineConfig.views``): `make train` resumed a run folder holding that first
    stage (turned back from its ONNX file into a checkpoint, BN folded into the convolutions, its outputs
    equal within 4e-6), trained the second, depth and crossing-point stages, placed both score biases on
    val and shipped them. The card's training time counts the first stage's 16 epochs as that run measured
    them (about 49 minutes: its card's 70.0 minutes less the later stages' times then) beside the later
    stages' times now. Then the first stage's adapt epochs (``AdaptConfig``) trained on the six Cycles
    supplements from that best epoch, and the second stage and the depth check again beside the adapted
    first stage (`make train` resuming the same run folder). That was the model before
    ``AugmentConfig.distractor_gain``; the one after it is a whole `make train` run from scratch with
    those settings (70.9 minutes on this 2-core machine, the first stage's 16 epochs 32 of them, 116 s an
    epoch, where the run above measured 55 minutes for them on a busier machine).

    ``other_renderer_repeats``: the second-stage supplements' images (another renderer's frames: the 264
    Cycles frames of ``pipelines/cycles-train-*.yaml``) also join the first epochs' training images, each
    listed this many times (0: they wait for the adapt epochs, as before the setting existed). At 2 they
    are 18% of the images (528 of 2,928; 732 steps an epoch against 600), and the adapt epochs and later
    stages mix them as before. The shipped model is that whole `make train` run from scratch (76.8 minutes,
    the first stage's 16 epochs 38 of them, 137-146 s an epoch), against the one before (the same settings
    at 0), both scored in one session on the same builds (`rebar detect DATASET --split all|test
    [--no-depth]`; before / now). The Cycles sets, RGB only: crossval-planar AP@0.5 0.959 / 0.973, PCK@2px
    0.961 / 0.960, recall@P0.99 0.793 / 0.876; crossval-tunnel 0.947 / 0.956, 0.931 / 0.937, 0.755 /
    0.765; their images with a lower mat AP@0.5 0.829 / 0.878 and 0.892 / 0.911, recall@P0.99 0.137 /
    0.188 and 0.222 / 0.456. With depth, recall@P0.99 0.980 / 0.991 and 0.966 / 0.958. Paper-tunnel's
    test split with depth: AP@0.5 0.979 / 0.979, PCK@2px 0.954 / 0.954, recall@P0.99 0.990 / 0.990; RGB
    only recall@P0.99 0.957 / 0.964; the first stage alone 0.917 / 0.935. Planar-slab (all splits, with
    depth) AP@0.5 0.975 / 0.966, PCK@2px 0.857 / 0.858, recall@P0.99 0.842 / 0.871. The first stage alone
    after its best epoch, before the adapt epochs (RGB only on the Cycles sets): AP@0.5 0.880 / 0.913 and
    0.876 / 0.901, PCK@2px 0.847 / 0.843 and 0.733 / 0.797; on the images with a lower mat AP@0.5 0.547 /
    0.652 and 0.765 / 0.820. On paper-tunnel's val split the first epochs scored as before (OKS AP@0.5:0.95
    0.822 / 0.819 at epoch 16).

    Then 96 more Cycles frames, every scene with a lower mat (``cycles-train-tunnel-d`` and ``-planar-d``),
    joined the Makefile's second-stage supplements: 360 frames, 23% of the first epochs' images (720 of
    3,120; 780 steps an epoch). The shipped model is that whole `make train` run from scratch (85.0
    minutes: the first stage's 16 epochs 42 of them, 150-160 s an epoch, the adapt epochs 14.2, the second
    stage 23.5), against the one above (before / now, scored in one session on the same builds). The
    Cycles sets, RGB only: crossval-planar AP@0.5 0.973 / 0.971, PCK@2px 0.960 / 0.960, recall@P0.99
    0.876 / 0.863; crossval-tunnel 0.956 / 0.961, 0.937 / 0.940, 0.765 / 0.868; with depth, recall@P0.99
    0.991 / 0.989 and 0.958 / 0.969. Paper-tunnel's test split with depth: AP@0.5 0.979 / 0.979, PCK@2px
    0.954 / 0.953, recall@P0.99 0.990 / 0.990; RGB only recall@P0.99 0.964 / 0.953. Planar-slab (with
    depth): AP@0.5 0.966 / 0.967, PCK@2px 0.858 / 0.852, recall@P0.99 0.871 / 0.879. The adapted first
    stage alone on the Cycles sets, RGB only: recall@P0.99 0.435 / 0.634 and 0.643 / 0.752, AP@0.5 0.927 /
    0.929 and 0.907 / 0.931; before its adapt epochs AP@0.5 0.913 / 0.892 and 0.901 / 0.905. Confident
    false detections (above the score where recall reaches 0.97): 45 / 33 on the slab, 67 / 64 on the
    curved set, 42 / 27 and 62 / 59 of them at the lower mat's crossings.

    Earlier, with the first 1,680 images alone and the second stage's verification at full weight
    (``RefineConfig.verify_power`` 1): 22 epochs (best on val at 18) gave OKS AP@0.5 0.977, AP@0.5:0.95
    0.906, PCK@2px 0.927, recall@P0.99 0.958 (first stage alone 0.937); 11 epochs 0.965, 0.895, 0.913 and
    0.933 (first stage alone 0.859); 8 epochs left the first stage alone at 0.70.
    """

    epochs: PositiveInt = 16
    batch_size: PositiveInt = 8
    crop_px: Annotated[int, Field(ge=32, multiple_of=16)] = 384
    crops_per_image: PositiveInt = 2
    lr: Positive = 3e-3
    weight_decay: NonNegative = 1e-4
    warmup_epochs: NonNegative = 1.0
    patience: PositiveInt = 12
    heatmap_sigma_cells: Positive = 1.0
    offset_weight: Positive = 1.0
    occluded: Literal["ignore", "negative"] = "ignore"
    val_every: PositiveInt = 2
    val_max_images: PositiveInt = 60
    threads: PositiveInt = 1
    seed: NonNegativeInt = 0
    cache_images: bool = True
    loader_workers: Literal[0, 1] = 1
    model: ModelConfig = ModelConfig()
    augment: AugmentConfig = AugmentConfig()
    other_renderer_repeats: NonNegativeInt = 2
    adapt: AdaptConfig = AdaptConfig()
    refine: RefineConfig = RefineConfig()
    depth_check: DepthCheckConfig = DepthCheckConfig()
    crossing_point: CrossingPointConfig = CrossingPointConfig()
    line_check: LineCheckConfig = LineCheckConfig()


def resolve_config(
    config: TrainConfig | dict | None, overrides: dict[str, Any], *, source: str = "train settings"
) -> TrainConfig:
    """Settings from a TrainConfig or dict with keyword overrides applied (None values are left out);
    ``source`` names where they came from in an error (the settings file, for ``rebar train --config``)."""
    base = config.model_dump() if isinstance(config, TrainConfig) else dict(config or {})
    base.update({k: v for k, v in overrides.items() if v is not None})
    try:
        return TrainConfig.model_validate(base)
    except Exception as e:
        from pydantic import ValidationError

        if isinstance(e, ValidationError):
            raise ConfigError(format_validation_error(e, source, base)) from None
        raise
