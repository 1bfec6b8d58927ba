"""The region-of-interest window: geometry, the cut-box rule, the focus hold, the fallback, the mapping."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.config import DetectorConfig
from companion.perception.detector import load_detector
from companion.perception.detector.roi import RoiDetector, RoiWindow, cut_by_window, focus_box, roi_window
from companion.perception.types import Detection, DetectorResult, DetectorTiming

CFG = DetectorConfig(roi_conf_threshold=0.2)  # the lower window threshold on (off by default)


def test_window_is_three_box_widths_at_the_frame_aspect_magnified() -> None:
    # A 450-class quad 5 m ahead: ~51x29 px in a 640x480 frame.
    win = roi_window((300.0, 200.0, 351.0, 229.0), 640, 480, CFG)
    assert win is not None
    assert (win.w_px, win.h_px) == (160, 120)  # 3 x 51 = 153 -> the next 32 px step, 4:3
    assert win.input_size_px == 288  # 1.75 x 160 = 280 -> the next multiple of 32
    assert win.x0_px + win.w_px / 2 == pytest.approx(325.5, abs=1.0)
    assert win.y0_px + win.h_px / 2 == pytest.approx(214.5, abs=1.0)


def test_window_stays_inside_the_frame_and_has_a_minimum() -> None:
    win = roi_window((0.0, 470.0, 10.0, 480.0), 640, 480, CFG)
    assert win == RoiWindow(0, 480 - 96, 128, 96, 224)


def test_a_near_leader_gets_the_whole_frame_and_input_is_capped() -> None:
    assert roi_window((100.0, 100.0, 300.0, 250.0), 640, 480, CFG) is None  # 600 px > 0.6 x 640
    win = roi_window(
        (250.0, 200.0, 370.0, 260.0), 640, 480, CFG.model_copy(update={"roi_max_frame_fraction": 1.0})
    )
    assert win is not None
    assert win.input_size_px == CFG.input_size_px


def test_boxes_touching_an_inner_window_edge_are_cut_but_frame_edges_are_not() -> None:
    win = RoiWindow(100, 0, 160, 120, 256)
    assert cut_by_window((100.5, 50.0, 130.0, 70.0), win, 640, 480)  # left edge inside the frame
    assert cut_by_window((200.0, 50.0, 259.5, 70.0), win, 640, 480)  # right edge
    assert cut_by_window((200.0, 50.0, 230.0, 119.5), win, 640, 480)  # bottom edge
    assert not cut_by_window((200.0, 0.0, 230.0, 20.0), win, 640, 480)  # top edge is the frame's
    assert not cut_by_window((150.0, 40.0, 200.0, 70.0), win, 640, 480)


class _Track:
    def __init__(self, status: str, box: tuple[float, float, float, float] | None) -> None:
        self.status = type("S", (), {"name": status})()
        self.measurement = None if box is None else type("M", (), {"box_xyxy_px": box})()


def test_focus_comes_only_from_a_confirmed_track_measurement() -> None:
    box = (1.0, 2.0, 3.0, 4.0)
    assert focus_box(_Track("CONFIRMED", box)) == box
    assert focus_box(_Track("TENTATIVE", box)) is None
    assert focus_box(_Track("CONFIRMED", None)) is None
    assert focus_box(_Track("COASTING", box)) is None


class _Inner:
    """Records which search ran; answers from canned results."""

    runtime = "fake"
    input_size_px = 320
    conf_threshold = 0.35

    def __init__(self, window: list[Detection], whole: list[Detection]) -> None:
        self.window, self.whole = window, whole
        self.calls: list[str] = []

    def detect(self, rgb: np.ndarray) -> DetectorResult:
        self.calls.append(f"whole {self.input_size_px}")
        return DetectorResult(list(self.whole), DetectorTiming(1.0, 8.0, 0.5))

    def detect_window(
        self, rgb: np.ndarray, xywh: tuple[int, int, int, int], size: int, conf: float | None = None
    ) -> DetectorResult:
        if xywh == (0, 0, rgb.shape[1], rgb.shape[0]):
            self.calls.append(f"whole {size}")
            return DetectorResult(list(self.whole), DetectorTiming(1.0, 8.0, 0.5))
        self.calls.append(f"window {xywh} {size} {conf}")
        return DetectorResult(list(self.window), DetectorTiming(0.5, 4.0, 0.5))


def test_detector_searches_the_window_holds_it_and_falls_back_to_the_frame() -> None:
    leader = Detection((300.0, 200.0, 351.0, 229.0), 0.9)
    inner = _Inner([leader], [])
    roi = RoiDetector(inner, CFG)  # type: ignore[arg-type]
    rgb = np.zeros((480, 640, 3), np.uint8)
    assert roi.detect(rgb).detections == []  # no focus yet: the whole frame
    roi.focus(leader.box_xyxy_px)
    assert roi.detect(rgb).detections == [leader]
    assert inner.calls[-1].startswith("window")
    assert inner.calls[-1].endswith(f" {CFG.roi_conf_threshold}")  # the window's own, lower threshold
    for _ in range(CFG.roi_low_conf_misses):  # a few misses: the window keeps its lower threshold
        roi.focus(None)
    roi.detect(rgb)
    assert inner.calls[-1].endswith(f" {CFG.roi_conf_threshold}")
    for _ in range(CFG.roi_hold_frames - CFG.roi_low_conf_misses):  # more: held, at the usual threshold
        roi.focus(None)
    roi.detect(rgb)
    assert inner.calls[-1].startswith("window")
    assert inner.calls[-1].endswith(" None")
    roi.focus(None)  # one miss too many: whole frames again (the second search without a window: the
    roi.detect(rgb)  # network's own input, see the alternation test)
    assert inner.calls[-1] == f"whole {inner.input_size_px}"
    assert inner.calls[0] == f"whole {CFG.search_input_px}"


def test_searches_without_a_window_alternate_with_the_networks_input_but_fallbacks_do_not() -> None:
    """A close leader scores low at 1:1 for a network trained smaller; a window's fallback stays at 1:1."""
    rgb = np.zeros((480, 640, 3), np.uint8)
    inner = _Inner([], [])
    roi = RoiDetector(inner, CFG)  # type: ignore[arg-type]
    for _ in range(4):
        roi.detect(rgb)
    assert inner.calls == ["whole 640", "whole 320", "whole 640", "whole 320"]
    roi.focus((300.0, 200.0, 351.0, 229.0))
    for _ in range(3):
        roi.detect(rgb)  # the window finds nothing: the fallback, always 1:1
    assert [c for c in inner.calls[4:] if c.startswith("whole")] == ["whole 640"] * 3
    roi.reset()
    roi.detect(rgb)
    assert inner.calls[-1] == "whole 640"  # a reset starts over at 1:1
    inner = _Inner([], [])
    roi = RoiDetector(inner, CFG.model_copy(update={"search_alternate": False}))  # type: ignore[arg-type]
    for _ in range(3):
        roi.detect(rgb)
    assert inner.calls == ["whole 640"] * 3


def test_the_whole_frame_is_searched_at_its_own_input_size() -> None:
    """640 (the default) shows a 640 px frame 1:1; equal to ``input_size_px`` it is the plain detect."""
    rgb = np.zeros((480, 640, 3), np.uint8)
    for size, call in ((640, "whole 640"), (320, "whole 320")):
        inner = _Inner([], [])
        roi = RoiDetector(inner, CFG.model_copy(update={"search_input_px": size}))  # type: ignore[arg-type]
        roi.detect(rgb)
        roi.focus((300.0, 200.0, 351.0, 229.0))
        roi.detect(rgb)  # the window finds nothing: the same search
        assert inner.calls == [call, inner.calls[1], call]
        assert inner.calls[1].startswith("window")


def test_an_empty_or_cut_window_result_falls_back_to_the_whole_frame_in_the_same_call() -> None:
    cut = Detection((240.0, 200.0, 300.0, 229.0), 0.9)  # crosses the window's left edge (x0 = 246)
    whole = Detection((230.0, 200.0, 300.0, 229.0), 0.6)
    inner = _Inner([cut], [whole])
    roi = RoiDetector(inner, CFG)  # type: ignore[arg-type]
    roi.focus((300.0, 200.0, 351.0, 229.0))
    result = roi.detect(np.zeros((480, 640, 3), np.uint8))
    assert inner.calls[0].startswith("window")
    assert inner.calls[1] == f"whole {CFG.search_input_px}"
    assert result.detections == [whole]
    assert result.timing is not None
    assert result.timing.inference_ms == pytest.approx(12.0)
    assert (roi.window_frames, roi.fallback_frames) == (1, 1)


def test_window_boxes_are_in_frame_pixels(shipped_model: Path) -> None:
    """The real network on a patch pasted into a bigger frame: the window gives the patch's boxes, shifted."""
    det = load_detector(DetectorConfig(model_path=str(shipped_model), conf_threshold=0.002), runtime="onnx")
    patch = np.random.default_rng(3).integers(0, 256, (240, 320, 3), dtype=np.uint8)
    frame = np.zeros((480, 640, 3), np.uint8)
    frame[100:340, 64:384] = patch
    alone = det.detect(patch).detections
    inside = det.detect_window(frame, (64, 100, 320, 240), det.input_size_px).detections
    assert len(alone) == len(inside) > 0
    for a, b in zip(alone, inside, strict=True):
        assert b.score == pytest.approx(a.score, abs=1e-6)
        assert np.allclose(np.subtract(b.box_xyxy_px, a.box_xyxy_px), (64, 100, 64, 100), atol=1e-3)


def test_the_lower_window_threshold_only_speaks_when_nothing_passes_the_usual_one() -> None:
    leader = Detection((300.0, 200.0, 351.0, 229.0), 0.25)
    weak = Detection((260.0, 240.0, 280.0, 250.0), 0.22)
    strong = Detection((250.0, 170.0, 270.0, 180.0), 0.5)
    roi = RoiDetector(_Inner([leader, weak], []), CFG)  # type: ignore[arg-type]
    roi.focus(leader.box_xyxy_px)
    assert roi.detect(np.zeros((480, 640, 3), np.uint8)).detections == [leader]
    roi = RoiDetector(_Inner([strong, leader, weak], []), CFG)  # type: ignore[arg-type]
    roi.focus(leader.box_xyxy_px)
    assert roi.detect(np.zeros((480, 640, 3), np.uint8)).detections == [strong]
