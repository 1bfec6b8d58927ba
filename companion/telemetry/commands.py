"""Authenticated commands over MQTT (``<prefix>/<vehicle_id>/cmd``), off unless ``mqtt.command_topic``.

Broker credentials say who may *connect*; they do not prove who sent a message (any client with publish
rights on the topic could). So every command is signed by an operator's key (``mqtt.command_keys_file``,
one line per operator: ``KEY_ID HEX_KEY``; delete a line to revoke that operator). The MAC covers the
topic, which names the vehicle: a command signed for one follower is refused by every other.

Replays: each operator's commands must carry send times that only go up. The newest accepted time per
key id (the high-water mark) is kept on disk (``service.state_dir``) before the command is acted upon,
so a restarted service refuses a command it has already obeyed, as MAVLink signing keeps its timestamp.
A send time more than ``command_max_age_s`` from the drone's clock is refused too.

Message: ``{"cmd": "land" | "hold" | "set_offset", "offset_cam_m": [x, y, z] (set_offset only),
"time_unix_s": <sender's clock>, "key_id": "<operator>", "nonce": "<optional, echoed in events>",
"mac": "<hex>"}``. The names are :data:`~companion.mission.types.SENT_COMMANDS`; only the message's form
is checked here: whether the mission takes the command (a slot's bounds included) it decides on its tick.
"""

from __future__ import annotations

import json
import logging
import math
import os
import tempfile
from collections.abc import Mapping
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from companion.mission.types import SENT_COMMANDS, OperatorCommand
from companion.telemetry.inbound import InboundRejectedError, Keyring, parse_object, sign

log = logging.getLogger(__name__)

#: What the MAC of a command is bound to besides its topic (a share's MAC can never pass as a command's).
COMMAND_DOMAIN = b"wingman-command-v2"


class RejectReason(Enum):
    """Why a command was refused (the value is what ``events`` says)."""

    TOO_LARGE = "larger than mqtt.max_inbound_bytes"
    MALFORMED = "not a JSON object with cmd, time_unix_s, key_id and mac"
    BAD_MAC = "authentication failed"
    EXPIRED = "time_unix_s too far from our clock"
    REPLAYED = "not newer than this operator's last command"
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

    name: OperatorCommand
    #: The operator's key id (who sent it).
    key_id: str
    sent_unix_s: float
    nonce: str = ""
    #: For set_offset: the new desired leader position in the camera frame, m.
    offset_cam_m: tuple[float, float, float] | None = None


def sign_command(key: bytes, key_id: str, topic: str, message: Mapping[str, Any]) -> bytes:
    """The JSON a ground station publishes on ``topic`` (``<prefix>/<vehicle_id>/cmd``)."""
    return sign(key, key_id, COMMAND_DOMAIN, topic, message)


class HighWaterMarks:
    """The newest accepted send time per key id (unix s), in a JSON file written atomically.

    ``path`` None keeps them in memory only (tests, or no state folder). A file that cannot be read is an
    error at start (OSError / ValueError): starting without it would accept every replay.
    """

    def __init__(self, path: Path | None) -> None:
        self.path = path
        self._marks: dict[str, float] = {}
        if path is not None and path.exists():
            data = json.loads(path.read_text())
            if not isinstance(data, dict) or not all(
                isinstance(k, str) and isinstance(v, int | float) and math.isfinite(v)
                for k, v in data.items()
            ):
                raise ValueError(f"{path}: expected an object of key id -> time_unix_s")
            self._marks = {k: float(v) for k, v in data.items()}

    def get(self, key_id: str) -> float:
        return self._marks.get(key_id, -math.inf)

    def raise_to(self, key_id: str, t_unix_s: float) -> None:
        """Move ``key_id``'s mark up to ``t_unix_s`` in memory (call :meth:`save` to keep it)."""
        self._marks[key_id] = max(self.get(key_id), t_unix_s)

    def save(self) -> None:
        """Write the marks (temporary file, fsync, rename): blocking, call it off the event loop."""
        if self.path is None:
            return
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.path.parent, prefix=".high-water-")
        try:
            with os.fdopen(fd, "w") as f:
                json.dump(self._marks, f, sort_keys=True)
                f.flush()
                os.fsync(f.fileno())
            Path(tmp).replace(self.path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise


class CommandVerifier:
    """Checks size, MAC, age and the sender's high-water mark of incoming commands.

    Args:
        keyring: the operators' keys.
        topic: the command topic this vehicle listens on (the MAC covers it).
        max_age_s: refuse a send time further than this from our clock, s.
        marks: the per-operator high-water marks (persisted by the caller after each accepted command).
        max_bytes: refuse larger payloads before parsing them.
    """

    def __init__(
        self,
        keyring: Keyring,
        topic: str,
        max_age_s: float,
        marks: HighWaterMarks | None = None,
        max_bytes: int = 4096,
    ) -> None:
        self._keyring = keyring
        self._topic = topic
        self._max_age_s = max_age_s
        self.marks = marks if marks is not None else HighWaterMarks(None)
        self._max_bytes = max_bytes

    def verify(self, raw: bytes, now_unix_s: float) -> Command:
        """The verified command, or :class:`CommandRejectedError`; raises nothing else, whatever ``raw`` is.

        An accepted command raises its sender's high-water mark in memory; persist it with
        ``marks.save()`` before acting on the command.
        """
        try:
            msg = parse_object(raw, self._max_bytes)
        except InboundRejectedError as exc:
            reason = RejectReason.TOO_LARGE if exc.reason == "too_large" else RejectReason.MALFORMED
            raise CommandRejectedError(reason, exc.detail) from None
        sent = msg.get("time_unix_s")
        if isinstance(sent, bool) or not isinstance(sent, int | float) or "cmd" not in msg:
            raise CommandRejectedError(RejectReason.MALFORMED)
        try:
            key_id = self._keyring.verify(COMMAND_DOMAIN, self._topic, msg)
        except InboundRejectedError as exc:
            reason = RejectReason.BAD_MAC if exc.reason == "bad_mac" else RejectReason.MALFORMED
            raise CommandRejectedError(reason, exc.detail) from None
        # Only an authenticated message reaches the checks below, so their answers leak nothing.
        sent_s = float(sent)
        if abs(now_unix_s - sent_s) > self._max_age_s:
            raise CommandRejectedError(RejectReason.EXPIRED, f"{now_unix_s - sent_s:+.1f} s")
        if sent_s <= self.marks.get(key_id):
            raise CommandRejectedError(RejectReason.REPLAYED, f"operator {key_id}")
        name = next((c for c in SENT_COMMANDS if c.value == msg["cmd"]), None)
        if name is None:
            raise CommandRejectedError(RejectReason.UNKNOWN_COMMAND, repr(msg["cmd"])[:40])
        offset = None
        if name.takes_offset:
            offset = _parse_offset(msg.get("offset_cam_m"))
        nonce = msg.get("nonce", "")
        self.marks.raise_to(key_id, sent_s)
        return Command(
            name=name,
            key_id=key_id,
            sent_unix_s=sent_s,
            nonce=nonce[:64] if isinstance(nonce, str) else "",
            offset_cam_m=offset,
        )


def _parse_offset(value: object) -> tuple[float, float, float]:
    """The slot's three numbers (camera frame, m); their bounds are the mission's to judge."""
    if (
        not isinstance(value, list)
        or len(value) != 3
        or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in value)
    ):
        raise CommandRejectedError(RejectReason.BAD_ARGUMENTS, "offset_cam_m must be [x, y, z] in m")
    x, y, z = (float(v) for v in value)
    return (x, y, z)
