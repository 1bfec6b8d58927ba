"""Detection metrics in numpy: precision, recall, AP over IoU thresholds, recall by range, false positives.

Matching is COCO-style: predictions in descending score order each take the unmatched ground-truth box they
overlap most (IoU >= threshold). AP is the area under the interpolated precision-recall curve sampled at 101
recall points, averaged over IoU 0.50:0.05:0.95 for mAP@0.5:0.95 (one class, so AP = mAP).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.perception.detector.postprocess import box_iou

IOU_THRESHOLDS = np.round(np.arange(0.5, 0.96, 0.05), 2)
#: Also reported, outside mAP@0.5:0.95: AP at IoU 0.25, for data whose boxes are loose (hand- or
#: semi-automatically labelled video, where a tight box around a 10 px drone can miss IoU 0.5).
LOOSE_IOU = 0.25
#: Range bins for recall, m: [lo, hi).
RANGE_BINS_M: tuple[tuple[float, float], ...] = ((0.0, 5.0), (5.0, 10.0), (10.0, 15.0), (15.0, 20.0))


def match(
    pred_boxes: NDArray[np.floating],
    pred_scores: NDArray[np.floating],
    gt_boxes: NDArray[np.floating],
    iou_thresholds: Sequence[float] | NDArray[np.floating] = IOU_THRESHOLDS,
) -> tuple[NDArray[np.bool_], NDArray[np.intp]]:
    """Greedy matching at every IoU threshold.

    Returns ``tp`` (P, T): prediction p (in the given order) is a true positive at threshold t; and
    ``gt_match`` (G, T): index of the prediction matched to each ground truth box, -1 if none.
    """
    thr = np.asarray(iou_thresholds, np.float64)
    p, g, t = len(pred_boxes), len(gt_boxes), len(thr)
    tp = np.zeros((p, t), bool)
    gt_match = np.full((g, t), -1, np.intp)
    if p == 0 or g == 0:
        return tp, gt_match
    iou = box_iou(pred_boxes, gt_boxes)  # (P, G)
    taken = np.zeros((g, t), bool)
    for i in np.argsort(-np.asarray(pred_scores), kind="stable"):
        cand = np.where(taken, -1.0, iou[i][:, None])  # (G, T)
        best = cand.argmax(0)
        ok = cand[best, np.arange(t)] >= thr
        tp[i] = ok
        cols = np.flatnonzero(ok)
        taken[best[cols], cols] = True
        gt_match[best[cols], cols] = i
    return tp, gt_match


def average_precision(scores: NDArray[np.floating], tp: NDArray[np.bool_], n_gt: int) -> float:
    """101-point interpolated AP of one IoU threshold from all predictions' scores and TP flags."""
    if n_gt == 0:
        return float("nan")
    if len(scores) == 0:
        return 0.0
    order = np.argsort(-scores, kind="stable")
    tps = np.cumsum(tp[order])
    fps = np.cumsum(~tp[order])
    recall = tps / n_gt
    precision = tps / np.maximum(tps + fps, 1)
    envelope = np.maximum.accumulate(precision[::-1])[::-1]
    points = np.linspace(0.0, 1.0, 101)
    idx = np.searchsorted(recall, points, side="left")
    sampled = np.where(idx < len(envelope), envelope[np.minimum(idx, len(envelope) - 1)], 0.0)
    return float(sampled.mean())


@dataclass
class ImageRecord:
    """What one image contributed: predictions (at a low threshold) and ground truth."""

    pred_boxes: NDArray[np.float32]
    pred_scores: NDArray[np.float32]
    gt_boxes: NDArray[np.float32]
    range_m: float | None
    #: None of the leader visible (for the false-positive rate); None: judge by the labels.
    leader_free: bool | None = None


@dataclass
class DetectionStats:
    """Accumulates images, then summarises at an operating confidence threshold."""

    records: list[ImageRecord] = field(default_factory=list)

    def add(
        self,
        pred_boxes: NDArray[np.float32],
        pred_scores: NDArray[np.float32],
        gt_boxes: NDArray[np.float32],
        range_m: float | None = None,
        leader_free: bool | None = None,
    ) -> None:
        self.records.append(ImageRecord(pred_boxes, pred_scores, gt_boxes, range_m, leader_free))

    def summary(
        self, conf_threshold: float, iou_thresholds: NDArray[np.floating] = IOU_THRESHOLDS
    ) -> dict[str, Any]:
        """Every figure of the evaluation as a JSON-ready dict (see :func:`format_summary`)."""
        all_scores, all_tp = [], []
        n_gt = 0
        op_tp = op_fp = 0
        leader_free = leader_free_fp = 0
        loose_found = 0
        size_ratios: list[float] = []
        bin_hits = np.zeros(len(RANGE_BINS_M), int)
        bin_total = np.zeros(len(RANGE_BINS_M), int)
        i50 = int(np.argmin(np.abs(iou_thresholds - 0.5)))
        thresholds = np.concatenate((iou_thresholds, [LOOSE_IOU]))
        for r in self.records:
            tp, gt_match = match(r.pred_boxes, r.pred_scores, r.gt_boxes, thresholds)
            all_scores.append(r.pred_scores)
            all_tp.append(tp)
            n_gt += len(r.gt_boxes)
            above = r.pred_scores >= conf_threshold
            op_tp += int((tp[:, i50] & above).sum())
            op_fp += int((~tp[:, i50] & above).sum())
            loose = gt_match[:, -1]
            for g, p in enumerate(loose.tolist()):
                if p >= 0 and above[p]:
                    loose_found += 1
                    size_ratios.append(_side_ratio(r.pred_boxes[p], r.gt_boxes[g]))
            if r.leader_free if r.leader_free is not None else len(r.gt_boxes) == 0:
                leader_free += 1
                leader_free_fp += int(above.any())
            if r.range_m is not None and len(r.gt_boxes):
                m = gt_match[:, i50]
                if len(r.pred_scores):
                    found = (m >= 0) & (r.pred_scores[np.maximum(m, 0)] >= conf_threshold)
                else:  # nothing predicted in this image: every box is missed
                    found = np.zeros(len(m), bool)
                for b, (lo, hi) in enumerate(RANGE_BINS_M):
                    if lo <= r.range_m < hi:
                        bin_total[b] += len(found)
                        bin_hits[b] += int(found.sum())
        scores = np.concatenate(all_scores) if all_scores else np.zeros(0, np.float32)
        tps = np.concatenate(all_tp) if all_tp else np.zeros((0, len(thresholds)), bool)
        aps = [average_precision(scores, tps[:, t], n_gt) for t in range(len(iou_thresholds))]
        ap_loose = average_precision(scores, tps[:, -1], n_gt)
        near = bin_total[:2].sum()
        return {
            "images": len(self.records),
            "leader_boxes": n_gt,
            "conf_threshold": conf_threshold,
            "precision": op_tp / (op_tp + op_fp) if op_tp + op_fp else float("nan"),
            "recall": op_tp / n_gt if n_gt else float("nan"),
            "map50": aps[i50],
            "map50_95": float(np.mean(aps)) if n_gt else float("nan"),
            "ap25": ap_loose,
            "recall_loose": loose_found / n_gt if n_gt else float("nan"),
            # In logs, so that boxes twice and half their labels' size average to 1.
            "box_scale_median": float(np.exp(np.median(np.log(size_ratios)))) if size_ratios else None,
            "ap_by_iou": {f"{t:.2f}": a for t, a in zip(iou_thresholds, aps, strict=True)},
            "recall_by_range_m": {
                f"{lo:g}-{hi:g}": {"recall": (h / n if n else None), "boxes": int(n)}
                for (lo, hi), h, n in zip(RANGE_BINS_M, bin_hits, bin_total, strict=True)
            },
            "recall_within_10m": (bin_hits[:2].sum() / near) if near else None,
            "leader_free_images": leader_free,
            "leader_free_fp_rate": leader_free_fp / leader_free if leader_free else None,
        }


def _side_ratio(pred: NDArray[np.floating], gt: NDArray[np.floating]) -> float:
    """sqrt(area ratio) of a predicted box to its label: > 1 where the prediction is the larger."""
    pa = max(float(pred[2] - pred[0]), 0.0) * max(float(pred[3] - pred[1]), 0.0)
    ga = max(float(gt[2] - gt[0]), 1e-6) * max(float(gt[3] - gt[1]), 1e-6)
    return float(np.sqrt(pa / ga))


def scaled_boxes(boxes: NDArray[np.float32], scale: float) -> NDArray[np.float32]:
    """``boxes`` (N, 4, xyxy) scaled by ``scale`` about their centres."""
    c = (boxes[:, :2] + boxes[:, 2:]) / 2
    h = (boxes[:, 2:] - boxes[:, :2]) * (scale / 2)
    return np.concatenate((c - h, c + h), 1).astype(np.float32)


def ap50_scaled(records: Sequence[ImageRecord], scale: float) -> float:
    """AP@0.5 of ``records`` with every predicted box scaled by ``scale`` about its centre."""
    scores, tps, n_gt = [], [], 0
    for r in records:
        tp, _ = match(scaled_boxes(r.pred_boxes, scale), r.pred_scores, r.gt_boxes, (0.5,))
        scores.append(r.pred_scores)
        tps.append(tp[:, 0])
        n_gt += len(r.gt_boxes)
    if not scores:
        return float("nan")
    return average_precision(np.concatenate(scores), np.concatenate(tps), n_gt)


def _fmt(v: Any, pct: bool = True) -> str:
    if v is None or (isinstance(v, float) and np.isnan(v)):
        return "n/a"
    return f"{100 * v:.1f}%" if pct else str(v)


def format_summary(s: dict[str, Any]) -> str:
    """A short human-readable table of a :meth:`DetectionStats.summary`."""
    lines = [
        f"images {s['images']}, leader boxes {s['leader_boxes']}, "
        f"leader-free images {s['leader_free_images']}",
        f"at conf >= {s['conf_threshold']:.2f}: precision {_fmt(s['precision'])}, recall {_fmt(s['recall'])} "
        f"(at IoU 0.25 {_fmt(s['recall_loose'])})",
        f"mAP@0.5 {_fmt(s['map50'])}, mAP@0.5:0.95 {_fmt(s['map50_95'])} (AP@0.25 {_fmt(s['ap25'])})",
    ]
    bins = [
        f"{k} m {_fmt(v['recall'])} (n={v['boxes']})" for k, v in s["recall_by_range_m"].items() if v["boxes"]
    ]
    if bins:
        lines.append("recall by range: " + ", ".join(bins) + f"; within 10 m {_fmt(s['recall_within_10m'])}")
    else:
        lines.append("recall by range: no ranges known for this data")
    if s.get("box_scale_median") is not None:
        lines.append(f"found boxes' side against their labels' (median ratio): {s['box_scale_median']:.2f}")
    lines.append(f"false positives on leader-free images: {_fmt(s['leader_free_fp_rate'])}")
    return "\n".join(lines)
