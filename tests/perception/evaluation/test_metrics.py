from __future__ import annotations

import contextlib
import io

import numpy as np
import pytest

from rebar_data.perception.evaluation.metrics import (
    DEFAULT_OKS_SIGMA,
    Truth,
    ap_ceiling,
    format_summary,
    keypoint_ap,
    oks_matrix,
    oks_radius_px,
    pixel_metrics,
    summary,
)


def _scene(rng: np.random.Generator, n_images: int = 12):
    """Random truths, and predictions that are the truths moved by up to a few px, with misses and extras."""
    truths, preds = [], []
    for _ in range(n_images):
        n = int(rng.integers(0, 25))
        uv = rng.uniform(0, 640, (n, 2))
        box = rng.uniform(15, 45, n)
        n_ign = int(rng.integers(0, 4))
        truths.append(Truth(uv, box, rng.uniform(0, 640, (n_ign, 2)), rng.uniform(15, 45, n_ign)))
        keep = rng.uniform(size=n) > 0.1
        p = uv[keep] + rng.normal(0, rng.uniform(0.2, 3.0), (keep.sum(), 2))
        extra = rng.uniform(0, 640, (int(rng.integers(0, 4)), 2))
        near_ignored = truths[-1].ignore_uv + rng.normal(0, 0.5, truths[-1].ignore_uv.shape)
        p = np.r_[p, extra, near_ignored]
        preds.append(np.c_[p, rng.uniform(0.05, 1.0, len(p))])
    return truths, preds


def _cocoeval(truths, preds, sigma):
    from pycocotools.coco import COCO
    from pycocotools.cocoeval import COCOeval

    images, anns, dets = [], [], []
    for i, (t, p) in enumerate(zip(truths, preds, strict=True)):
        images.append({"id": i + 1, "width": 640, "height": 640})
        for (u, v), b, crowd in [
            *zip(t.uv, t.box_size_px, [0] * len(t.uv), strict=True),
            *zip(t.ignore_uv, t.ignore_box_size_px, [1] * len(t.ignore_uv), strict=True),
        ]:
            anns.append(
                {
                    "id": len(anns) + 1,
                    "image_id": i + 1,
                    "category_id": 1,
                    "keypoints": [float(u), float(v), 2],
                    "num_keypoints": 1,
                    "area": float(b * b),
                    "bbox": [float(u - b / 2), float(v - b / 2), float(b), float(b)],
                    "iscrowd": crowd,
                }
            )
        for u, v, s in p:
            dets.append(
                {"image_id": i + 1, "category_id": 1, "keypoints": [float(u), float(v), 1], "score": float(s)}
            )
    with contextlib.redirect_stdout(io.StringIO()):
        gt = COCO()
        gt.dataset = {
            "images": images,
            "annotations": anns,
            "categories": [{"id": 1, "name": "intersection", "keypoints": ["intersection"]}],
        }
        gt.createIndex()
        dt = gt.loadRes(dets)
        ev = COCOeval(gt, dt, "keypoints")
        ev.params.kpt_oks_sigmas = np.array([sigma])
        ev.params.maxDets = [1000]
        ev.params.areaRng = [[0, 1e10]]
        ev.params.areaRngLbl = ["all"]
        ev.evaluate()
        ev.accumulate()
    prec = ev.eval["precision"][:, :, 0, 0, 0]
    return float(prec[prec > -1].mean()), float(prec[0].mean()), prec


@pytest.mark.parametrize("sigma", [DEFAULT_OKS_SIGMA, 0.1])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ap_equals_pycocotools_cocoeval(seed, sigma):
    truths, preds = _scene(np.random.default_rng(seed))
    ours = keypoint_ap(truths, preds, sigma=sigma)
    ap, ap50, prec = _cocoeval(truths, preds, sigma)
    assert ours.ap == pytest.approx(ap, abs=1e-12)
    assert ours.ap50 == pytest.approx(ap50, abs=1e-12)
    np.testing.assert_allclose(ours.precision, prec, atol=1e-12)
    assert 0.2 < ours.ap < ours.ap50 < 1.0  # the scene is neither trivial nor hopeless


def test_perfect_predictions_give_ap_one_and_pck_one():
    rng = np.random.default_rng(3)
    truths = [Truth(rng.uniform(0, 640, (20, 2)), np.full(20, 30.0)) for _ in range(4)]
    preds = [np.c_[t.uv, np.full(len(t.uv), 0.9)] for t in truths]
    m = summary(truths, preds)
    assert m["oks_ap"] == pytest.approx(1.0)
    assert m["oks_ap50"] == pytest.approx(1.0)
    assert m["pck1"] == m["recall"] == m["precision"] == m["recall_at_p99"] == 1.0
    assert m["mean_px"] == 0.0


def test_shift_drops_ap_where_the_sigma_says():
    """A shift just inside the OKS-0.5 radius passes at 0.5 and fails at 0.55; just outside fails at 0.5."""
    box = 30.0
    r50 = oks_radius_px(DEFAULT_OKS_SIGMA, box)
    assert 2.0 < r50 < 5.0  # "a few pixels" for a typical box
    uv = np.array([[100.0, 100.0], [300.0, 200.0], [500.0, 400.0]])
    truths = [Truth(uv, np.full(3, box))]
    inside = keypoint_ap(truths, [np.c_[uv + [r50 * 0.99, 0], np.ones(3)]])
    outside = keypoint_ap(truths, [np.c_[uv + [0, r50 * 1.01], np.ones(3)]])
    assert inside.ap50 == pytest.approx(1.0)
    assert inside.precision[1].mean() == 0.0  # OKS 0.55
    assert inside.ap == pytest.approx(0.1)
    assert outside.ap50 == 0.0 and outside.ap == 0.0
    np.testing.assert_allclose(oks_matrix(uv[:1] + [r50, 0], uv[:1], [box], DEFAULT_OKS_SIGMA), [[0.5]])


def test_ap_falls_monotonically_with_shift():
    uv = np.random.default_rng(4).uniform(50, 590, (30, 2))
    truths = [Truth(uv, np.full(30, 25.0))]
    aps = [keypoint_ap(truths, [np.c_[uv + [s, 0], np.ones(30)]]).ap for s in (0.0, 0.5, 1.0, 2.0, 3.0, 5.0)]
    assert aps == sorted(aps, reverse=True)
    assert aps[0] == pytest.approx(1.0) and aps[-1] == 0.0


def test_pixel_metrics_count_only_confident_matches_for_pck():
    uv = np.array([[10.0, 10.0], [100.0, 100.0], [200.0, 200.0], [300.0, 300.0]])
    truths = [Truth(uv, np.full(4, 30.0))]
    pred = np.array(
        [
            [10.5, 10.0, 0.9],  # 0.5 px
            [101.5, 100.0, 0.9],  # 1.5 px
            [203.0, 200.0, 0.9],  # 3 px
            [300.0, 300.0, 0.3],  # exact but below the operating threshold
            [400.0, 400.0, 0.8],  # false positive
        ]
    )
    px = pixel_metrics(truths, [pred])
    assert px.pck == {1.0: 0.25, 2.0: 0.5, 5.0: 0.75}
    assert px.precision == pytest.approx(3 / 4)
    assert px.recall == pytest.approx(3 / 4)
    assert px.median_px == pytest.approx(1.5)
    # precision stays >= 0.99 only until the false positive (score 0.8) comes in: 3 of 4 found
    assert px.recall_at_p99 == pytest.approx(0.75)


def test_ignored_crossings_neither_count_nor_penalise():
    uv = np.array([[50.0, 50.0], [150.0, 50.0]])
    ign = np.array([[250.0, 50.0]])
    pred = np.array([[50.0, 50.0, 0.9], [150.0, 50.0, 0.8], [250.0, 50.0, 0.95]])
    strict = summary([Truth(uv, np.full(2, 30.0))], [pred])
    lenient = summary([Truth(uv, np.full(2, 30.0), ign, np.full(1, 30.0))], [pred])
    assert strict["precision"] == pytest.approx(2 / 3) and strict["oks_ap"] < 1.0
    assert lenient["precision"] == 1.0 and lenient["oks_ap"] == pytest.approx(1.0)


def test_pixel_metrics_agree_with_a_plain_reimplementation_of_the_scorer():
    from scipy.optimize import linear_sum_assignment

    truths, preds = _scene(np.random.default_rng(5), n_images=8)
    truths = [Truth(t.uv, t.box_size_px) for t in truths]
    errs, scored, n_gt = [], [], 0
    for t, p in zip(truths, preds, strict=True):
        n_gt += len(t.uv)
        tp = np.zeros(len(p), bool)
        if len(t.uv) and len(p):
            d = np.hypot(t.uv[:, None, 0] - p[None, :, 0], t.uv[:, None, 1] - p[None, :, 1])
            r, c = linear_sum_assignment(np.where(d < 5, d, 1e6))
            ok = d[r, c] < 5
            tp[c[ok]] = True
            errs += list(d[r, c][ok][p[c[ok], 2] >= 0.5])
        scored += list(zip(p[:, 2], tp, strict=True))
    scored.sort(key=lambda x: -x[0])
    tps = np.cumsum([t for _, t in scored])
    prec, rec = tps / np.arange(1, len(scored) + 1), tps / n_gt
    px = pixel_metrics(truths, preds)
    e = np.array(errs)
    assert px.pck[2.0] == pytest.approx((e <= 2).sum() / n_gt)
    assert px.median_px == pytest.approx(np.median(e))
    assert px.recall_at_p99 == pytest.approx(rec[prec >= 0.99].max() if (prec >= 0.99).any() else 0.0)


def test_score_bias_puts_score_one_half_at_the_best_f1():
    from rebar_data.perception.evaluation.data import Sample
    from rebar_data.perception.evaluation.evaluate import calibrate_score_bias

    gt = np.array([[10.0, 10.0], [50.0, 10.0], [90.0, 10.0], [130.0, 10.0]])
    sample = Sample("a", None, 200, 40, gt, np.full(4, 30.0))
    # four hits scored 0.3-0.2, then two misses lower: the best F1 keeps the four hits, cut below 0.2
    pred = np.array(
        [[10.5, 10, 0.3], [50, 10.5, 0.28], [90, 10, 0.25], [130, 10, 0.2], [170, 30, 0.1], [5, 35, 0.05]]
    )
    b = calibrate_score_bias([sample], [pred])
    scores = 1 / (1 + np.exp(-(np.log(pred[:, 2] / (1 - pred[:, 2])) + b)))
    assert (scores[:4] >= 0.5).all() and (scores[4:] < 0.5).all()


def _two_scenes(tmp_path, *, lower_mat: bool = True):
    """A 100 x 80 image with a crossing inside the frame and one 3 px from its left border, detected with
    a false detection inside and one at the right border; and a second image without crossings."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from rebar_data.perception.evaluation.data import Sample

    uv = np.array([[50.0, 40.0], [3.0, 40.0]])
    samples = [
        Sample("a", None, 100, 80, uv, np.full(2, 30.0)),
        Sample("b", None, 100, 80, np.zeros((0, 2)), np.zeros(0)),
    ]
    preds = [
        np.array([[50.2, 40.0, 0.9], [3.5, 40.0, 0.8], [98.0, 10.0, 0.95], [70.0, 60.0, 0.7]]),
        np.array([[30.0, 30.0, 0.6]]),
    ]
    columns = {"image_id": ["a", "b"]}
    if lower_mat:
        columns["surr_lower_layer"] = [True, False]
    (tmp_path / "tables").mkdir()
    pq.write_table(pa.table(columns), tmp_path / "tables/samples.parquet")
    return samples, preds


def test_setting_the_border_aside_ignores_the_crossings_and_drops_the_detections_there(tmp_path):
    from rebar_data.perception.evaluation.evaluate import score, set_border_aside

    samples, preds = _two_scenes(tmp_path)
    every = score(samples, preds, sigma=DEFAULT_OKS_SIGMA)
    assert every["n_gt"] == 2 and every["precision"] == pytest.approx(2 / 5) and every["recall"] == 1.0
    truths, kept = set_border_aside(samples, preds, 8.0)
    np.testing.assert_array_equal(truths[0].uv, [[50.0, 40.0]])
    np.testing.assert_array_equal(truths[0].ignore_uv, [[3.0, 40.0]])
    np.testing.assert_array_equal(kept[0][:, 2], [0.9, 0.7])  # the two within 8 px of the border dropped
    inside = summary(truths, kept)
    assert inside["n_gt"] == 1 and inside["precision"] == pytest.approx(1 / 3) and inside["recall"] == 1.0


def test_the_breakdown_scores_the_frames_inside_and_the_scenes_with_and_without_a_lower_mat(tmp_path):
    from rebar_data.perception.evaluation.evaluate import breakdown

    samples, preds = _two_scenes(tmp_path)
    rows = breakdown(tmp_path, samples, preds, sigma=DEFAULT_OKS_SIGMA)
    assert list(rows) == [
        "crossings >= 8 px inside the frame",
        "scenes with a lower mat",
        "scenes without a lower mat",
    ]
    assert rows["scenes with a lower mat"]["n_gt"] == 2 and rows["scenes without a lower mat"]["n_gt"] == 0
    assert rows["scenes with a lower mat"]["precision"] == pytest.approx(2 / 4)
    assert rows["scenes without a lower mat"]["precision"] == 0.0  # its one detection is false
    other = tmp_path / "other"
    other.mkdir()
    samples, preds = _two_scenes(other, lower_mat=False)  # a dataset without the column: the inside alone
    assert list(breakdown(other, samples, preds, sigma=DEFAULT_OKS_SIGMA)) == [
        "crossings >= 8 px inside the frame"
    ]


def test_ap50_is_capped_by_the_recall_reached_however_few_the_false_detections():
    """COCOeval counts precision 0 at the recall thresholds above the highest reached: 98 of 100 crossings
    found exactly, no false detection, give AP@0.5 99/101, which is the ceiling the summary states."""
    uv = np.random.default_rng(5).uniform(50, 590, (100, 2))
    truths = [Truth(uv, np.full(100, 30.0))]
    m = summary(truths, [np.c_[uv[:98], np.ones(98)]])
    assert m["oks_recall50"] == pytest.approx(0.98)
    assert m["oks_ap50"] == pytest.approx(99 / 101) == m["oks_ap50_ceiling"]
    assert m["precision"] == 1.0 and m["recall_at_p99"] == pytest.approx(0.98)
    assert "AP@0.5 at most 0.9802" in format_summary(m)
    # every crossing found lifts it to 1; one missing of 1000 still caps it at 100/101
    assert ap_ceiling(1.0) == 1.0 and ap_ceiling(0.999) == pytest.approx(100 / 101)
    assert np.isnan(ap_ceiling(float("nan")))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_ap50_never_exceeds_its_ceiling(seed):
    truths, preds = _scene(np.random.default_rng(seed))
    m = summary(truths, preds)
    assert 0.0 < m["oks_ap50"] <= m["oks_ap50_ceiling"] <= 1.0
    assert m["oks_recall50"] == pytest.approx(keypoint_ap(truths, preds).recall[0])
