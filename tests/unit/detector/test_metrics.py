from __future__ import annotations

import numpy as np
import pytest

from companion.lab.training.metrics import DetectionStats, average_precision, format_summary, match

E = np.zeros((0, 4), np.float32)


def b(*xs: float) -> np.ndarray:
    return np.asarray(xs, np.float32).reshape(-1, 4)


def test_match_is_greedy_by_score_and_one_to_one() -> None:
    gt = b(0, 0, 10, 10)
    pred = b(0, 0, 10, 10, 1, 1, 10, 10)
    tp, gm = match(pred, np.array([0.5, 0.9]), gt, [0.5])
    assert tp[:, 0].tolist() == [False, True]  # the higher score takes the box, the duplicate is a FP
    assert gm[0, 0] == 1


def test_ap_of_a_perfect_detector_is_one_and_of_none_is_zero() -> None:
    assert average_precision(np.array([0.9, 0.8]), np.array([True, True]), 2) == pytest.approx(1.0)
    assert average_precision(np.zeros(0), np.zeros(0, bool), 3) == 0.0
    # Half the boxes found, no false positive: precision 1 up to recall 0.5 -> 51 of 101 points.
    assert average_precision(np.array([0.9]), np.array([True]), 2) == pytest.approx(51 / 101)


def test_summary_operating_point_range_bins_and_leader_free_fp() -> None:
    s = DetectionStats()
    s.add(b(0, 0, 10, 10), np.array([0.9], np.float32), b(0, 0, 10, 10), range_m=3.0)  # TP near
    s.add(b(0, 0, 10, 10), np.array([0.2], np.float32), b(0, 0, 10, 10), range_m=12.0)  # below conf: miss
    s.add(b(0, 0, 5, 5), np.array([0.6], np.float32), E, range_m=None)  # FP on a leader-free frame
    s.add(E, np.zeros(0, np.float32), E)  # clean leader-free frame
    out = s.summary(conf_threshold=0.5)
    assert out["precision"] == pytest.approx(0.5)
    assert out["recall"] == pytest.approx(0.5)
    assert out["recall_by_range_m"]["0-5"] == {"recall": 1.0, "boxes": 1}
    assert out["recall_by_range_m"]["10-15"] == {"recall": 0.0, "boxes": 1}
    assert out["recall_by_range_m"]["15-20"]["recall"] is None
    assert out["recall_within_10m"] == pytest.approx(1.0)
    assert out["leader_free_images"] == 2
    assert out["leader_free_fp_rate"] == pytest.approx(0.5)
    # AP ranks all predictions: TP 0.9, FP 0.6, TP 0.2 -> precision 1 to recall .5, then 2/3 to recall 1.
    assert out["map50"] == pytest.approx((51 * 1.0 + 50 * 2 / 3) / 101)
    assert "false positives on leader-free images: 50.0%" in format_summary(out)


def test_map50_95_penalises_loose_boxes() -> None:
    s = DetectionStats()
    s.add(b(0, 0, 10, 12), np.array([0.9], np.float32), b(0, 0, 10, 10))  # IoU 0.833
    out = s.summary(0.5)
    assert out["map50"] == pytest.approx(1.0)
    assert out["map50_95"] == pytest.approx(0.7)  # TP at 0.50 .. 0.80: 7 of 10 thresholds


def test_a_frame_with_an_unlabelled_leader_is_not_leader_free() -> None:
    s = DetectionStats()
    s.add(b(0, 0, 5, 5), np.array([0.9], np.float32), E, leader_free=False)  # leader too hidden for a box
    s.add(E, np.zeros(0, np.float32), E, leader_free=True)
    out = s.summary(0.5)
    assert out["leader_free_images"] == 1
    assert out["leader_free_fp_rate"] == 0.0
    assert out["precision"] == 0.0  # still a false positive for precision (no box to match)


def test_loose_iou_ap_is_reported_apart() -> None:
    s = DetectionStats()
    s.add(b(0, 0, 10, 10), np.array([0.9], np.float32), b(-4, -4, 14, 14))  # IoU 100/324 = 0.31
    out = s.summary(0.5)
    assert out["map50"] == 0.0
    assert out["ap25"] == pytest.approx(1.0)


def test_a_labelled_frame_with_no_prediction_counts_as_a_miss_in_its_range_bin() -> None:
    s = DetectionStats()
    s.add(E, np.zeros(0, np.float32), b(0, 0, 10, 10), range_m=7.0)
    out = s.summary(conf_threshold=0.5)
    assert out["recall_by_range_m"]["5-10"] == {"recall": 0.0, "boxes": 1}
    assert out["recall"] == 0.0
