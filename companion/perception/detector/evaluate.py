"""Evaluation of a detector on any folder of images with YOLO labels (rendered test split or real photos)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from companion.perception.detector.dataset import Sample, read_labels, read_rgb
from companion.perception.detector.metrics import DetectionStats
from companion.perception.detector.runtime import FrameDetector

#: Predictions below this score still count for AP (the precision-recall curve); the operating point uses
#: the detector's own confidence threshold.
AP_SCORE_FLOOR = 0.001


def evaluate(detector: FrameDetector, samples: Sequence[Sample], progress: bool = True) -> dict[str, Any]:
    """Run ``detector`` on every sample and summarise (see :meth:`DetectionStats.summary`)."""
    stats = DetectionStats()
    iterator: Sequence[Sample] = samples
    if progress:
        from tqdm import tqdm  # noqa: PLC0415

        iterator = tqdm(samples, desc="evaluating", unit="img", leave=False)
    for s in iterator:
        rgb = read_rgb(s.image_path)
        h, w = rgb.shape[:2]
        boxes, scores = detector.raw(rgb, AP_SCORE_FLOOR)
        leader_free = None if s.leader_visible is None else not s.leader_visible
        stats.add(boxes.copy(), scores, read_labels(s, w, h), s.range_m, leader_free)
    out = stats.summary(detector.conf_threshold)
    out["runtime"] = detector.runtime
    out["input_size_px"] = detector.input_size_px
    out["nms_iou"] = detector.nms_iou
    return out
