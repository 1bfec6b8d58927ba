"""The channels of the live view and the flight logs: topic, encoding and schema, one table for both.

Images, annotations, transforms, the 3D scene and the mission's log lines use Foxglove's well-known
schemas (protobuf, shipped with the Foxglove SDK), which Foxglove and Lichtblick draw without plugins; the
rest is JSON with a JSON Schema. Topics are relative to a follower's namespace (``/follower2/camera/image``
in a formation, ``/camera/image`` otherwise).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from typing import Any

from foxglove import messages as fm


@dataclass(frozen=True, slots=True)
class Topic:
    """One channel: its name, message encoding and schema (name, encoding, bytes)."""

    name: str
    message_encoding: str
    schema_name: str
    schema_encoding: str
    schema_data: bytes


def _well_known(name: str, message: Any) -> Topic:
    s = message.get_schema()
    return Topic(name, "protobuf", s.name, s.encoding, bytes(s.data))


def _json(name: str, schema_name: str, properties: dict[str, Any]) -> Topic:
    schema = {"type": "object", "title": schema_name, "properties": properties}
    return Topic(name, "json", schema_name, "jsonschema", json.dumps(schema).encode())


_VEC3 = {"type": "array", "items": {"type": "number"}, "minItems": 3, "maxItems": 3}
_NUM = {"type": "number"}
_STR = {"type": "string"}
_BOOL = {"type": "boolean"}
_INT = {"type": "integer"}

IMAGE = "/camera/image"
DEPTH = "/camera/depth"
CALIBRATION = "/camera/calibration"
ANNOTATIONS = "/camera/annotations"
TF = "/tf"
SCENE = "/scene"
MISSION_LOG = "/mission/log"
MISSION_STATE = "/mission/state"
FORMATION = "/follower/formation"
VEHICLE = "/vehicle/status"
PERCEPTION = "/perception/frame"
HEALTH = "/service/health"

TOPICS: dict[str, Topic] = {
    t.name: t
    for t in (
        _well_known(IMAGE, fm.CompressedImage),
        _well_known(DEPTH, fm.RawImage),
        _well_known(CALIBRATION, fm.CameraCalibration),
        _well_known(ANNOTATIONS, fm.ImageAnnotations),
        _well_known(TF, fm.FrameTransforms),
        _well_known(SCENE, fm.SceneUpdate),
        _well_known(MISSION_LOG, fm.Log),
        _json(
            MISSION_STATE,
            "wingman.MissionState",
            {"stamp_s": _NUM, "state": _STR, "reason": _STR, "detail": _STR, "vision_mode": _STR},
        ),
        _json(
            FORMATION,
            "wingman.Formation",
            {
                "stamp_s": _NUM,
                "formation_error_ned_m": _VEC3,
                "formation_error_m": _NUM,
                "leader_rel_ned_m": _VEC3,
                "leader_rel_sd_ned_m": _VEC3,
                "leader_status": _STR,
                "setpoint_kind": _STR,
                "setpoint_v_m_s": _VEC3,
                "setpoint_yaw_rad": _NUM,
                "setpoint_yaw_rate_rad_s": _NUM,
            },
        ),
        _json(
            VEHICLE,
            "wingman.VehicleStatus",
            {
                "stamp_s": _NUM,
                "link_ok": _BOOL,
                "heartbeat_age_s": _NUM,
                "armed": _BOOL,
                "in_air": _BOOL,
                "flight_mode": _STR,
                "gps_fix_type": _INT,
                "gps_satellites": _INT,  # null: the autopilot does not know (MAVLink's 255)
                "gps_ok": _BOOL,
                "position_valid": _BOOL,
                "p_ned_m": _VEC3,
                "v_ned_m_s": _VEC3,
                "battery_remaining_frac": _NUM,
            },
        ),
        _json(
            PERCEPTION,
            "wingman.PerceptionFrame",
            {
                "seq": _INT,
                "stamp_s": _NUM,
                "detections": {
                    "type": "array",
                    "items": {
                        "type": "object",
                        "properties": {
                            "box_xyxy_px": {"type": "array", "items": _NUM},
                            "score": _NUM,
                            "scale": _NUM,
                        },
                    },
                },
                "track_status": _STR,
                "track_id": _INT,
                "tracked_box_xyxy_px": {"type": "array", "items": _NUM},
                "leader_cam_m": _VEC3,
                "range_m": _NUM,
                "q_ned_body_wxyz": {"type": "array", "items": _NUM},
            },
        ),
        _json(
            HEALTH,
            "wingman.Health",
            {"stamp_s": _NUM, "healthy": _BOOL, "components": {"type": "object"}, "viz": {"type": "object"}},
        ),
    )
}
