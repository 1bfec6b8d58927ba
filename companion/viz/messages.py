"""From what the flight saw to encoded messages of :mod:`companion.viz.channels` (on the worker thread).

Every builder returns ``(topic, log_time_ns, bytes)`` records. Times are the service clock's seconds plus a
fixed offset (``time_offset_s``: the wall clock's epoch in the service; in the simulator a fixed date, whose
logs start at 2000-01-01 00:00:00 UTC + sim time), in nanoseconds; a message's own timestamp is the same
instant, so images, their annotations and the frame's transforms line up.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from foxglove import messages as fm

from companion.kernel.camera import Intrinsics, RgbdFrame
from companion.kernel.flight import (
    Severity,
    VehicleState,
)
from companion.kernel.frames import R_from_euler, quat_from_R
from companion.mission.types import MissionInputs, StepOutput, Transition
from companion.perception.transform import CameraGeometry
from companion.perception.types import DetectorResult
from companion.viz import channels as ch
from companion.viz.encode import (
    Record,
    depth_mm,
    json_record,
    pose,
    quat,
    rounded,
    setpoint_fields,
    stamp,
    v3,
    vehicle_fields,
)
from companion.viz.frames import CAMERA, FOLLOWER, LEADER, R_FLU_FRD, WORLD, R_world_follower, enu

_LOG_LEVEL = {
    Severity.EMERGENCY: fm.LogLevel.Fatal,
    Severity.ALERT: fm.LogLevel.Fatal,
    Severity.CRITICAL: fm.LogLevel.Error,
    Severity.ERROR: fm.LogLevel.Error,
    Severity.WARNING: fm.LogLevel.Warning,
    Severity.NOTICE: fm.LogLevel.Info,
    Severity.INFO: fm.LogLevel.Info,
    Severity.DEBUG: fm.LogLevel.Debug,
}
_GREEN = fm.Color(r=0.1, g=0.9, b=0.2, a=1.0)
_ORANGE = fm.Color(r=1.0, g=0.6, b=0.1, a=1.0)
_WHITE = fm.Color(r=1.0, g=1.0, b=1.0, a=1.0)
_SHADE = fm.Color(r=0.0, g=0.0, b=0.0, a=0.6)
_TRACK_COLOUR = {
    "confirmed": fm.Color(r=0.1, g=0.9, b=0.2, a=0.35),
    "coasting": fm.Color(r=1.0, g=0.85, b=0.1, a=0.35),
}


def _box_edges(size_m: tuple[float, float, float]) -> list[fm.Point3]:
    """The 12 edges of a box centred on the origin, as a line list (pairs of points)."""
    hx, hy, hz = (x / 2.0 for x in size_m)
    corners = [(sx * hx, sy * hy, sz * hz) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    pts = []
    for i, a in enumerate(corners):
        for b in corners[i + 1 :]:
            if sum(x != y for x, y in zip(a, b, strict=True)) == 1:  # corners one axis apart: an edge
                pts += [fm.Point3(x=a[0], y=a[1], z=a[2]), fm.Point3(x=b[0], y=b[1], z=b[2])]
    return pts


#: The formation slot's wire box: the body (0.45 x 0.45 x 0.12 m) with a margin, so both show when they meet.
_SLOT_EDGES = _box_edges((0.7, 0.7, 0.3))
_TENTATIVE = fm.Color(r=0.6, g=0.6, b=0.6, a=0.35)
#: The camera frustum is drawn out to this range, m (about the stereo range).
FRUSTUM_RANGE_M = 10.0


@dataclass(frozen=True, slots=True)
class Namespace:
    """Where one follower's channels and frames live: ``""`` alone, its vehicle id in a formation.

    ``origin_ned_m`` places the follower's local NED origin in the shared ``world`` (formations), m.
    """

    prefix: str = ""
    origin_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def topic(self, name: str) -> str:
        return f"/{self.prefix}{name}" if self.prefix else name

    def frame(self, name: str) -> str:
        return f"{self.prefix}/{name}" if self.prefix else name


class MessageBuilder:
    """Builds the records of one follower (the recorder's worker calls it; nothing here blocks on I/O)."""

    def __init__(self, geometry: CameraGeometry, ns: Namespace, time_offset_s: float) -> None:
        self.geometry = geometry
        self.ns = ns
        self.time_offset_s = time_offset_s
        self._intrinsics: Intrinsics | None = None
        self._calibration: bytes = b""
        self._frustum: Any = None
        # The camera's mount in the follower's FLU body frame (fixed).
        self._R_flu_cam = R_FLU_FRD @ geometry.R_body_cam
        self._t_flu_cam = tuple(float(c) for c in R_FLU_FRD @ geometry.t_body_cam_m)

    def ns_of(self, stamp_s: float) -> int:
        """A service-clock stamp as the logs' time, ns."""
        return round((stamp_s + self.time_offset_s) * 1e9)

    # ---------------------------------------------------------------- per frame
    def frame_records(self, frame: RgbdFrame, result: DetectorResult, track: Any) -> list[Record]:
        """The frame's detections and track (JSON), its annotations and its calibration."""
        ns = self.ns_of(frame.stamp_s)
        ns_ = self.ns
        meas = None if track is None else track.measurement
        est = None if track is None else track.estimate
        payload: dict[str, Any] = {
            "seq": frame.seq,
            "stamp_s": frame.stamp_s,
            "detections": [
                {"box_xyxy_px": list(d.box_xyxy_px), "score": d.score, "scale": d.scale}
                for d in result.detections
            ],
            "track_status": "none" if track is None else track.status.value,
            "track_id": 0 if track is None else track.track_id,
            "tracked_box_xyxy_px": None if meas is None else list(meas.box_xyxy_px),
            "leader_cam_m": None if est is None else rounded(est.p_cam_leader_m),
            "range_m": None if est is None else round(float(est.range_m), 3),
            "q_ned_body_wxyz": None if est is None else [float(c) for c in quat_from_R(est.R_ned_body)],
        }
        records = [
            json_record(ns_.topic(ch.PERCEPTION), ns, payload),
            (ns_.topic(ch.ANNOTATIONS), ns, self._annotations(ns, result, track)),
        ]
        if self._intrinsics != frame.intrinsics:
            self._intrinsics = frame.intrinsics
            self._calibration = b""
            self._frustum = None
        return records

    def calibration(self, frame: RgbdFrame) -> Record:
        """The camera's intrinsics (sent with every image, so a viewer that joins late has them)."""
        ns = self.ns_of(frame.stamp_s)
        i = frame.intrinsics
        msg = fm.CameraCalibration(
            timestamp=stamp(ns),
            frame_id=self.ns.frame(CAMERA),
            width=i.width_px,
            height=i.height_px,
            distortion_model="plumb_bob",
            D=[0.0] * 5,
            K=[i.fx_px, 0.0, i.cx_px, 0.0, i.fy_px, i.cy_px, 0.0, 0.0, 1.0],
            R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            P=[i.fx_px, 0.0, i.cx_px, 0.0, 0.0, i.fy_px, i.cy_px, 0.0, 0.0, 0.0, 1.0, 0.0],
        )
        return self.ns.topic(ch.CALIBRATION), ns, msg.encode()

    def image(self, frame: RgbdFrame, data: bytes, fmt: str) -> Record:
        ns = self.ns_of(frame.stamp_s)
        msg = fm.CompressedImage(timestamp=stamp(ns), frame_id=self.ns.frame(CAMERA), data=data, format=fmt)
        return self.ns.topic(ch.IMAGE), ns, msg.encode()

    def depth(self, frame: RgbdFrame, step: int = 1) -> Record:
        """Depth as a 16UC1 image in millimetres (``step`` > 1: every step-th pixel, for the live view)."""
        ns = self.ns_of(frame.stamp_s)
        mm = depth_mm(frame.depth_m, step)
        h, w = mm.shape
        msg = fm.RawImage(
            timestamp=stamp(ns),
            frame_id=self.ns.frame(CAMERA),
            width=w,
            height=h,
            encoding="16UC1",
            step=2 * w,
            data=mm.tobytes(),
        )
        return self.ns.topic(ch.DEPTH), ns, msg.encode()

    def _annotations(self, ns: int, result: DetectorResult, track: Any) -> bytes:
        ts = stamp(ns)
        meas = None if track is None else track.measurement
        points, texts = [], []
        for d in result.detections:
            tracked = meas is not None and tuple(meas.box_xyxy_px) == tuple(d.box_xyxy_px)
            x0, y0, x1, y1 = (float(c) for c in d.box_xyxy_px)
            points.append(
                fm.PointsAnnotation(
                    timestamp=ts,
                    type=fm.PointsAnnotationType.LineLoop,
                    points=[
                        fm.Point2(x=x0, y=y0),
                        fm.Point2(x=x1, y=y0),
                        fm.Point2(x=x1, y=y1),
                        fm.Point2(x=x0, y=y1),
                    ],
                    outline_color=_GREEN if tracked else _ORANGE,
                    thickness=3.0 if tracked else 1.5,
                )
            )
            label = f"{d.score:.2f}"
            if tracked and track is not None and track.estimate is not None:
                label = f"leader {d.score:.2f} {track.status.value} {float(track.estimate.range_m):.1f} m"
            texts.append(
                fm.TextAnnotation(
                    timestamp=ts,
                    position=fm.Point2(x=x0, y=max(0.0, y0 - 4.0)),
                    text=label,
                    font_size=14.0,
                    text_color=_WHITE,
                    background_color=_SHADE,
                )
            )
        if meas is None and track is not None and track.estimate is not None:
            texts.append(
                fm.TextAnnotation(
                    timestamp=ts,
                    position=fm.Point2(x=8.0, y=20.0),
                    text=f"leader {track.status.value}, no detection this frame",
                    font_size=14.0,
                    text_color=_WHITE,
                    background_color=_SHADE,
                )
            )
        return fm.ImageAnnotations(timestamp=ts, points=points, texts=texts).encode()

    # ---------------------------------------------------------------- per control step
    def step_records(self, now_s: float, inputs: MissionInputs, out: StepOutput) -> list[Record]:
        """Transforms, the 3D scene, the formation's time series, the state and the vehicle's flags."""
        ns = self.ns_of(now_s)
        v = inputs.vehicle
        est = inputs.leader
        records = [
            (self.ns.topic(ch.TF), ns, self._transforms(ns, v, est)),
            (self.ns.topic(ch.SCENE), ns, self._scene(ns, inputs, out)),
            json_record(
                self.ns.topic(ch.MISSION_STATE),
                ns,
                {
                    "stamp_s": now_s,
                    "state": out.state.value,
                    "vision_mode": None if out.vision_mode is None else str(out.vision_mode.value),
                },
            ),
            json_record(self.ns.topic(ch.FORMATION), ns, self._formation(now_s, inputs, out)),
            json_record(self.ns.topic(ch.VEHICLE), ns, vehicle_fields(now_s, v)),
        ]
        return records

    def _follower_enu(self, v: VehicleState) -> tuple[float, float, float]:
        o = self.ns.origin_ned_m
        return enu((v.p_ned_m[0] + o[0], v.p_ned_m[1] + o[1], v.p_ned_m[2] + o[2]))

    def _transforms(self, ns: int, v: VehicleState, est: Any) -> bytes:
        ts = stamp(ns)
        R = R_world_follower(R_from_euler(v.roll_rad, v.pitch_rad, v.yaw_rad))
        p = self._follower_enu(v)
        tfs = [
            fm.FrameTransform(
                timestamp=ts,
                parent_frame_id=WORLD,
                child_frame_id=self.ns.frame(FOLLOWER),
                translation=v3(*p),
                rotation=quat(R),
            ),
            fm.FrameTransform(
                timestamp=ts,
                parent_frame_id=self.ns.frame(FOLLOWER),
                child_frame_id=self.ns.frame(CAMERA),
                translation=v3(*self._t_flu_cam),
                rotation=quat(self._R_flu_cam),
            ),
        ]
        if est is not None:
            rel = enu(est.p_ned_rel_m)
            tfs.append(
                fm.FrameTransform(
                    timestamp=ts,
                    parent_frame_id=WORLD,
                    child_frame_id=self.ns.frame(LEADER),
                    translation=v3(p[0] + rel[0], p[1] + rel[1], p[2] + rel[2]),
                    rotation=fm.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0),
                )
            )
        return fm.FrameTransforms(transforms=tfs).encode()

    def _scene(self, ns: int, inputs: MissionInputs, out: StepOutput) -> bytes:
        ts = stamp(ns)
        v = inputs.vehicle
        p = self._follower_enu(v)
        pre = self.ns.prefix or "follower"
        entities = [
            fm.SceneEntity(
                timestamp=ts,
                frame_id=self.ns.frame(FOLLOWER),
                id=f"{pre}/body",
                frame_locked=True,
                cubes=[
                    fm.CubePrimitive(
                        pose=pose((0.0, 0.0, 0.0)),
                        size=v3(0.45, 0.45, 0.12),
                        color=fm.Color(r=0.2, g=0.5, b=1.0, a=0.9),
                    )
                ],
                arrows=[
                    fm.ArrowPrimitive(
                        pose=pose((0.0, 0.0, 0.0)),
                        shaft_length=0.5,
                        shaft_diameter=0.04,
                        head_length=0.15,
                        head_diameter=0.1,
                        color=fm.Color(r=0.2, g=0.5, b=1.0, a=1.0),
                    )
                ],
                texts=[
                    fm.TextPrimitive(
                        pose=pose((0.0, 0.0, 0.4)),
                        billboard=True,
                        font_size=14.0,
                        scale_invariant=True,
                        color=_WHITE,
                        text=self.ns.prefix or "follower",
                    )
                ],
            )
        ]
        frustum = self._frustum_entity(ts, pre)
        if frustum is not None:
            entities.append(frustum)
        est = inputs.leader
        deletions = []
        if est is not None:
            rel = enu(est.p_ned_rel_m)
            c = (p[0] + rel[0], p[1] + rel[1], p[2] + rel[2])
            sd = enu(tuple(math.sqrt(max(0.0, x)) for x in est.var_ned_rel_m2))  # type: ignore[arg-type]
            colour = _TRACK_COLOUR.get(est.status.value, _TENTATIVE)
            entities.append(
                fm.SceneEntity(
                    timestamp=ts,
                    frame_id=WORLD,
                    id=f"{pre}/leader",
                    spheres=[
                        # The 2-sigma ellipsoid of the estimate (axes of the NED covariance diagonal).
                        fm.SpherePrimitive(
                            pose=pose(c), size=v3(*(max(0.05, 4.0 * abs(s)) for s in sd)), color=colour
                        ),
                    ],
                    cubes=[
                        # The leader itself, the follower's size in red (the ellipsoid may be a few cm).
                        fm.CubePrimitive(
                            pose=pose(c),
                            size=v3(0.45, 0.45, 0.12),
                            color=fm.Color(r=1.0, g=0.2, b=0.2, a=1.0),
                        )
                    ],
                    texts=[
                        fm.TextPrimitive(
                            pose=pose((c[0], c[1], c[2] + 0.5)),
                            billboard=True,
                            font_size=14.0,
                            scale_invariant=True,
                            color=_WHITE,
                            text=f"leader ({est.status.value}, 2-sigma)",
                        )
                    ],
                )
            )
        else:
            deletions.append(fm.SceneEntityDeletion(timestamp=ts, id=f"{pre}/leader"))
        err = out.formation_error_ned_m
        if err is not None:
            e = enu(err)
            entities.append(
                fm.SceneEntity(
                    timestamp=ts,
                    frame_id=WORLD,
                    id=f"{pre}/slot",
                    lines=[
                        fm.LinePrimitive(
                            # Where the follower should be (its position plus the formation error): a cyan
                            # wire box a little larger than the body, seen around it when it is in its slot.
                            type=fm.LinePrimitiveLineType.LineList,
                            pose=pose((p[0] + e[0], p[1] + e[1], p[2] + e[2])),
                            thickness=2.0,
                            scale_invariant=True,
                            points=_SLOT_EDGES,
                            color=fm.Color(r=0.0, g=0.85, b=1.0, a=1.0),
                        )
                    ],
                )
            )
        else:
            deletions.append(fm.SceneEntityDeletion(timestamp=ts, id=f"{pre}/slot"))
        if inputs.neighbours:
            o = self.ns.origin_ned_m
            spheres, texts = [], []
            for n in inputs.neighbours:
                q = enu((n.p_ned_m[0] + o[0], n.p_ned_m[1] + o[1], n.p_ned_m[2] + o[2]))
                spheres.append(
                    fm.SpherePrimitive(
                        pose=pose(q), size=v3(0.5, 0.5, 0.5), color=fm.Color(r=0.8, g=0.4, b=1.0, a=0.6)
                    )
                )
                texts.append(
                    fm.TextPrimitive(
                        pose=pose((q[0], q[1], q[2] + 0.5)),
                        billboard=True,
                        font_size=12.0,
                        scale_invariant=True,
                        color=_WHITE,
                        text=f"{n.name} (shared)",
                    )
                )
            entities.append(
                fm.SceneEntity(
                    timestamp=ts, frame_id=WORLD, id=f"{pre}/neighbours", spheres=spheres, texts=texts
                )
            )
        return fm.SceneUpdate(deletions=deletions, entities=entities).encode()

    def _frustum_entity(self, ts: fm.Timestamp, pre: str) -> fm.SceneEntity | None:
        i = self._intrinsics
        if i is None:
            return None
        if self._frustum is None:
            d = FRUSTUM_RANGE_M
            corners = [
                fm.Point3(x=(u - i.cx_px) / i.fx_px * d, y=(v - i.cy_px) / i.fy_px * d, z=d)
                for u, v in ((0.0, 0.0), (i.width_px, 0.0), (i.width_px, i.height_px), (0.0, i.height_px))
            ]
            apex = fm.Point3(x=0.0, y=0.0, z=0.0)
            pts = []
            for k in range(4):
                pts += [apex, corners[k], corners[k], corners[(k + 1) % 4]]
            self._frustum = pts
        return fm.SceneEntity(
            timestamp=ts,
            frame_id=self.ns.frame(CAMERA),
            id=f"{pre}/frustum",
            frame_locked=True,
            lines=[
                fm.LinePrimitive(
                    type=fm.LinePrimitiveLineType.LineList,
                    pose=pose((0.0, 0.0, 0.0)),
                    thickness=1.5,
                    scale_invariant=True,
                    points=self._frustum,
                    color=fm.Color(r=1.0, g=1.0, b=1.0, a=0.5),
                )
            ],
        )

    def _formation(self, now_s: float, inputs: MissionInputs, out: StepOutput) -> dict[str, Any]:
        est = inputs.leader
        err = out.formation_error_ned_m
        payload: dict[str, Any] = {
            "stamp_s": now_s,
            "formation_error_ned_m": None if err is None else rounded(err),
            "formation_error_m": None if err is None else round(math.sqrt(sum(c * c for c in err)), 4),
            "leader_rel_ned_m": None if est is None else rounded(est.p_ned_rel_m),
            "leader_rel_sd_ned_m": None
            if est is None
            else rounded(math.sqrt(max(0.0, x)) for x in est.var_ned_rel_m2),
            "leader_status": "none" if est is None else est.status.value,
        }
        payload.update(setpoint_fields(out.setpoint))
        return payload

    # ---------------------------------------------------------------- per transition
    def transition_records(self, tr: Transition) -> list[Record]:
        """The transition as a log line and as the state's new value."""
        ns = self.ns_of(tr.stamp_s)
        detail = f" ({tr.detail})" if tr.detail else ""
        text = f"{tr.from_state.value} -> {tr.to_state.value}: {tr.reason.value}{detail}"
        log = fm.Log(
            timestamp=stamp(ns),
            level=_LOG_LEVEL.get(tr.severity, fm.LogLevel.Info),
            message=text,
            name=self.ns.prefix or "mission",
        )
        return [
            (self.ns.topic(ch.MISSION_LOG), ns, log.encode()),
            json_record(
                self.ns.topic(ch.MISSION_STATE),
                ns,
                {
                    "stamp_s": tr.stamp_s,
                    "state": tr.to_state.value,
                    "reason": tr.reason.name,
                    "detail": tr.detail,
                },
            ),
        ]

    def health_record(self, now_s: float, payload: dict[str, Any]) -> Record:
        return json_record(self.ns.topic(ch.HEALTH), self.ns_of(now_s), {"stamp_s": now_s, **payload})
