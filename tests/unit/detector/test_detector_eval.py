"""Evaluation per manifest column, false positives on empty frames, the worst cases and the contact sheet."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from companion.lab.training.evaluate import contact_sheet, group_summaries, worst_cases
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
