"""Checks on what other vehicles share over MQTT: the leader's position and the neighbours' poses.

A share steers the follower (the slot turns with the leader's heading, the separation barrier holds
against neighbours, ``vision_external_position`` hands the leader's position to PX4's estimator), so it
is checked before anything uses it, and a bad one is counted and dropped:

- signed with the formation key (``mqtt.formation_keys_file``) when one is configured, the MAC bound to
  the topic (so to the sender's vehicle id), as commands are;
- finite numbers only (the parser refuses NaN and Infinity), in plausible ranges: latitude, longitude,
  altitude, a speed below ``share_max_speed_m_s``;
- a time that is neither older than ``share_max_age_s`` nor ahead of our clock by more than
  ``share_max_ahead_s``, and newer than the sender's last accepted share (kept for good, however long
  the sender was silent);
- no jump: the distance from the sender's last accepted position fits ``share_max_speed_m_s`` over the
  time that really passed (the share times' difference, at most our clock's since that share arrived
  plus ``share_max_ahead_s``), plus ``JUMP_SLACK_M`` for GPS noise.
"""

from __future__ import annotations

import math
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, TypeVar

from pydantic import ValidationError

from companion.telemetry.inbound import InboundRejectedError, Keyring, parse_object, sign
from companion.telemetry.leader import GeoOrigin
from companion.telemetry.payloads import LeaderPositionMsg, PoseMsg

T = TypeVar("T")

#: What a share's MAC is bound to besides its topic.
SHARE_DOMAIN = b"wingman-share-v1"
#: GPS noise allowed between two shares on top of the speed bound, m.
JUMP_SLACK_M = 5.0
#: A local NED position further than this from the EKF origin is not plausible for a formation, m.
_MAX_NED_M = 100_000.0
_SIGNATURE_FIELDS = ("mac", "key_id")
#: Senders (topics) whose last share is remembered; the longest silent is forgotten beyond this.
MAX_SENDERS = 256


@dataclass(frozen=True, slots=True)
class ShareLimits:
    """Bounds on a share (``[mqtt]``: ``max_inbound_bytes``, ``share_max_*``)."""

    max_bytes: int = 4096
    max_age_s: float = 2.0
    max_ahead_s: float = 0.5
    max_speed_m_s: float = 30.0


@dataclass(frozen=True, slots=True)
class _Last:
    t_unix_s: float
    received_unix_s: float
    geo: tuple[float, float, float] | None


def sign_share(keyring: Keyring, topic: str, message: dict[str, Any]) -> bytes:
    """The JSON to publish a share on ``topic``, signed with the keyring's first key."""
    return sign(keyring.signing_key, keyring.signing_id, SHARE_DOMAIN, topic, message)


class ShareGate:
    """Verifies and checks shares; remembers each sender's last accepted one (by topic).

    Raises :class:`~companion.telemetry.inbound.InboundRejectedError` for a share that must not be used;
    ``accepted`` and ``rejected`` count them (rejected by reason).
    """

    def __init__(
        self,
        limits: ShareLimits,
        wall_time_s: Callable[[], float],
        keyring: Keyring | None = None,
    ) -> None:
        self.limits = limits
        self._wall_time_s = wall_time_s
        self.keyring = keyring
        self._last: OrderedDict[str, _Last] = OrderedDict()
        self.accepted = 0
        self.rejected: Counter[str] = Counter()

    def leader_position(self, topic: str, raw: bytes) -> LeaderPositionMsg:
        """The leader's position from ``raw`` on ``topic``, checked."""
        return self._count(lambda: self._leader(topic, raw))

    def neighbour_pose(self, topic: str, raw: bytes) -> PoseMsg:
        """A neighbour's pose from ``raw`` on ``topic``, checked."""
        return self._count(lambda: self._neighbour(topic, raw))

    def _count(self, check: Callable[[], T]) -> T:
        try:
            out = check()
        except InboundRejectedError as exc:
            self.rejected[exc.reason] += 1
            raise
        self.accepted += 1
        return out

    def _authentic(self, topic: str, raw: bytes) -> dict[str, Any]:
        obj = parse_object(raw, self.limits.max_bytes)
        if self.keyring is not None:
            self.keyring.verify(SHARE_DOMAIN, topic, obj)
        for field in _SIGNATURE_FIELDS:
            obj.pop(field, None)
        return obj

    def _leader(self, topic: str, raw: bytes) -> LeaderPositionMsg:
        obj = self._authentic(topic, raw)
        try:
            msg = LeaderPositionMsg.model_validate(obj)
        except ValidationError as exc:
            raise InboundRejectedError("malformed", _first_error(exc)) from None
        self._check_speed(msg.v_ned_m_s)
        self._check_time_and_jump(topic, msg.time_unix_s, (msg.lat_deg, msg.lon_deg, msg.alt_amsl_m))
        return msg

    def _neighbour(self, topic: str, raw: bytes) -> PoseMsg:
        obj = self._authentic(topic, raw)
        try:
            msg = PoseMsg.model_validate(obj)
        except ValidationError as exc:
            raise InboundRejectedError("malformed", _first_error(exc)) from None
        if msg.time_unix_s is None:
            raise InboundRejectedError("malformed", "no time_unix_s")
        if msg.p_ned_m is not None and max(abs(c) for c in msg.p_ned_m) > _MAX_NED_M:
            raise InboundRejectedError("implausible", "p_ned_m out of range")
        self._check_speed(msg.v_ned_m_s)
        geo = None
        if msg.lat_deg is not None and msg.lon_deg is not None and msg.alt_amsl_m is not None:
            geo = (msg.lat_deg, msg.lon_deg, msg.alt_amsl_m)
            _check_geo(geo)
        self._check_time_and_jump(topic, msg.time_unix_s, geo)
        return msg

    def _check_speed(self, v_ned_m_s: tuple[float, float, float] | None) -> None:
        if v_ned_m_s is not None and math.hypot(*v_ned_m_s) > self.limits.max_speed_m_s:
            raise InboundRejectedError("implausible", f"speed above {self.limits.max_speed_m_s:g} m/s")

    def _check_time_and_jump(
        self, topic: str, t_unix_s: float, geo: tuple[float, float, float] | None
    ) -> None:
        now = self._wall_time_s()
        lim = self.limits
        if t_unix_s > now + lim.max_ahead_s:
            raise InboundRejectedError("future", f"{t_unix_s - now:.1f} s ahead of our clock")
        if t_unix_s < now - lim.max_age_s:
            raise InboundRejectedError("stale", f"{now - t_unix_s:.1f} s old")
        last = self._last.get(topic)
        if last is not None:
            # Kept for good, not forgotten after max_age_s: a sender silent for a while must not be open to
            # a forged jump (nor to its own old shares replayed).
            if t_unix_s <= last.t_unix_s:
                raise InboundRejectedError("replayed", "not newer than the sender's last share")
            if geo is not None and last.geo is not None:
                # The time that really passed bounds the move: a share stamped ahead gains nothing.
                elapsed_s = min(t_unix_s - last.t_unix_s, now - last.received_unix_s + lim.max_ahead_s)
                n, e, d = GeoOrigin(*last.geo).to_ned(*geo)
                jump_m = math.sqrt(n * n + e * e + d * d)
                if jump_m > lim.max_speed_m_s * max(elapsed_s, 0.0) + JUMP_SLACK_M:
                    raise InboundRejectedError("jump", f"{jump_m:.0f} m in {elapsed_s:.2f} s")
        self._last[topic] = _Last(t_unix_s, now, geo)
        self._last.move_to_end(topic)
        while len(self._last) > MAX_SENDERS:
            self._last.popitem(last=False)


def _check_geo(geo: tuple[float, float, float]) -> None:
    lat, lon, alt = geo
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and -500.0 <= alt <= 10_000.0):
        raise InboundRejectedError("implausible", "latitude, longitude or altitude out of range")


def _first_error(exc: ValidationError) -> str:
    err = exc.errors()[0]
    where = ".".join(str(p) for p in err.get("loc", ()))
    return f"{where}: {err.get('msg', '')}"[:80]
