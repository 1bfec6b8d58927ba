"""Authenticated commands over MQTT (``<prefix>/<vehicle_id>/cmd``), off unless ``mqtt.command_topic``.

Broker credentials say who may *connect*; they do not prove who sent a message (any client with publish
rights on the topic could). So every command carries an HMAC-SHA256 over its canonical JSON with a key
shared with the ground station (``mqtt.command_key_file``), a send time and a nonce: a forged, stale or
replayed command is refused and reported on ``events``.

Message: ``{"cmd": "land" | "hold" | "set_offset", "offset_cam_m": [x, y, z] (set_offset only),
"time_unix_s": <sender's clock>, "nonce": "<unique>", "mac": "<hex HMAC of the rest>"}``.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import math
from collections import OrderedDict
from dataclasses import dataclass
from enum import Enum
from typing import Any

from companion.kernel.compat import StrEnum

#: A shorter key is guessable; 32 random bytes is what the docs tell operators to generate.
MIN_KEY_BYTES = 16
_MAX_OFFSET_M = 50.0


class CommandName(StrEnum):
    """What the ground station may ask for."""

    LAND = "land"
    HOLD = "hold"
    SET_OFFSET = "set_offset"


class RejectReason(Enum):
    """Why a command was refused (the value is what ``events`` says)."""

    MALFORMED = "not a JSON object with cmd, time_unix_s, nonce and mac"
    BAD_MAC = "authentication failed"
    EXPIRED = "time_unix_s too far from our clock"
    REPLAYED = "nonce already used"
    UNKNOWN_COMMAND = "unknown command"
    BAD_ARGUMENTS = "bad arguments"


class CommandRejectedError(Exception):
    """A command failed verification; ``reason`` says which check."""

    def __init__(self, reason: RejectReason, detail: str = "") -> None:
        self.reason = reason
        self.detail = detail
        super().__init__(reason.value + (f": {detail}" if detail else ""))


@dataclass(frozen=True, slots=True)
class Command:
    """A verified command."""

    name: CommandName
    nonce: str
    sent_unix_s: float
    #: For set_offset: the new desired leader position in the camera frame, m.
    offset_cam_m: tuple[float, float, float] | None = None


def canonical_body(message: dict[str, Any]) -> bytes:
    """The bytes the MAC covers: every field but ``mac``, sorted keys, no spaces."""
    body = {k: v for k, v in message.items() if k != "mac"}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def sign_command(key: bytes, message: dict[str, Any]) -> bytes:
    """Add the MAC to ``message`` and return the JSON to publish (what a ground station does)."""
    mac = hmac.new(key, canonical_body(message), hashlib.sha256).hexdigest()
    return json.dumps({**message, "mac": mac}).encode()


class CommandVerifier:
    """Checks MAC, age and nonce of incoming commands; remembers nonces for ``max_age_s``."""

    def __init__(self, key: bytes, max_age_s: float, max_nonces: int = 4096) -> None:
        if len(key) < MIN_KEY_BYTES:
            raise ValueError(f"command key must be at least {MIN_KEY_BYTES} bytes (got {len(key)})")
        self._key = key
        self._max_age_s = max_age_s
        self._max_nonces = max_nonces
        self._seen: OrderedDict[str, float] = OrderedDict()

    def verify(self, raw: bytes, now_unix_s: float) -> Command:
        """The verified command, or :class:`CommandRejectedError`. Pure apart from the nonce memory."""
        try:
            msg = json.loads(raw)
        except (json.JSONDecodeError, UnicodeDecodeError):
            raise CommandRejectedError(RejectReason.MALFORMED) from None
        if not isinstance(msg, dict):
            raise CommandRejectedError(RejectReason.MALFORMED)
        mac = msg.get("mac")
        sent = msg.get("time_unix_s")
        nonce = msg.get("nonce")
        if (
            not isinstance(mac, str)
            or not isinstance(nonce, str)
            or not nonce
            or len(nonce) > 128
            or isinstance(sent, bool)
            or not isinstance(sent, int | float)
            or not math.isfinite(sent)
            or "cmd" not in msg
        ):
            raise CommandRejectedError(RejectReason.MALFORMED)
        try:
            body = canonical_body(msg)
        except ValueError:
            raise CommandRejectedError(RejectReason.MALFORMED) from None
        expected = hmac.new(self._key, body, hashlib.sha256).hexdigest()
        if not hmac.compare_digest(expected, mac):
            raise CommandRejectedError(RejectReason.BAD_MAC)
        # Only an authenticated message reaches the checks below, so their answers leak nothing.
        if abs(now_unix_s - float(sent)) > self._max_age_s:
            raise CommandRejectedError(RejectReason.EXPIRED, f"{now_unix_s - float(sent):+.1f} s")
        self._forget_older_than(now_unix_s - self._max_age_s)
        if nonce in self._seen:
            raise CommandRejectedError(RejectReason.REPLAYED)
        try:
            name = CommandName(msg["cmd"])
        except ValueError:
            raise CommandRejectedError(RejectReason.UNKNOWN_COMMAND, repr(msg["cmd"])[:40]) from None
        offset = None
        if name is CommandName.SET_OFFSET:
            offset = _parse_offset(msg.get("offset_cam_m"))
        self._seen[nonce] = float(sent)
        while len(self._seen) > self._max_nonces:
            self._seen.popitem(last=False)
        return Command(name=name, nonce=nonce, sent_unix_s=float(sent), offset_cam_m=offset)

    def _forget_older_than(self, t_unix_s: float) -> None:
        for nonce, sent in list(self._seen.items()):
            if sent < t_unix_s:
                del self._seen[nonce]


def _parse_offset(value: object) -> tuple[float, float, float]:
    if (
        not isinstance(value, list)
        or len(value) != 3
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        raise CommandRejectedError(RejectReason.BAD_ARGUMENTS, "offset_cam_m must be [x, y, z] in m")
    x, y, z = (float(v) for v in value)
    if not all(math.isfinite(v) and abs(v) <= _MAX_OFFSET_M for v in (x, y, z)) or z <= 0:
        raise CommandRejectedError(
            RejectReason.BAD_ARGUMENTS, f"offset_cam_m needs |v| <= {_MAX_OFFSET_M} m and z > 0"
        )
    return (x, y, z)
