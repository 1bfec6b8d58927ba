"""The RealSense SDK's ROS1 bag format (file format version 3): its layout, message types and image decoding.

Shared by the reader (:class:`~companion.perception.sources.bag.BagSource`, which also reads the rosbag2
recordings of the current SDK) and the writer (:mod:`companion.perception.sources.bag_writer`); the topic
layout is described in :mod:`companion.perception.sources.bag`.
"""

from __future__ import annotations

import re
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import DepthImage, Intrinsics, RgbImage
from companion.kernel.errors import CameraError
from companion.kernel.frames import Mat3, Vec3

FILE_VERSION = 3
STREAM_TOPIC = re.compile(r"^/device_(\d+)/sensor_(\d+)/(Depth|Color)_(\d+)/(.+)$")
STREAM_INFO_MSG = "uint32 fps\nstring encoding\nbool is_recommended\n"
#: ROS1 bags refuse a zero time; the SDK writes its static device description at this one.
STATIC_TIME_NS = 1


def typestore() -> Any:
    """The ROS1 Noetic type store plus realsense_msgs/StreamInfo (imports rosbags lazily)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore  # noqa: PLC0415

    ts = get_typestore(Stores.ROS1_NOETIC)
    ts.register(get_types_from_msg(STREAM_INFO_MSG, "realsense_msgs/msg/StreamInfo"))
    return ts


def header_stamp_s(header: Any) -> float:
    """A ROS header's stamp, s."""
    return float(header.stamp.sec) + float(header.stamp.nanosec) * 1e-9


def intrinsics_of(info: Any) -> Intrinsics:
    """Intrinsics of a sensor_msgs/CameraInfo."""
    K = np.asarray(info.K, dtype=np.float64)
    return Intrinsics(float(K[0]), float(K[4]), float(K[2]), float(K[5]), int(info.width), int(info.height))


def decode_depth_units(img: Any) -> NDArray[np.uint16]:
    """A mono16 / 16UC1 / z16 sensor_msgs/Image as an H x W uint16 array (a view where possible)."""
    if img.encoding.lower() not in ("mono16", "16uc1", "z16"):
        raise CameraError(f"bag source: depth encoding {img.encoding!r} is not supported (want mono16)")
    dtype = np.dtype(">u2" if img.is_bigendian else "<u2")
    rows = np.frombuffer(img.data, dtype=np.uint8).reshape(img.height, img.step)[:, : img.width * 2]
    return np.ascontiguousarray(rows).view(dtype).reshape(img.height, img.width).astype(np.uint16, copy=False)


COLOR_CHANNELS = {"rgb8": 3, "bgr8": 3, "rgba8": 4, "bgra8": 4, "yuv422": 2, "yuyv": 2, "uyvy": 2}


def decode_rgb(img: Any) -> RgbImage:
    """A colour sensor_msgs/Image (rgb8, bgr8, rgba8, bgra8, yuyv, uyvy) as H x W x 3 RGB uint8."""
    enc = img.encoding.lower()
    ch = COLOR_CHANNELS.get(enc)
    if ch is None:
        raise CameraError(f"bag source: colour encoding {img.encoding!r} is not supported")
    rows = np.frombuffer(img.data, dtype=np.uint8).reshape(img.height, img.step)[:, : img.width * ch]
    px = rows.reshape(img.height, img.width, ch)
    if enc == "rgb8":
        return np.ascontiguousarray(px)
    if enc == "bgr8":
        return np.ascontiguousarray(px[..., ::-1])
    if enc == "rgba8":
        return np.ascontiguousarray(px[..., :3])
    if enc == "bgra8":
        return np.ascontiguousarray(px[..., 2::-1])
    code = cv2.COLOR_YUV2RGB_UYVY if enc == "uyvy" else cv2.COLOR_YUV2RGB_YUYV
    return np.asarray(cv2.cvtColor(np.ascontiguousarray(px), code), dtype=np.uint8)


def align_depth_to_color(
    depth_m: DepthImage,
    depth_intr: Intrinsics,
    color_intr: Intrinsics,
    R_color_depth: Mat3,
    t_color_depth_m: Vec3,
) -> DepthImage:
    """Reproject a depth image into the colour camera (nearest surface wins; unfilled pixels are 0).

    Each valid depth pixel is back-projected, moved by ``p_color = R_color_depth @ p_depth + t`` and
    projected to the nearest colour pixel. Where the colour image is finer than the depth image some
    pixels stay empty, as with any point splat: the pose's robust depth ignores them.
    """
    v, u = np.nonzero(depth_m > 0)
    z = depth_m[v, u].astype(np.float64)
    pts = np.stack(
        [(u - depth_intr.cx_px) / depth_intr.fx_px * z, (v - depth_intr.cy_px) / depth_intr.fy_px * z, z]
    )
    pc = R_color_depth @ pts + t_color_depth_m.reshape(3, 1)
    front = pc[2] > 1e-6
    pc = pc[:, front]
    uc = np.rint(color_intr.fx_px * pc[0] / pc[2] + color_intr.cx_px).astype(np.int64)
    vc = np.rint(color_intr.fy_px * pc[1] / pc[2] + color_intr.cy_px).astype(np.int64)
    inside = (uc >= 0) & (uc < color_intr.width_px) & (vc >= 0) & (vc < color_intr.height_px)
    lin = vc[inside] * color_intr.width_px + uc[inside]
    zc = pc[2, inside]
    order = np.lexsort((zc, lin))  # by pixel, nearest first
    first = np.unique(lin[order], return_index=True)[1]
    out = np.zeros(color_intr.height_px * color_intr.width_px, dtype=np.float32)
    out[lin[order][first]] = zc[order][first]
    return out.reshape(color_intr.height_px, color_intr.width_px)
