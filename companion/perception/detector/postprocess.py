"""Turning the network's raw maps into boxes, in numpy: threshold first, then decode, then NMS.

The network emits one map per level, (1, 4*reg_max + 1, H/s, W/s): box-distance logits (left, top, right,
bottom, each a distribution over ``reg_max`` bins of one stride) and one leader logit. Only cells whose score
passes the threshold are decoded, so the cost is a sigmoid over ~1,700 cells plus a few softmaxes.
Shared by the torch and ONNX Runtime paths, so both give the same boxes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float32]


def logit(p: float) -> float:
    """Inverse sigmoid."""
    return math.log(p / (1.0 - p))


def box_iou(a: NDArray[np.floating], b: NDArray[np.floating]) -> NDArray[np.float64]:
    """IoU matrix (N, M) of boxes ``a`` (N, 4) and ``b`` (M, 4), both x0 y0 x1 y1."""
    a64 = np.asarray(a, np.float64)[:, None, :]
    b64 = np.asarray(b, np.float64)[None, :, :]
    iw = np.clip(np.minimum(a64[..., 2], b64[..., 2]) - np.maximum(a64[..., 0], b64[..., 0]), 0.0, None)
    ih = np.clip(np.minimum(a64[..., 3], b64[..., 3]) - np.maximum(a64[..., 1], b64[..., 1]), 0.0, None)
    inter = iw * ih
    area_a = (a64[..., 2] - a64[..., 0]) * (a64[..., 3] - a64[..., 1])
    area_b = (b64[..., 2] - b64[..., 0]) * (b64[..., 3] - b64[..., 1])
    union = area_a + area_b - inter
    return np.where(union > 0.0, inter / np.where(union > 0.0, union, 1.0), 0.0)


def nms(boxes: NDArray[np.floating], scores: NDArray[np.floating], iou_threshold: float) -> NDArray[np.intp]:
    """Greedy non-maximum suppression; indices of the kept boxes, best first.

    The IoU matrix is computed once (vectorised); the greedy pass only visits boxes not yet suppressed.
    """
    order = np.argsort(-scores, kind="stable")
    if order.size <= 1:
        return order.astype(np.intp)
    iou = box_iou(boxes[order], boxes[order])
    suppressed = np.zeros(order.size, bool)
    keep: list[int] = []
    for i in range(order.size):
        if suppressed[i]:
            continue
        keep.append(i)
        suppressed |= iou[i] > iou_threshold
    return order[np.asarray(keep, np.intp)]


#: Cell grids cached by :class:`Decoder` (one per input size) before the cache is cleared.
MAX_GRIDS = 16


class Decoder:
    """Decodes raw level maps into boxes in network-input pixels; caches the cell grid per input size."""

    def __init__(self, strides: Sequence[int], reg_max: int) -> None:
        self.strides = tuple(strides)
        self.reg_max = reg_max
        self._bins = np.arange(reg_max, dtype=np.float32)
        # One grid per input size: whole frames and region-of-interest windows alternate (see .roi).
        self._grids: dict[tuple[tuple[int, int], ...], tuple[FloatArray, FloatArray]] = {}

    def _grid(self, shapes: tuple[tuple[int, int], ...]) -> tuple[FloatArray, FloatArray]:
        grid = self._grids.get(shapes)
        if grid is None:
            pts, strides = [], []
            for (h, w), s in zip(shapes, self.strides, strict=True):
                gy, gx = np.meshgrid(
                    np.arange(h, dtype=np.float32), np.arange(w, dtype=np.float32), indexing="ij"
                )
                pts.append(np.stack(((gx.ravel() + 0.5) * s, (gy.ravel() + 0.5) * s), 1))
                strides.append(np.full(h * w, s, np.float32))
            if len(self._grids) >= MAX_GRIDS:
                self._grids.clear()
            grid = self._grids[shapes] = (np.concatenate(pts), np.concatenate(strides))
        return grid

    def __call__(
        self,
        levels: Sequence[FloatArray],
        conf_threshold: float,
        nms_iou: float,
        max_det: int = 20,
        pre_nms_top_k: int = 200,
    ) -> tuple[FloatArray, FloatArray]:
        """Boxes (N, 4) x0 y0 x1 y1 in input pixels and scores (N,), best first, for image 0 of the batch."""
        shapes = tuple((int(lv.shape[-2]), int(lv.shape[-1])) for lv in levels)
        points, stride_col = self._grid(shapes)
        cls_logits = np.concatenate([lv[0, -1].ravel() for lv in levels])
        cand = np.flatnonzero(cls_logits > logit(conf_threshold))
        if cand.size == 0:
            return np.empty((0, 4), np.float32), np.empty((0,), np.float32)
        if cand.size > pre_nms_top_k:
            cand = cand[np.argpartition(-cls_logits[cand], pre_nms_top_k)[:pre_nms_top_k]]
        scores = (1.0 / (1.0 + np.exp(-cls_logits[cand]))).astype(np.float32)
        box_logits = self._gather_box_logits(levels, shapes, cand)  # (n, 4, reg_max)
        box_logits -= box_logits.max(-1, keepdims=True)
        prob = np.exp(box_logits)
        ltrb = (prob @ self._bins) / prob.sum(-1)  # (n, 4) in strides
        ltrb *= stride_col[cand, None]
        p = points[cand]
        boxes = np.concatenate((p - ltrb[:, :2], p + ltrb[:, 2:]), 1).astype(np.float32)
        keep = nms(boxes, scores, nms_iou)[:max_det]
        return boxes[keep], scores[keep]

    def _gather_box_logits(
        self, levels: Sequence[FloatArray], shapes: tuple[tuple[int, int], ...], cand: NDArray[np.intp]
    ) -> FloatArray:
        out = np.empty((cand.size, 4 * self.reg_max), np.float32)
        start = 0
        for lv, (h, w) in zip(levels, shapes, strict=True):
            n = h * w
            sel = (cand >= start) & (cand < start + n)
            if sel.any():
                out[sel] = lv[0, :-1].reshape(4 * self.reg_max, n)[:, cand[sel] - start].T
            start += n
        return out.reshape(cand.size, 4, self.reg_max)
