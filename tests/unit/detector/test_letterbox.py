from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.perception.detector.letterbox import (
    PAD_VALUE,
    Letterboxer,
    boxes_to_source,
    letterbox_geometry,
    letterbox_uint8,
)


def test_vga_frame_becomes_320_by_256() -> None:
    g = letterbox_geometry(480, 640, 320)
    assert (g.input_w_px, g.input_h_px) == (320, 256)
    assert (g.resized_w_px, g.resized_h_px) == (320, 240)
    assert (g.pad_x_px, g.pad_y_px) == (0, 8)
    assert g.scale == pytest.approx(0.5)


def test_letterboxer_matches_reference_and_reuses_its_buffer() -> None:
    rng = np.random.default_rng(0)
    rgb = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    lb = Letterboxer(320)
    x1, g = lb(rgb)
    ref = letterbox_uint8(rgb, g).transpose(2, 0, 1)[None].astype(np.float32) / 255.0
    np.testing.assert_allclose(x1, ref, atol=1e-6)
    assert x1[0, 0, 0, 0] == pytest.approx(PAD_VALUE / 255.0)
    x2, _ = lb(rgb[::-1].copy())
    assert x2 is x1  # same preallocated buffer


def test_buffers_follow_a_new_frame_size() -> None:
    lb = Letterboxer(320)
    x, g = lb(np.zeros((512, 640, 3), np.uint8))
    assert x.shape == (1, 3, 256, 320)
    x, g = lb(np.zeros((100, 50, 3), np.uint8))
    assert x.shape == (1, 3, 320, 160)
    assert g.resized_w_px == 160


@settings(max_examples=50, deadline=None)
@given(
    h=st.integers(50, 1000),
    w=st.integers(50, 1000),
    size=st.sampled_from([128, 320, 416]),
    box=st.tuples(st.floats(0, 0.5), st.floats(0, 0.5), st.floats(0.5, 1), st.floats(0.5, 1)),
)
def test_boxes_round_trip_through_the_letterbox(h: int, w: int, size: int, box: tuple[float, ...]) -> None:
    g = letterbox_geometry(h, w, size)
    assert g.input_w_px % 32 == 0
    assert g.input_h_px % 32 == 0
    assert max(g.resized_w_px, g.resized_h_px) == size
    src = np.array([[box[0] * w, box[1] * h, box[2] * w, box[3] * h]], np.float32)
    net = src * g.scale + np.array([g.pad_x_px, g.pad_y_px, g.pad_x_px, g.pad_y_px], np.float32)
    back = boxes_to_source(net, g)
    np.testing.assert_allclose(back, src, atol=1e-3 * max(h, w))


def test_boxes_outside_the_frame_are_clipped() -> None:
    g = letterbox_geometry(480, 640, 320)
    b = np.array([[-10.0, 0.0, 400.0, 300.0]], np.float32)
    out = boxes_to_source(b, g)
    np.testing.assert_allclose(out, [[0.0, 0.0, 640.0, 480.0]])
