"""The camera wire format between the simulator and the service: one RGB-D frame per message.

The simulator's camera server (:class:`sitl.render.camera_server.CameraServer`) writes it over a Unix
socket and the service's sim frame source (:mod:`companion.perception.sources.sim`) reads it; it lives
here so that neither program imports the other. One message per frame, little-endian::

    magic        4 bytes   b"WGRD"
    header_len   uint32
    header       JSON (UTF-8), header_len bytes
    rgb          uint8, height x width x 3 (RGB order), header["rgb_bytes"] bytes
    depth        uint16 millimetres or float32 metres, height x width, header["depth_bytes"] bytes

``header``: ``v`` (1), ``seq``, ``stamp_s`` (sim clock), ``width``, ``height``, ``intrinsics``
([fx, fy, cx, cy] px), ``depth`` ("u16_mm" or "f32_m"; 0 = invalid either way), ``rgb_bytes``,
``depth_bytes`` and ``truth`` (null, or the fields of :class:`GroundTruth` as JSON, NaN as null).
Depth as uint16 mm halves the bandwidth and quantises to 1 mm, as a RealSense does.
"""

from __future__ import annotations

import json
import math
import struct
from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import GroundTruth, Intrinsics, RgbdFrame

MAGIC = b"WGRD"
WIRE_VERSION = 1
#: Every message starts with the magic and the header length.
PREFIX = struct.Struct("<4sI")
#: Refuse headers longer than this (a corrupt stream, not a frame).
MAX_HEADER_BYTES = 1 << 16

DepthEncoding = Literal["u16_mm", "f32_m"]


def _vec(values: Sequence[float] | None) -> list[float | None] | None:
    if values is None:
        return None
    return [float(v) if math.isfinite(float(v)) else None for v in values]


def _arr(values: Sequence[float | None] | None) -> NDArray[np.float64] | None:
    if values is None:
        return None
    return np.array([math.nan if v is None else float(v) for v in values], dtype=np.float64)


def truth_to_json(truth: GroundTruth | None) -> dict[str, Any] | None:
    """A JSON-safe dict of a frame's ground truth (NaN becomes null)."""
    if truth is None:
        return None
    return {
        "box_xyxy_px": None if truth.box_xyxy_px is None else [float(v) for v in truth.box_xyxy_px],
        "visible_fraction": float(truth.visible_fraction),
        "p_cam_leader_m": _vec(list(truth.p_cam_leader_m)),
        "yaw_rel_rad": float(truth.yaw_rel_rad) if math.isfinite(truth.yaw_rel_rad) else None,
        "p_ned_follower_m": _vec(None if truth.p_ned_follower_m is None else list(truth.p_ned_follower_m)),
        "p_ned_leader_m": _vec(None if truth.p_ned_leader_m is None else list(truth.p_ned_leader_m)),
        "q_ned_follower_wxyz": _vec(
            None if truth.q_ned_follower_wxyz is None else list(truth.q_ned_follower_wxyz)
        ),
    }


def truth_from_json(d: dict[str, Any] | None) -> GroundTruth | None:
    """Inverse of :func:`truth_to_json`."""
    if d is None:
        return None
    box = d.get("box_xyxy_px")
    p_cam = _arr(d.get("p_cam_leader_m"))
    yaw = d.get("yaw_rel_rad")
    return GroundTruth(
        box_xyxy_px=None if box is None else (float(box[0]), float(box[1]), float(box[2]), float(box[3])),
        visible_fraction=float(d["visible_fraction"]),
        p_cam_leader_m=p_cam if p_cam is not None else np.full(3, math.nan),
        yaw_rel_rad=math.nan if yaw is None else float(yaw),
        p_ned_follower_m=_arr(d.get("p_ned_follower_m")),
        p_ned_leader_m=_arr(d.get("p_ned_leader_m")),
        q_ned_follower_wxyz=_arr(d.get("q_ned_follower_wxyz")),
    )


def encode_frame(frame: RgbdFrame, depth: DepthEncoding = "u16_mm") -> list[bytes | memoryview]:
    """The wire message of one frame, as buffers to write in order (no copy of the colour image)."""
    rgb = np.ascontiguousarray(frame.rgb, dtype=np.uint8)
    if depth == "u16_mm":
        depth_buf = np.minimum(np.rint(frame.depth_m * np.float32(1000.0)), 65535).astype("<u2")
    else:
        depth_buf = np.ascontiguousarray(frame.depth_m, dtype="<f4")
    intr = frame.intrinsics
    header = {
        "v": WIRE_VERSION,
        "seq": frame.seq,
        "stamp_s": frame.stamp_s,
        "width": intr.width_px,
        "height": intr.height_px,
        "intrinsics": [intr.fx_px, intr.fy_px, intr.cx_px, intr.cy_px],
        "depth": depth,
        "rgb_bytes": rgb.nbytes,
        "depth_bytes": depth_buf.nbytes,
        "truth": truth_to_json(frame.truth),
    }
    raw = json.dumps(header, separators=(",", ":")).encode()
    return [PREFIX.pack(MAGIC, len(raw)) + raw, rgb.data.cast("B"), depth_buf.data.cast("B")]


def decode_frame(header: dict[str, Any], rgb_bytes: bytes, depth_bytes: bytes) -> RgbdFrame:
    """An :class:`RgbdFrame` from a parsed header and its payloads (rgb is a read-only view)."""
    w, h = int(header["width"]), int(header["height"])
    fx, fy, cx, cy = (float(v) for v in header["intrinsics"])
    rgb = np.frombuffer(rgb_bytes, dtype=np.uint8).reshape(h, w, 3)
    if header["depth"] == "u16_mm":
        depth = np.frombuffer(depth_bytes, dtype="<u2").reshape(h, w).astype(np.float32)
        depth *= np.float32(0.001)
    else:
        depth = np.frombuffer(depth_bytes, dtype="<f4").reshape(h, w).astype(np.float32)
    return RgbdFrame(
        rgb=rgb,
        depth_m=depth,
        intrinsics=Intrinsics(fx, fy, cx, cy, w, h),
        stamp_s=float(header["stamp_s"]),
        seq=int(header["seq"]),
        truth=truth_from_json(header.get("truth")),
    )
