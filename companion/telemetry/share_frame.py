"""MQTT's geodetic shares placed in the follower's local NED frame, as the mission takes them; pure.

The leader's position and the formation neighbours' poses arrive as latitude, longitude and altitude with a
Unix send time. The follower's own frame is PX4's local NED, whose origin is learnt from the follower's
telemetry while its GPS is good (:class:`~companion.telemetry.leader.OriginTracker`) and kept through a
loss. A share's age (our Unix time minus its send time) carries it onto the flight's clock.
"""

from __future__ import annotations

import math

from companion.kernel.flight import VehicleState
from companion.mission.types import SharedLeaderPosition, SharedNeighbour
from companion.telemetry.leader import OriginTracker, local_at
from companion.telemetry.payloads import LeaderPositionMsg, PoseMsg


class ShareFrame:
    """Places shares in the follower's local NED frame once our own fix has shown where that frame is."""

    def __init__(self) -> None:
        self._origin = OriginTracker()

    def leader(
        self, msg: LeaderPositionMsg, own: VehicleState, now_unix_s: float, now_s: float
    ) -> SharedLeaderPosition | None:
        """The leader's share in our frame (None before our first GPS fix), stamped on the flight's clock.

        ``own``: the follower's latest telemetry, which also refreshes the origin; ``now_unix_s`` and
        ``now_s``: the same instant on the Unix clock and on the flight's clock, s.
        """
        # The geodetic fix was sampled with the velocity (GLOBAL_POSITION_INT): the local position is
        # brought to that instant before the two are paired.
        p_local = local_at(own.p_ned_m, own.v_ned_m_s, own.local_position_stamp_s, own.velocity_stamp_s)
        self._origin.update(
            own.gps_fix_type, _finite(own.lat_deg), _finite(own.lon_deg), _finite(own.alt_amsl_m), p_local
        )
        origin = self._origin.origin
        if origin is None:
            return None  # no GPS fix seen yet: the frame is unknown
        age_s = max(0.0, now_unix_s - msg.time_unix_s)
        return SharedLeaderPosition(
            stamp_s=now_s - age_s,
            p_ned_m=origin.to_ned(msg.lat_deg, msg.lon_deg, msg.alt_amsl_m),
            yaw_rad=None if msg.yaw_deg is None else math.radians(msg.yaw_deg),
            v_ned_m_s=msg.v_ned_m_s,
            yaw_rate_rad_s=None if msg.yaw_rate_deg_s is None else math.radians(msg.yaw_rate_deg_s),
        )

    def neighbour(self, name: str, msg: PoseMsg, now_unix_s: float, now_s: float) -> SharedNeighbour | None:
        """Another follower's pose in our frame; None while our frame is unknown or its own is not valid."""
        origin = self._origin.origin
        if origin is None or msg.time_unix_s is None or msg.p_ned_m is None:
            return None
        if msg.lat_deg is None or msg.lon_deg is None or msg.alt_amsl_m is None:
            return None
        age_s = max(0.0, now_unix_s - msg.time_unix_s)
        p = origin.to_ned(msg.lat_deg, msg.lon_deg, msg.alt_amsl_m)
        v = msg.v_ned_m_s if msg.v_ned_m_s is not None else (0.0, 0.0, 0.0)
        return SharedNeighbour(name, now_s - age_s, p, v)


def _finite(x: float) -> float | None:
    return x if math.isfinite(x) else None
