"""Evaluation per manifest column, false positives on empty frames, the worst cases and the contact sheet."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from companion.lab.training.evaluate import contact_sheet, group_summaries, size_oracle, worst_cases
from companion.lab.training.metrics import DetectionStats
from companion.perception.detector.dataset import Sample


def _box(*v: float) -> np.ndarray:
    return np.asarray([v], np.float32).reshape(-1, 4)


def _setup(tmp_path: Path) -> tuple[list[Sample], DetectionStats]:
    samples = []
    for i, (dist, kind) in enumerate(
        [("CLOSE", "F450"), ("DISTANT", "F450"), ("DISTANT", "BIRD"), ("CLOSE", "BIRD")]
    ):
        p = tmp_path / f"img{i}.png"
        cv2.imwrite(str(p), np.full((120, 160, 3), 200, np.uint8))
        samples.append(Sample(p, None, attrs=(("distance_bin", dist), ("drone_type", kind))))
    empty = np.zeros((0, 4), np.float32)
    none = np.zeros(0, np.float32)
    stats = DetectionStats()
    stats.add(_box(10, 10, 40, 40), np.asarray([0.9], np.float32), _box(10, 10, 40, 40))  # found
    stats.add(_box(100, 50, 110, 60), np.asarray([0.2], np.float32), _box(100, 50, 112, 60))  # low score
    stats.add(_box(60, 60, 70, 70), np.asarray([0.8], np.float32), empty)  # false positive
    stats.add(empty, none, empty)  # clean empty frame
    return samples, stats


def test_groups_report_recall_and_false_positives_per_value(tmp_path: Path) -> None:
    samples, stats = _setup(tmp_path)
    g = group_summaries(stats, samples, ["distance_bin", "drone_type", "absent"], 0.5)
    assert set(g) == {"distance_bin", "drone_type"}
    assert g["distance_bin"]["CLOSE"]["recall"] == 1.0
    assert g["distance_bin"]["CLOSE"]["leader_free_fp_rate"] == 0.0
    assert g["distance_bin"]["DISTANT"]["recall"] == 0.0
    assert g["distance_bin"]["DISTANT"]["leader_free_fp_rate"] == 1.0
    assert g["drone_type"]["BIRD"]["leader_free_fp_rate"] == 0.5
    assert g["drone_type"]["BIRD"]["leader_boxes"] == 0
    assert stats.summary(0.5)["leader_free_fp_rate"] == 0.5


def test_worst_cases_and_contact_sheet(tmp_path: Path) -> None:
    samples, stats = _setup(tmp_path)
    misses, fps = worst_cases(stats, 0.5, 5)
    assert [(c.image_index, round(c.score, 2)) for c in misses] == [(1, 0.2)]
    assert [(c.image_index, round(c.score, 2)) for c in fps] == [(2, 0.8)]
    out = contact_sheet(samples, stats, misses, fps, tmp_path / "sheet.png", conf_threshold=0.5, tile_px=64)
    img = cv2.imread(str(out))
    assert img is not None
    assert img.shape[1] == 6 * 64


def test_size_oracle_separates_box_size_from_detection(tmp_path: Path) -> None:
    """Two 'videos' whose labels carry different margins: centred predictions of one size miss IoU 0.5 on
    both, and each video's own scale recovers them (the oracle), while no single scale fits both."""
    samples: list[Sample] = []
    stats = DetectionStats()
    for i in range(6):
        video = "tight" if i < 3 else "loose"
        p = tmp_path / f"v{i}.png"
        cv2.imwrite(str(p), np.full((120, 160, 3), 200, np.uint8))
        samples.append(Sample(p, None, attrs=(("video", video),)))
        half = 10.0 if video == "tight" else 40.0  # label half-sides: 20 px and 80 px boxes
        label = _box(80 - half, 60 - half, 80 + half, 60 + half)
        pred = _box(60, 40, 100, 80)  # 40 px, centred: IoU 0.25 with either label
        stats.add(pred, np.asarray([0.9 - 0.01 * i], np.float32), label)
    s = stats.summary(0.5)
    assert s["map50"] == 0.0
    assert s["ap25"] > 0.99
    assert s["recall_loose"] == 1.0
    assert s["box_scale_median"] == pytest.approx(1.0)  # half of the ratios are 2, half 0.5
    g = group_summaries(stats, samples, ["video"], 0.5)
    assert g["video"]["tight"]["box_scale_median"] == 2.0
    assert g["video"]["loose"]["box_scale_median"] == 0.5
    o = size_oracle(stats, samples, "video")
    assert o["map50"] > 0.99
    assert 0.6 < o["scales"]["tight"] < 0.75
    assert 1.35 < o["scales"]["loose"] < 1.6
