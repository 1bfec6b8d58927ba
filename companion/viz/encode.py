"""Encoding helpers for the viz messages: Foxglove's basic types, JSON without NaN, images, vehicle fields."""

from __future__ import annotations

import json
import math
from typing import Any

import cv2
import numpy as np
from foxglove import messages as fm
from numpy.typing import NDArray

from companion.kernel.camera import DepthImage, RgbImage
from companion.kernel.flight import (
    NEVER_S,
    AttitudeSetpoint,
    Setpoint,
    VehicleState,
    VelocityBodySetpoint,
    VelocityNedSetpoint,
)
from companion.kernel.frames import quat_from_R

Record = tuple[str, int, bytes]

#: MAVLink's satellites_visible for "unknown" (GPS_RAW_INT), logged as null rather than as a count.
SATELLITES_UNKNOWN = 255


def stamp(ns: int) -> fm.Timestamp:
    """A Foxglove timestamp from nanoseconds."""
    return fm.Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def v3(x: float, y: float, z: float) -> fm.Vector3:
    """A Foxglove vector."""
    return fm.Vector3(x=x, y=y, z=z)


def quat(R: Any) -> fm.Quaternion:
    """A rotation matrix as a Foxglove quaternion."""
    w, x, y, z = (float(c) for c in quat_from_R(R))
    return fm.Quaternion(x=x, y=y, z=z, w=w)


def pose(p: tuple[float, float, float], R: Any = None) -> fm.Pose:
    """A Foxglove pose: position ``p``, rotation ``R`` (identity when None)."""
    q = fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0) if R is None else quat(R)
    return fm.Pose(position=v3(*p), orientation=q)


def json_record(topic: str, ns: int, payload: dict[str, Any]) -> Record:
    """``payload`` as a JSON record on ``topic`` at ``ns`` (NaN and infinity written as null)."""
    try:
        text = json.dumps(payload, allow_nan=False, separators=(",", ":"))
    except ValueError:  # a NaN or infinity somewhere: JSON has none, so null
        text = json.dumps(no_nan(payload), separators=(",", ":"))
    return topic, ns, text.encode()


def no_nan(x: Any) -> Any:
    """``x`` with every non-finite float replaced by None (nested dicts and lists too)."""
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {k: no_nan(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [no_nan(v) for v in x]
    return x


def finite_or_none(x: float) -> float | None:
    """``x``, or None when it is not finite."""
    return x if math.isfinite(x) else None


def rounded(v: Any, nd: int = 4) -> list[float]:
    """A vector as a list of floats rounded to ``nd`` decimals."""
    return [round(float(c), nd) for c in v]


def encode_colour(rgb: RgbImage, fmt: str, jpeg_quality: int) -> bytes:
    """RGB pixels as JPEG or PNG bytes."""
    bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
    params = [cv2.IMWRITE_JPEG_QUALITY, jpeg_quality] if fmt == "jpeg" else [cv2.IMWRITE_PNG_COMPRESSION, 1]
    ok, buf = cv2.imencode(".jpg" if fmt == "jpeg" else ".png", bgr, params)
    if not ok:
        raise ValueError(f"{fmt} encoding failed")
    return buf.tobytes()


def depth_mm(depth_m: DepthImage, step: int = 1) -> NDArray[np.uint16]:
    """Depth in millimetres as uint16 (0: no depth), every ``step``-th pixel."""
    d = depth_m[::step, ::step] if step > 1 else depth_m
    mm: NDArray[np.uint16] = np.clip(np.nan_to_num(d, nan=0.0) * 1000.0 + 0.5, 0.0, 65535.0).astype(np.uint16)
    return mm


def vehicle_fields(now_s: float, v: VehicleState) -> dict[str, Any]:
    """The ``/vehicle/status`` fields of ``v`` at ``now_s`` (service clock, s)."""
    return {
        "stamp_s": now_s,
        "link_ok": v.connected,
        "heartbeat_age_s": None
        if v.heartbeat_stamp_s == NEVER_S
        else round(max(0.0, now_s - v.heartbeat_stamp_s), 3),
        "armed": v.armed,
        "in_air": v.in_air,
        "flight_mode": v.flight_mode.value,
        "gps_fix_type": v.gps_fix_type,
        "gps_satellites": None if v.gps_satellites == SATELLITES_UNKNOWN else v.gps_satellites,
        "gps_ok": v.global_position_ok,
        "position_valid": v.position_valid,
        "p_ned_m": rounded(v.p_ned_m),
        "v_ned_m_s": rounded(v.v_ned_m_s),
        "battery_remaining_frac": finite_or_none(v.battery_remaining_frac),
    }


def setpoint_fields(sp: Setpoint | None) -> dict[str, Any]:
    """The setpoint's kind and values for ``/follower/formation``."""
    if isinstance(sp, VelocityNedSetpoint):
        return {
            "setpoint_kind": "velocity_ned",
            "setpoint_v_m_s": rounded(sp.v_ned_m_s),
            "setpoint_yaw_rad": sp.yaw_rad,
            "setpoint_a_m_s2": None if sp.a_ned_m_s2 is None else rounded(sp.a_ned_m_s2),
        }
    if isinstance(sp, VelocityBodySetpoint):
        return {
            "setpoint_kind": "velocity_body",
            "setpoint_v_m_s": rounded(sp.v_body_m_s),
            "setpoint_yaw_rate_rad_s": sp.yaw_rate_rad_s,
        }
    if isinstance(sp, AttitudeSetpoint):
        return {
            "setpoint_kind": "attitude",
            "setpoint_roll_rad": sp.roll_rad,
            "setpoint_pitch_rad": sp.pitch_rad,
            "setpoint_yaw_rad": sp.yaw_rad,
            "setpoint_thrust_norm": sp.thrust_norm,
        }
    return {"setpoint_kind": "none"}
