"""MAVLink 2 signing as a PX4 vehicle does it: its key, its timestamp, and what it takes unsigned.

Once a vehicle has a key (SETUP_SIGNING while disarmed, :mod:`sitl.autopilot.mavlink`), a message reaches
its autopilot only if :meth:`VehicleSigning.accept` passes it: a valid signature on a stream that moves
forward, or one of :data:`UNSIGNED_ALLOWED`. Its links (:mod:`sitl.world.links`) check each incoming
message and sign each outgoing one (:class:`SignedOutgoing`).
"""

from __future__ import annotations

import hashlib
import hmac
from collections import Counter, OrderedDict
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

#: What a signing vehicle still takes unsigned (PX4's list).
UNSIGNED_ALLOWED = frozenset({"HEARTBEAT", "RADIO_STATUS", "ADSB_VEHICLE", "COLLISION"})
#: A new signing stream may be at most this far behind the vehicle's timestamp (10 us units: one minute).
_NEW_STREAM_WINDOW = 6_000_000
_MAX_STREAMS = 256


class VehicleSigning:
    """One vehicle's MAVLink 2 signing state: its key, its timestamp, each sender's newest timestamp.

    ``mav_signing`` is pymavlink's signing state, shared by every packer of the vehicle's links so that
    all its outgoing messages are signed with one timestamp that only goes up.
    """

    def __init__(self, key: bytes, initial_timestamp: int) -> None:
        self.key = key
        self.mav_signing = mavlink.MAVLinkSigning()
        self.mav_signing.secret_key = key
        self.mav_signing.sign_outgoing = True
        self.mav_signing.timestamp = initial_timestamp
        self._streams: OrderedDict[tuple[int, int, int], int] = OrderedDict()
        self.counters: Counter[str] = Counter()

    def accept(self, msg: Any, src_system: int, src_component: int) -> bool:
        """Does ``msg`` (as received, with its wire bytes) pass? Counts why not."""
        buf = msg.get_msgbuf()
        if not buf or buf[0] != 0xFD or not buf[2] & 0x01:
            if msg.get_type() in UNSIGNED_ALLOWED:
                self.counters["unsigned_passed"] += 1
                return True
            self.counters["unsigned_dropped"] += 1
            return False
        link_id = buf[-13]
        timestamp = int.from_bytes(bytes(buf[-12:-6]), "little")
        stream = (link_id, src_system, src_component)
        last = self._streams.get(stream)
        if last is not None and timestamp <= last:
            self.counters["replayed"] += 1
            return False
        if last is None and timestamp + _NEW_STREAM_WINDOW < self.mav_signing.timestamp:
            self.counters["stale_stream"] += 1
            return False
        expected = hashlib.sha256(self.key + bytes(buf[:-6])).digest()[:6]
        if not hmac.compare_digest(expected, bytes(buf[-6:])):
            self.counters["bad_signature"] += 1
            return False
        # Only a valid signature moves the stream (pymavlink moves it first: a forgery could lock it out).
        self._streams[stream] = timestamp
        self._streams.move_to_end(stream)
        while len(self._streams) > _MAX_STREAMS:
            self._streams.popitem(last=False)
        self.mav_signing.timestamp = max(self.mav_signing.timestamp, timestamp)
        self.counters["signed"] += 1
        return True


class SignedOutgoing:
    """An outgoing message that packs signed: it hands its packer the vehicle's signing state first."""

    __slots__ = ("_msg", "_signing")

    def __init__(self, msg: Any, signing: Any) -> None:
        self._msg = msg
        self._signing = signing

    def pack(self, mav: Any, force_mavlink1: bool = False) -> bytes:
        mav.signing = self._signing
        return bytes(self._msg.pack(mav, force_mavlink1=force_mavlink1))

    def __getattr__(self, name: str) -> Any:
        return getattr(self._msg, name)
