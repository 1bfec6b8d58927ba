from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from companion.perception.detector.postprocess import Decoder, box_iou, logit, nms


def test_box_iou_hand_cases() -> None:
    a = np.array([[0, 0, 10, 10], [0, 0, 0, 0]], np.float32)
    b = np.array([[0, 0, 10, 10], [5, 0, 15, 10], [20, 20, 30, 30]], np.float32)
    iou = box_iou(a, b)
    np.testing.assert_allclose(iou[0], [1.0, 50 / 150, 0.0])
    np.testing.assert_allclose(iou[1], [0.0, 0.0, 0.0])  # degenerate box: no division by zero


def test_nms_keeps_best_of_overlapping_and_separate_boxes() -> None:
    boxes = np.array([[0, 0, 10, 10], [1, 1, 11, 11], [50, 50, 60, 60], [0, 0, 10, 10.5]], np.float32)
    scores = np.array([0.8, 0.9, 0.5, 0.1], np.float32)
    assert nms(boxes, scores, 0.5).tolist() == [1, 2]
    assert nms(boxes[:0], scores[:0], 0.5).size == 0


box_strategy = arrays(np.float32, (30, 4), elements=st.floats(0, 100, width=32))


@settings(max_examples=60, deadline=None)
@given(
    raw=box_strategy,
    scores=arrays(np.float32, 30, elements=st.floats(0, 1, width=32)),
    thr=st.floats(0.1, 0.9),
)
def test_nms_properties(raw: np.ndarray, scores: np.ndarray, thr: float) -> None:
    boxes = np.concatenate([np.minimum(raw[:, :2], raw[:, 2:]), np.maximum(raw[:, :2], raw[:, 2:])], 1)
    keep = nms(boxes, scores, thr)
    kept = boxes[keep]
    iou = box_iou(kept, kept)
    np.fill_diagonal(iou, 0)
    assert (iou <= thr + 1e-6).all()  # no two kept boxes overlap beyond the threshold
    assert (np.diff(scores[keep]) <= 0).all()  # best first
    dropped = np.setdiff1d(np.arange(len(boxes)), keep)
    if len(dropped):  # each dropped box is covered by a kept box at least as good
        cover = box_iou(boxes[dropped], kept) > thr
        better = scores[keep][None, :] >= scores[dropped][:, None]
        assert (cover & better).any(1).all()


def _levels_with_one_box(strides: tuple[int, ...], reg_max: int, h: int, w: int) -> list[np.ndarray]:
    levels = [np.full((1, 4 * reg_max + 1, h // s, w // s), -20.0, np.float32) for s in strides]
    # One cell of the stride-16 level, at row 3, col 5 -> centre (88, 56); distances 2, 1, 3, 4 strides.
    lv = levels[1]
    lv[0, -1, 3, 5] = logit(0.9)
    for side, dist in enumerate((2, 1, 3, 4)):
        lv[0, side * reg_max + dist, 3, 5] = 20.0
    return levels


def test_decoder_recovers_an_encoded_box() -> None:
    dec = Decoder((8, 16, 32), 16)
    boxes, scores = dec(_levels_with_one_box((8, 16, 32), 16, 256, 320), 0.5, 0.5)
    assert scores.tolist() == pytest.approx([0.9])
    np.testing.assert_allclose(boxes[0], [88 - 32, 56 - 16, 88 + 48, 56 + 64], atol=1e-3)
    boxes, _ = dec(_levels_with_one_box((8, 16, 32), 16, 256, 320), 0.95, 0.5)
    assert boxes.shape == (0, 4)  # below the threshold


def test_decoder_caps_candidates_and_detections() -> None:
    dec = Decoder((8, 16, 32), 4)
    levels = [np.zeros((1, 17, 256 // s, 320 // s), np.float32) for s in (8, 16, 32)]
    boxes, _scores = dec(levels, 0.3, 0.5, max_det=5, pre_nms_top_k=50)
    assert len(boxes) <= 5
