"""Letterboxing: fit a frame into the network input without distorting it, and map boxes back.

The frame is scaled so that its longer side equals ``input_size_px`` and each side is padded up to a multiple
of the network stride (32), not to a square: a 640x480 frame becomes 320x256, not 320x320 (20% less work).
Downscaling uses area interpolation (the same in training and at run time, so small targets look alike).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np
from numpy.typing import NDArray

#: Grey fill of the padding, as in the training images.
PAD_VALUE = 114
STRIDE = 32


@dataclass(frozen=True, slots=True)
class LetterboxGeometry:
    """How a ``src_w_px`` x ``src_h_px`` frame maps into an ``input_w_px`` x ``input_h_px`` network input."""

    src_w_px: int
    src_h_px: int
    input_w_px: int
    input_h_px: int
    #: input px per source px.
    scale: float
    #: Size of the scaled frame inside the input, px.
    resized_w_px: int
    resized_h_px: int
    #: Offset of the scaled frame inside the input (the left and top padding), px.
    pad_x_px: int
    pad_y_px: int


def letterbox_geometry(
    src_h_px: int, src_w_px: int, input_size_px: int, stride: int = STRIDE
) -> LetterboxGeometry:
    """Fit the longer side to ``input_size_px``; pad each side up to a multiple of ``stride``."""
    if src_h_px <= 0 or src_w_px <= 0:
        raise ValueError(f"empty frame {src_w_px}x{src_h_px}")
    scale = input_size_px / max(src_h_px, src_w_px)
    rw = max(1, round(src_w_px * scale))
    rh = max(1, round(src_h_px * scale))
    iw = math.ceil(rw / stride) * stride
    ih = math.ceil(rh / stride) * stride
    return LetterboxGeometry(src_w_px, src_h_px, iw, ih, scale, rw, rh, (iw - rw) // 2, (ih - rh) // 2)


def resize_image(
    img: NDArray[np.uint8], w_px: int, h_px: int, dst: NDArray[np.uint8] | None = None
) -> NDArray[np.uint8]:
    """Resize with area interpolation when shrinking and bilinear when enlarging (into ``dst`` if given)."""
    if img.shape[1] == w_px and img.shape[0] == h_px:
        if dst is None:
            return img
        dst[...] = img
        return dst
    interp = cv2.INTER_AREA if w_px < img.shape[1] else cv2.INTER_LINEAR
    out = cv2.resize(img, (w_px, h_px), dst=dst, interpolation=interp)
    return np.asarray(out, dtype=np.uint8)


def letterbox_uint8(img: NDArray[np.uint8], geom: LetterboxGeometry) -> NDArray[np.uint8]:
    """A new HxWx3 uint8 letterboxed image (training, tools; the frame path uses :class:`Letterboxer`)."""
    out = np.full((geom.input_h_px, geom.input_w_px, 3), PAD_VALUE, np.uint8)
    y, x = geom.pad_y_px, geom.pad_x_px
    out[y : y + geom.resized_h_px, x : x + geom.resized_w_px] = resize_image(
        img, geom.resized_w_px, geom.resized_h_px
    )
    return out


def boxes_to_source(boxes_xyxy_px: NDArray[np.float32], geom: LetterboxGeometry) -> NDArray[np.float32]:
    """Boxes in network-input pixels -> boxes in source-frame pixels, clipped to the frame (in place)."""
    b = boxes_xyxy_px
    b[:, 0::2] -= geom.pad_x_px  # views of columns 0, 2 and 1, 3 (fancy indexing would copy)
    b[:, 1::2] -= geom.pad_y_px
    b /= geom.scale
    np.clip(b[:, 0::2], 0.0, geom.src_w_px, out=b[:, 0::2])
    np.clip(b[:, 1::2], 0.0, geom.src_h_px, out=b[:, 1::2])
    return b


class Letterboxer:
    """Turns RGB frames into the network's NCHW float32 input in [0, 1], reusing its buffers.

    The buffers are allocated for the first frame size seen and again only when the size changes; each call
    writes into them and returns the same input array, so a caller must use it before the next call.
    """

    def __init__(self, input_size_px: int, stride: int = STRIDE) -> None:
        self.input_size_px = input_size_px
        self.stride = stride
        self.geometry: LetterboxGeometry | None = None
        self._resized: NDArray[np.uint8] = np.empty((0, 0, 3), np.uint8)
        self._input: NDArray[np.float32] = np.empty((1, 3, 0, 0), np.float32)

    def _allocate(self, h_px: int, w_px: int) -> LetterboxGeometry:
        g = letterbox_geometry(h_px, w_px, self.input_size_px, self.stride)
        self.geometry = g
        self._resized = np.empty((g.resized_h_px, g.resized_w_px, 3), np.uint8)
        self._input = np.full((1, 3, g.input_h_px, g.input_w_px), PAD_VALUE / 255.0, np.float32)
        return g

    def __call__(self, rgb: NDArray[np.uint8]) -> tuple[NDArray[np.float32], LetterboxGeometry]:
        """Letterbox one HxWx3 uint8 RGB frame; returns the (1, 3, H, W) input and its geometry."""
        g = self.geometry
        if g is None or g.src_h_px != rgb.shape[0] or g.src_w_px != rgb.shape[1]:
            g = self._allocate(rgb.shape[0], rgb.shape[1])
        resized = resize_image(rgb, g.resized_w_px, g.resized_h_px, dst=self._resized)
        y, x = g.pad_y_px, g.pad_x_px
        view = self._input[0, :, y : y + g.resized_h_px, x : x + g.resized_w_px]
        np.multiply(resized.transpose(2, 0, 1), np.float32(1.0 / 255.0), out=view)
        return self._input, g
