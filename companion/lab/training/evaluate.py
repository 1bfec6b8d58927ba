"""Evaluation of a detector on any folder of images with YOLO labels (rendered test split or real frames).

Besides the figures of :meth:`DetectionStats.summary` over the whole folder, the same figures per value of
the manifest's text columns (e.g. ``distance_bin``, ``drone_type``: recall and mAP where the group has
boxes, the false-positive rate where it has leader-free images), and a contact sheet: crops of the worst
misses (labelled leaders the detector scored lowest) and the worst false positives (highest-scoring
detections that match no label), for people to look at.

Where the manifest gives the leader's range (renders), recall and AP per 2 m range bin
(:func:`range_bins`), for the whole frame and, with ``window``, for the service's tracking window on the
leader (:func:`collect_window`): the window the service would search had the tracker held the labelled box
(:func:`companion.perception.detector.roi.roi_window`), letterboxed at its magnification, its edge-cut boxes
dropped as the service drops them.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.config import DetectorConfig
from companion.lab.training.metrics import DetectionStats, ap50_scaled, scaled_boxes
from companion.perception.detector.dataset import Sample, read_labels, read_rgb
from companion.perception.detector.postprocess import box_iou
from companion.perception.detector.roi import cut_by_window, roi_window
from companion.perception.detector.runtime import FrameDetector

#: Predictions below this score still count for AP (the precision-recall curve); the operating point uses
#: the detector's own confidence threshold.
AP_SCORE_FLOOR = 0.001
#: Manifest columns reported per value by default (when the manifest has them).
DEFAULT_COLUMNS = ("distance_bin", "drone_type", "airframe", "time_of_day")
#: IoU at which a detection counts as finding a labelled leader (the operating point, contact sheet).
MATCH_IOU = 0.5
#: Width of the range bins of :func:`range_bins`, m.
RANGE_BIN_M = 2.0


@dataclass(frozen=True)
class Case:
    """One entry of the contact sheet: a missed leader or a false positive."""

    kind: str  # "miss" | "false positive"
    image_index: int
    box_xyxy_px: tuple[float, float, float, float]
    #: Miss: best score of any detection overlapping the label (0: none); false positive: its score.
    score: float


def group_summaries(
    stats: DetectionStats, samples: Sequence[Sample], columns: Sequence[str], conf_threshold: float
) -> dict[str, dict[str, dict[str, Any]]]:
    """Column -> value -> figures of the images with that value (only columns some sample has)."""
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for col in columns:
        values = sorted({v for s in samples if (v := s.attr(col)) is not None})
        if not values:
            continue
        per: dict[str, dict[str, Any]] = {}
        for v in values:
            sub = DetectionStats([r for r, s in zip(stats.records, samples, strict=True) if s.attr(col) == v])
            full = sub.summary(conf_threshold)
            per[v] = {
                k: full[k]
                for k in (
                    "images",
                    "leader_boxes",
                    "recall",
                    "map50",
                    "recall_loose",
                    "box_scale_median",
                    "leader_free_images",
                )
                if k in full
            }
            per[v]["leader_free_fp_rate"] = full["leader_free_fp_rate"]
        out[col] = per
    return out


#: Box scales the size oracle tries: 0.4x to 2.5x, log-spaced.
ORACLE_SCALES = np.exp(np.linspace(np.log(0.4), np.log(2.5), 41))


def size_oracle(stats: DetectionStats, samples: Sequence[Sample], column: str) -> dict[str, Any]:
    """mAP@0.5 had each ``column`` group's predicted boxes been scaled by the factor best for that group.

    A diagnostic for loosely labelled data, not a figure of the detector: where labels carry a margin that
    differs from group to group (e.g. per video), it separates box-size disagreement from detection. Each
    group's scale is chosen on its own AP@0.5 (an oracle: it sees the labels); groups without boxes keep 1.
    """
    groups: dict[str, list[int]] = {}
    for i, s in enumerate(samples):
        groups.setdefault(s.attr(column) or "", []).append(i)
    scales: dict[str, float] = {}
    scaled = DetectionStats()
    for value, idx in sorted(groups.items()):
        recs = [stats.records[i] for i in idx]
        if not sum(len(r.gt_boxes) for r in recs):
            scales[value] = 1.0
        else:
            aps = np.asarray([ap50_scaled(recs, float(k)) for k in ORACLE_SCALES])
            # Of the scales that do best, the one nearest 1: the least correction that explains the labels.
            best = np.flatnonzero(aps >= np.nanmax(aps) - 1e-9)
            scales[value] = float(ORACLE_SCALES[best[np.argmin(np.abs(np.log(ORACLE_SCALES[best])))]])
        for r in recs:
            scaled.add(scaled_boxes(r.pred_boxes, scales[value]), r.pred_scores, r.gt_boxes, r.range_m)
    return {
        "column": column,
        "map50": scaled.summary(1.0)["map50"],
        "scales": scales,
    }


def worst_cases(stats: DetectionStats, conf_threshold: float, n: int) -> tuple[list[Case], list[Case]]:
    """The ``n`` worst misses (lowest best score on the label) and false positives (highest score)."""
    misses: list[Case] = []
    fps: list[Case] = []
    for i, r in enumerate(stats.records):
        keep = r.pred_scores >= conf_threshold
        pb, ps = r.pred_boxes[keep], r.pred_scores[keep]
        iou = box_iou(r.gt_boxes, r.pred_boxes) if len(r.gt_boxes) and len(r.pred_boxes) else None
        iou_op = box_iou(r.gt_boxes, pb) if len(r.gt_boxes) and len(pb) else np.zeros((len(r.gt_boxes), 0))
        for g, box in enumerate(r.gt_boxes):
            if iou_op.shape[1] and (iou_op[g] >= MATCH_IOU).any():
                continue
            best = 0.0
            if iou is not None:
                over = iou[g] >= MATCH_IOU
                best = float(r.pred_scores[over].max()) if over.any() else 0.0
            misses.append(Case("miss", i, _tuple(box), best))
        matched_gt: NDArray[np.bool_] = np.zeros(len(pb), bool)
        if len(r.gt_boxes) and len(pb):
            matched_gt = np.asarray((box_iou(pb, r.gt_boxes) >= MATCH_IOU).any(1), bool)
        for box, score, hit in zip(pb, ps, matched_gt.tolist(), strict=True):
            if not hit:
                fps.append(Case("false positive", i, _tuple(box), float(score)))
    misses.sort(key=lambda c: c.score)
    fps.sort(key=lambda c: -c.score)
    return misses[:n], fps[:n]


def _tuple(b: NDArray[np.float32]) -> tuple[float, float, float, float]:
    return float(b[0]), float(b[1]), float(b[2]), float(b[3])


def contact_sheet(
    samples: Sequence[Sample],
    stats: DetectionStats,
    misses: Sequence[Case],
    false_positives: Sequence[Case],
    path: Path,
    *,
    conf_threshold: float,
    tile_px: int = 160,
    columns: int = 6,
) -> Path:
    """Write a PNG: a row block of misses, then one of false positives; each tile a crop around the case.

    Green: labelled boxes; red: detections at or above ``conf_threshold``; the caption gives the kind, the
    score and the image name.
    """
    import cv2  # noqa: PLC0415

    def tile(case: Case) -> NDArray[np.uint8]:
        rgb = read_rgb(samples[case.image_index].image_path)
        h, w = rgb.shape[:2]
        x0, y0, x1, y1 = case.box_xyxy_px
        side = max(64.0, 3.0 * max(x1 - x0, y1 - y0))
        cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
        ax0 = int(np.clip(cx - side / 2, 0, max(0, w - side)))
        ay0 = int(np.clip(cy - side / 2, 0, max(0, h - side)))
        s = int(min(side, w, h))
        crop = np.ascontiguousarray(rgb[ay0 : ay0 + s, ax0 : ax0 + s, ::-1])
        f = tile_px / s
        big = cv2.resize(crop, (tile_px, tile_px), interpolation=cv2.INTER_NEAREST)
        rec = stats.records[case.image_index]

        def draw(boxes: NDArray[np.float32], colour: tuple[int, int, int]) -> None:
            for b in boxes:
                p0 = (round((b[0] - ax0) * f), round((b[1] - ay0) * f))
                p1 = (round((b[2] - ax0) * f), round((b[3] - ay0) * f))
                cv2.rectangle(big, p0, p1, colour, 1)

        draw(rec.gt_boxes, (0, 200, 0))
        draw(rec.pred_boxes[rec.pred_scores >= conf_threshold], (0, 0, 255))
        canvas = np.full((tile_px + 30, tile_px, 3), 255, np.uint8)
        canvas[:tile_px] = big
        label = "MISS" if case.kind == "miss" else "FP"
        cv2.putText(canvas, f"{label} {case.score:.2f}", (2, tile_px + 12), 0, 0.4, (0, 0, 0), 1)
        name = samples[case.image_index].key[-24:]
        cv2.putText(canvas, name, (2, tile_px + 26), 0, 0.3, (60, 60, 60), 1)
        return canvas

    def block(cases: Sequence[Case], title: str) -> NDArray[np.uint8]:
        head = np.full((22, columns * tile_px, 3), 255, np.uint8)
        cv2.putText(head, title, (4, 16), 0, 0.5, (0, 0, 0), 1)
        rows = [head]
        tiles = [tile(c) for c in cases]
        for r in range(0, len(tiles), columns):
            row = tiles[r : r + columns]
            row += [np.full_like(tiles[0], 255)] * (columns - len(row))
            rows.append(np.concatenate(row, 1))
        if not tiles:
            empty = np.full((30, columns * tile_px, 3), 255, np.uint8)
            cv2.putText(empty, "none", (4, 20), 0, 0.5, (0, 0, 0), 1)
            rows.append(empty)
        return np.concatenate(rows, 0)

    sheet = np.concatenate(
        (
            block(misses, f"worst misses (labelled leader, best score below {conf_threshold:.2f})"),
            block(false_positives, f"worst false positives (score >= {conf_threshold:.2f}, no label)"),
        ),
        0,
    )
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), sheet)
    return path


def collect(detector: FrameDetector, samples: Sequence[Sample], progress: bool = True) -> DetectionStats:
    """Run ``detector`` on every sample; the predictions (down to :data:`AP_SCORE_FLOOR`) and labels."""
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
    return stats


def range_bins(
    stats: DetectionStats, conf_threshold: float, bin_m: float = RANGE_BIN_M
) -> list[dict[str, Any]]:
    """Figures per ``bin_m`` range bin ([lo, hi) m) of the images whose range is known, nearest first.

    Each bin's recall (IoU 0.5 and 0.25, at ``conf_threshold``), mAP@0.5 and AP@0.25 are over its own
    images: their labelled boxes and every prediction on them.
    """
    groups: dict[int, list[Any]] = {}
    for r in stats.records:
        if r.range_m is not None and np.isfinite(r.range_m):
            groups.setdefault(int(r.range_m // bin_m), []).append(r)
    out = []
    for b in sorted(groups):
        full = DetectionStats(groups[b]).summary(conf_threshold)
        out.append(
            {
                "range_m": [b * bin_m, (b + 1) * bin_m],
                "images": full["images"],
                "leader_boxes": full["leader_boxes"],
                "recall": full["recall"],
                "recall_loose": full["recall_loose"],
                "map50": full["map50"],
                "ap25": full["ap25"],
            }
        )
    return out


def collect_window(
    detector: FrameDetector, samples: Sequence[Sample], cfg: DetectorConfig, progress: bool = True
) -> DetectionStats:
    """The detector in the tracking window on each labelled leader (frames without a label: skipped).

    The window is :func:`~companion.perception.detector.roi.roi_window` of the frame's largest label, as if
    the tracker held that box; where none fits (a leader so near that the window would cover most of the
    frame) the frame is searched whole at the detector's input, as the service does.
    """
    stats = DetectionStats()
    iterator: Sequence[Sample] = samples
    if progress:
        from tqdm import tqdm  # noqa: PLC0415

        iterator = tqdm(samples, desc="evaluating (window)", unit="img", leave=False)
    for s in iterator:
        if s.label_path is None:
            continue
        rgb = read_rgb(s.image_path)
        h, w = rgb.shape[:2]
        labels = read_labels(s, w, h)
        if not len(labels):
            continue
        big = labels[int(np.argmax((labels[:, 2] - labels[:, 0]) * (labels[:, 3] - labels[:, 1])))]
        win = roi_window(_tuple(big), w, h, cfg)
        if win is None:
            boxes, scores = detector.raw(rgb, AP_SCORE_FLOOR)
            boxes = boxes.copy()
        else:
            found = detector.detect_window(
                rgb, (win.x0_px, win.y0_px, win.w_px, win.h_px), win.input_size_px, AP_SCORE_FLOOR
            ).detections
            kept = [d for d in found if not cut_by_window(d.box_xyxy_px, win, w, h)]
            boxes = np.asarray([d.box_xyxy_px for d in kept], np.float32).reshape(-1, 4)
            scores = np.asarray([d.score for d in kept], np.float32)
        stats.add(boxes, scores, labels, s.range_m, False)
    return stats


def evaluate(
    detector: FrameDetector,
    samples: Sequence[Sample],
    progress: bool = True,
    *,
    columns: Sequence[str] = DEFAULT_COLUMNS,
    sheet: Path | None = None,
    sheet_cases: int = 12,
    size_oracle_by: str | None = None,
    window: DetectorConfig | None = None,
) -> dict[str, Any]:
    """Run ``detector`` on every sample and summarise (see :meth:`DetectionStats.summary`).

    Adds ``by_column`` (:func:`group_summaries`), ``by_range_m`` (:func:`range_bins`, empty without
    ranges), with ``window`` (the service's detector settings) the same figures in the tracking window
    (:func:`collect_window`) under ``window``, and with ``sheet`` writes the contact sheet there.
    """
    stats = collect(detector, samples, progress)
    out = stats.summary(detector.conf_threshold)
    out["by_column"] = group_summaries(stats, samples, columns, detector.conf_threshold)
    out["by_range_m"] = range_bins(stats, detector.conf_threshold)
    if window is not None:
        win_stats = collect_window(detector, samples, window, progress)
        out["window"] = win_stats.summary(detector.conf_threshold)
        out["window"]["by_range_m"] = range_bins(win_stats, detector.conf_threshold)
    if size_oracle_by:
        out["size_oracle"] = size_oracle(stats, samples, size_oracle_by)
    if sheet is not None:
        misses, fps = worst_cases(stats, detector.conf_threshold, sheet_cases)
        out["contact_sheet"] = str(
            contact_sheet(samples, stats, misses, fps, sheet, conf_threshold=detector.conf_threshold)
        )
    out["runtime"] = detector.runtime
    out["input_size_px"] = detector.input_size_px
    out["nms_iou"] = detector.nms_iou
    return out
