"""MQTT payloads (JSON) and every topic name, in one place.

Topics live under ``<prefix>/<vehicle_id>/``:

- ``state``  (retained, QoS 1): mission state and reason, link, GPS; the last will sets ``online: false``.
- ``pose``   (QoS 0): own position and the leader estimate with its covariance.
- ``health`` (QoS 0): components, machine load, per-stage latency, dropped frames, MQTT buffer.
- ``events`` (QoS 1): state changes, command results, warnings; one message per event.
- ``cmd``    (subscribed only when ``mqtt.command_topic`` is on): authenticated commands.

Every message carries ``schema_version``, ``vehicle_id``, a per-topic ``seq`` (gaps = lost messages),
``time_unix_s`` (wall clock, for the ground station) and ``uptime_s``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

PAYLOAD_SCHEMA_VERSION = 1

Vec3 = tuple[float, float, float]
Severity = Literal["debug", "info", "notice", "warning", "error", "critical", "emergency"]


@dataclass(frozen=True, slots=True)
class Topics:
    """Topic names for one vehicle."""

    prefix: str
    vehicle_id: str

    def _t(self, leaf: str) -> str:
        return f"{self.prefix}/{self.vehicle_id}/{leaf}"

    @property
    def state(self) -> str:
        return self._t("state")

    @property
    def pose(self) -> str:
        return self._t("pose")

    @property
    def health(self) -> str:
        return self._t("health")

    @property
    def events(self) -> str:
        return self._t("events")

    @property
    def cmd(self) -> str:
        return self._t("cmd")


class Payload(BaseModel):
    """Envelope shared by every outgoing message (the reporter fills it in)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    schema_version: int = PAYLOAD_SCHEMA_VERSION
    vehicle_id: str = ""
    seq: int | None = None
    time_unix_s: float | None = None
    uptime_s: float | None = None

    def to_json_bytes(self) -> bytes:
        return self.model_dump_json().encode()


class StateMsg(Payload):
    """``state``: what the service is doing and why."""

    online: bool = True
    state: str = "STARTING"
    reason: str = ""
    #: Seconds spent in the current state.
    state_age_s: float | None = None
    link_ok: bool = False
    armed: bool | None = None
    in_air: bool | None = None
    flight_mode: str | None = None
    gps_fix_type: int | None = None
    gps_ok: bool | None = None
    leader_tracked: bool | None = None


class LeaderMsg(BaseModel):
    """The leader estimate relative to the follower (NED axes, m), with its 3x3 covariance (m^2)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    status: str
    p_rel_ned_m: Vec3
    v_rel_ned_m_s: Vec3 | None = None
    cov_ned_m2: tuple[Vec3, Vec3, Vec3] | None = None
    age_s: float | None = None
    range_m: float | None = None


class PoseMsg(Payload):
    """``pose``: own position and velocity in local NED, and the leader estimate."""

    p_ned_m: Vec3 | None = None
    v_ned_m_s: Vec3 | None = None
    yaw_deg: float | None = None
    lat_deg: float | None = None
    lon_deg: float | None = None
    alt_amsl_m: float | None = None
    leader: LeaderMsg | None = None


class HealthMsg(Payload):
    """``health``: components, machine, per-stage latency and drop counters."""

    healthy: bool = False
    components: list[dict[str, Any]] = Field(default_factory=list)
    system: dict[str, Any] = Field(default_factory=dict)
    latency_ms: dict[str, dict[str, float | int]] = Field(default_factory=dict)
    frames: dict[str, int] = Field(default_factory=dict)
    mqtt: dict[str, Any] = Field(default_factory=dict)


class EventMsg(Payload):
    """``events``: one thing that happened."""

    kind: str
    severity: Severity = "info"
    text: str
    data: dict[str, Any] = Field(default_factory=dict)


def offline_state(vehicle_id: str, reason: str) -> StateMsg:
    """The retained ``state`` that says the service is gone (last will, or a clean stop)."""
    return StateMsg(vehicle_id=vehicle_id, online=False, state="OFFLINE", reason=reason)


class LeaderPositionMsg(BaseModel):
    """The leader's own position, shared over MQTT (``mqtt.leader_topic``) for the external-position fallback.

    Geodetic so that leader and follower need not share a home; ``time_unix_s`` is the leader's fix time.
    """

    model_config = ConfigDict(frozen=True, extra="ignore")

    lat_deg: float = Field(ge=-90.0, le=90.0)
    lon_deg: float = Field(ge=-180.0, le=180.0)
    alt_amsl_m: float = Field(ge=-500.0, le=10000.0)
    v_ned_m_s: Vec3 | None = None
    time_unix_s: float
    #: The leader's heading and yaw rate (formations: the plan's slots turn with it), deg and deg/s.
    yaw_deg: float | None = Field(None, ge=-360.0, le=360.0)
    yaw_rate_deg_s: float | None = Field(None, ge=-720.0, le=720.0)
