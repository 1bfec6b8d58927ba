"""MAVLink 2 message signing on raw frames: sign, verify, and the timestamp both ends keep.

Pure (bytes in, bytes out); :mod:`companion.vehicle.signing_relay` puts it on the wire. The scheme is
MAVLink 2's own: a signed frame sets bit 0 of ``incompat_flags`` (so its CRC changes) and appends 13 bytes:
``link_id`` (1), a 48-bit timestamp in 10 us units since 2015-01-01 UTC (6), and the first 6 bytes of
SHA-256(key + everything before them). A receiver keeps the newest timestamp per stream
(link id, system, component) and refuses anything not newer (replay), and a new stream more than a minute
behind its own timestamp.

Two things are stricter here than in pymavlink: a stream's timestamp moves only after its signature
checked out (a forged frame cannot push a real sender's stream into the future and lock it out), and the
stream table is bounded (a flood of made-up senders cannot grow memory).
"""

from __future__ import annotations

import hashlib
import hmac
import math
import os
import tempfile
from collections import OrderedDict
from dataclasses import dataclass
from enum import Enum
from pathlib import Path

from pymavlink.dialects.v20 import common as mavlink

from companion.kernel.secret_files import read_secret

MAGIC_V2 = 0xFD
MAGIC_V1 = 0xFE
IFLAG_SIGNED = 0x01
SIGNATURE_BYTES = 13
HEADER_V2_BYTES = 10
HEADER_V1_BYTES = 6
KEY_BYTES = 32
#: The MAVLink signing epoch, 2015-01-01T00:00:00Z, in Unix seconds.
EPOCH_UNIX_S = 1_420_070_400
#: Timestamp units per second (10 us).
UNITS_PER_S = 100_000
#: A new stream may be at most this far behind our timestamp (MAVLink's rule: one minute), units.
NEW_STREAM_WINDOW = 60 * UNITS_PER_S
MAX_STREAMS = 256

MSG_HEARTBEAT = 0
MSG_RADIO_STATUS = 109
MSG_SETUP_SIGNING = 256
#: What passes unsigned (as PX4 lets it): presence and radio link quality, nothing that commands.
UNSIGNED_ALLOWED = frozenset({MSG_HEARTBEAT, MSG_RADIO_STATUS})


def _crc_table() -> tuple[int, ...]:
    table = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
        table.append(crc)
    return tuple(table)


_CRC_TABLE = _crc_table()


def x25_crc(data: bytes | bytearray, crc: int = 0xFFFF) -> int:
    """MAVLink's CRC-16/MCRF4XX (X.25) over ``data``, continuing from ``crc``."""
    table = _CRC_TABLE
    for b in data:
        crc = (crc >> 8) ^ table[(crc ^ b) & 0xFF]
    return crc


_CRC_EXTRA: dict[int, int] = {msg_id: cls.crc_extra for msg_id, cls in mavlink.mavlink_map.items()}


@dataclass(frozen=True, slots=True)
class FrameInfo:
    """A frame's header fields."""

    version: int
    signed: bool
    seq: int
    sys_id: int
    comp_id: int
    msg_id: int
    payload: bytes


def frame_size(buf: bytes | bytearray, i: int = 0) -> int | None:
    """The length of the frame starting at ``buf[i]`` from its header; None when no header is there yet."""
    n = len(buf) - i
    if n < 3:
        return None
    if buf[i] == MAGIC_V2:
        return HEADER_V2_BYTES + buf[i + 1] + 2 + (SIGNATURE_BYTES if buf[i + 2] & IFLAG_SIGNED else 0)
    if buf[i] == MAGIC_V1:
        return HEADER_V1_BYTES + buf[i + 1] + 2
    return None


def parse_header(frame: bytes) -> FrameInfo | None:
    """The header of one complete frame; None when its length does not match its header."""
    if frame_size(frame) != len(frame):
        return None
    if frame[0] == MAGIC_V2:
        n = frame[1]
        return FrameInfo(
            version=2,
            signed=bool(frame[2] & IFLAG_SIGNED),
            seq=frame[4],
            sys_id=frame[5],
            comp_id=frame[6],
            msg_id=int.from_bytes(frame[7:10], "little"),
            payload=frame[HEADER_V2_BYTES : HEADER_V2_BYTES + n],
        )
    n = frame[1]
    return FrameInfo(
        1, False, frame[2], frame[3], frame[4], frame[5], frame[HEADER_V1_BYTES : HEADER_V1_BYTES + n]
    )


def crc_ok(frame: bytes, info: FrameInfo) -> bool | None:
    """Does the frame's CRC match? None when the message id is unknown here (no CRC_EXTRA to check with)."""
    extra = _CRC_EXTRA.get(info.msg_id)
    if extra is None:
        return None
    header = HEADER_V2_BYTES if info.version == 2 else HEADER_V1_BYTES
    end = header + len(info.payload)
    crc = x25_crc(bytes((extra,)), x25_crc(frame[1:end]))
    return crc == int.from_bytes(frame[end : end + 2], "little")


def split_frames(data: bytes | bytearray) -> tuple[list[bytes], bytes, int]:
    """Cut bytes into frames by their headers: (complete frames, the incomplete tail, junk bytes skipped).

    Bytes before a start marker are skipped. A datagram's tail is junk; a serial stream keeps it for the
    next read. A length byte can lie (noise that looks like a start marker): callers check each frame's
    CRC or signature and, on a stream, resynchronise one byte further when it fails.
    """
    frames: list[bytes] = []
    junk = 0
    i, n = 0, len(data)
    while i < n:
        if data[i] not in (MAGIC_V2, MAGIC_V1):
            nxt = min(
                (p for p in (data.find(b"\xfd", i + 1), data.find(b"\xfe", i + 1)) if p >= 0), default=n
            )
            junk += nxt - i
            i = nxt
            continue
        size = frame_size(data, i)
        if size is None or i + size > n:
            return frames, bytes(data[i:]), junk
        frames.append(bytes(data[i : i + size]))
        i += size
    return frames, b"", junk


def take_stream_frames(buf: bytes | bytearray, key: bytes | None = None) -> tuple[list[bytes], bytes]:
    """Whole frames from the front of a byte stream (a serial link), and what must wait for more bytes.

    A start marker in noise can carry a length that swallows real frames: a frame whose CRC fails is not
    taken, and the search goes on one byte after its start marker. A message this dialect does not know
    has no CRC to check here: it is taken only when it is signed with ``key``.
    """
    frames: list[bytes] = []
    i, n = 0, len(buf)
    while i < n:
        if buf[i] not in (MAGIC_V2, MAGIC_V1):
            i += 1
            continue
        size = frame_size(buf, i)
        if size is None or i + size > n:
            break
        frame = bytes(buf[i : i + size])
        info = parse_header(frame)
        ok = None if info is None else crc_ok(frame, info)
        if ok is None and info is not None and key is not None:
            ok = info.signed and signature_matches(key, frame)
        if not ok:
            i += 1
            continue
        frames.append(frame)
        i += size
    return frames, bytes(buf[i:])


def signature_matches(key: bytes, frame: bytes) -> bool:
    """Is a signed frame's signature the one ``key`` gives (timestamps not considered)?"""
    expected = hashlib.sha256(key + frame[:-6]).digest()[:6]
    return hmac.compare_digest(expected, frame[-6:])


def load_key(path: str | os.PathLike[str]) -> bytes:
    """The 32-byte signing key from a file of 32 raw bytes or 64 hex digits (mode 0600; see read_secret)."""
    data = read_secret(path)
    if len(data) == KEY_BYTES:
        return data
    text = data.strip()
    if len(text) == 2 * KEY_BYTES:
        try:
            return bytes.fromhex(text.decode("ascii"))
        except (UnicodeDecodeError, ValueError):
            pass
    raise ValueError(f"{path}: expected 32 raw bytes or 64 hexadecimal digits (got {len(data)} bytes)")


def unix_to_units(t_unix_s: float) -> int:
    """A Unix time as a MAVLink signing timestamp (10 us since 2015-01-01); 0 before the epoch."""
    return max(0, math.floor((t_unix_s - EPOCH_UNIX_S) * UNITS_PER_S))


class SigningClock:
    """This end's signing timestamp: wall clock, never backwards, never below what was seen or stored.

    ``floor`` is where a restart must start (the stored timestamp plus how long it may have been stale);
    every frame we sign takes the next value, and every valid frame we receive lifts us to its timestamp.
    """

    def __init__(self, floor: int = 0) -> None:
        self.timestamp = floor

    def next(self, now_unix_s: float) -> int:
        """The timestamp for the next frame we sign."""
        self.timestamp = max(self.timestamp + 1, unix_to_units(now_unix_s))
        return self.timestamp

    def observe(self, timestamp: int) -> None:
        self.timestamp = max(self.timestamp, timestamp)


class Signer:
    """Signs unsigned MAVLink 2 frames with one key and link id."""

    def __init__(self, key: bytes, clock: SigningClock, link_id: int = 0) -> None:
        if len(key) != KEY_BYTES:
            raise ValueError(f"a signing key has {KEY_BYTES} bytes")
        self._key = key
        self.clock = clock
        self.link_id = link_id
        self._extra_guess: dict[int, int] = {}

    def sign(self, frame: bytes, now_unix_s: float) -> bytes | None:
        """``frame`` signed; None for what cannot be signed (MAVLink 1, already signed, broken)."""
        info = parse_header(frame)
        if info is None or info.version != 2 or info.signed:
            return None
        extra = _CRC_EXTRA.get(info.msg_id)
        end = HEADER_V2_BYTES + len(info.payload)
        if extra is None:
            extra = self._guess_extra(frame, info.msg_id, end)
            if extra is None:
                return None
        out = bytearray(frame[:end])
        out[2] |= IFLAG_SIGNED
        crc = x25_crc(bytes((extra,)), x25_crc(out[1:end]))
        out += crc.to_bytes(2, "little")
        out.append(self.link_id)
        out += self.clock.next(now_unix_s).to_bytes(6, "little")
        out += hashlib.sha256(self._key + out).digest()[:6]
        return bytes(out)

    def _guess_extra(self, frame: bytes, msg_id: int, end: int) -> int | None:
        """The CRC_EXTRA of a message this dialect does not know, recovered from the frame's own CRC."""
        if msg_id in self._extra_guess:
            return self._extra_guess[msg_id]
        partial = x25_crc(frame[1:end])
        want = int.from_bytes(frame[end : end + 2], "little")
        for extra in range(256):
            if x25_crc(bytes((extra,)), partial) == want:
                if len(self._extra_guess) < MAX_STREAMS:
                    self._extra_guess[msg_id] = extra
                return extra
        return None


class Verdict(Enum):
    """What a received frame's signature says (the value is the counter's name)."""

    OK = "signed"
    UNSIGNED = "unsigned"
    BAD_SIGNATURE = "bad_signature"
    REPLAYED = "replayed"
    STALE_STREAM = "stale_stream"


class Verifier:
    """Checks signed frames against one key, keeping each stream's newest timestamp."""

    def __init__(self, key: bytes, clock: SigningClock) -> None:
        if len(key) != KEY_BYTES:
            raise ValueError(f"a signing key has {KEY_BYTES} bytes")
        self._key = key
        self.clock = clock
        self._streams: OrderedDict[tuple[int, int, int], int] = OrderedDict()

    def check(self, frame: bytes, info: FrameInfo) -> Verdict:
        """The verdict on one complete frame (``info`` from :func:`parse_header`)."""
        if not info.signed:
            return Verdict.UNSIGNED
        link_id = frame[-SIGNATURE_BYTES]
        timestamp = int.from_bytes(frame[-12:-6], "little")
        stream = (link_id, info.sys_id, info.comp_id)
        last = self._streams.get(stream)
        if last is not None and timestamp <= last:
            return Verdict.REPLAYED
        if last is None and timestamp + NEW_STREAM_WINDOW < self.clock.timestamp:
            return Verdict.STALE_STREAM
        if not signature_matches(self._key, frame):
            return Verdict.BAD_SIGNATURE
        self._streams[stream] = timestamp
        self._streams.move_to_end(stream)
        while len(self._streams) > MAX_STREAMS:
            self._streams.popitem(last=False)
        self.clock.observe(timestamp)
        return Verdict.OK


class TimestampStore:
    """The signing timestamp on disk (``<state_dir>/mavlink-signing-timestamp``), as PX4 keeps its own.

    Saved now and then, so on a restart it may be up to one save interval old: :meth:`floor` adds that.
    """

    def __init__(self, path: Path, save_every_s: float = 10.0) -> None:
        self.path = path
        self.save_every_s = save_every_s

    def floor(self) -> int:
        """Where a restarted clock starts; 0 when nothing was stored (ValueError when it is corrupt)."""
        try:
            text = self.path.read_text().strip()
        except FileNotFoundError:
            return 0
        stored = int(text)
        if stored < 0:
            raise ValueError(f"{self.path}: negative timestamp")
        return stored + math.ceil(self.save_every_s * UNITS_PER_S)

    def save(self, timestamp: int) -> None:
        """Write it atomically (blocking: call off the event loop)."""
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=self.path.parent, prefix=".signing-")
        try:
            with os.fdopen(fd, "w") as f:
                f.write(f"{timestamp}\n")
                f.flush()
                os.fsync(f.fileno())
            Path(tmp).replace(self.path)
        except BaseException:
            Path(tmp).unlink(missing_ok=True)
            raise


def setup_signing_frame(
    key: bytes, initial_timestamp: int, src: tuple[int, int], target: tuple[int, int]
) -> bytes:
    """An unsigned SETUP_SIGNING frame giving ``target`` (system, component) our key.

    Unsigned on purpose: an autopilot without a key accepts it either way, and PX4 checks a signed one
    against the key it may already hold.
    """
    packer = mavlink.MAVLink(None, srcSystem=src[0], srcComponent=src[1])
    msg = mavlink.MAVLink_setup_signing_message(target[0], target[1], list(key), initial_timestamp)
    return bytes(msg.pack(packer))


def heartbeat_armed(info: FrameInfo) -> bool:
    """Does a HEARTBEAT's base_mode say armed (MAV_MODE_FLAG_SAFETY_ARMED)?"""
    payload = info.payload.ljust(9, b"\x00")  # MAVLink 2 trims trailing zero bytes
    return bool(payload[6] & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
