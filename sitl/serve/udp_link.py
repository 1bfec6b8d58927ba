"""One vehicle's MAVLink link on UDP, as PX4 SITL's: a default remote, plus any peer heard lately.

Besides the default remote, a link also answers any peer that sent it a valid MAVLink packet in the last
10 s (e.g. pymavlink's ``udpout:127.0.0.1:14580``); PX4 instead locks onto the first peer. Datagrams are
split into frames and parsed one by one with a fresh pymavlink parser, so a truncated or corrupt datagram
can never poison the next one; bad CRCs, unknown messages and junk are counted and dropped.
"""

from __future__ import annotations

import asyncio
import logging
import time
from collections import Counter
from typing import Any, cast

from pymavlink.dialects.v20 import common as mavlink

from sitl.world.links import MessageLink

log = logging.getLogger("sitl.serve.server")

#: A peer not heard for this long is no longer sent to, s.
PEER_TIMEOUT_S = 10.0
MAX_PEERS = 8
#: UDP payload budget per packet (below a 1500-byte MTU, as PX4's network buffer).
DATAGRAM_BYTES = 1400


class UdpLink(asyncio.DatagramProtocol):
    """One vehicle link on one UDP port: datagrams <-> :class:`MessageLink`."""

    def __init__(self, link: MessageLink, sysid: int, default_remote: tuple[str, int], label: str) -> None:
        self.link = link
        self.sysid = sysid
        self.default_remote = default_remote
        self.label = label
        self.transport: asyncio.DatagramTransport | None = None
        self._packer = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1)
        self._peers: dict[tuple[str, int], float] = {}
        self.counters: Counter[str] = Counter()
        #: The same vehicle's GCS link: what the companion says for the ground station is passed on there,
        #: as PX4 forwards its onboard link (MAV_x_FORWARD), so QGroundControl shows the service's texts.
        self.forward_to: UdpLink | None = None

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.transport = cast(asyncio.DatagramTransport, transport)

    def error_received(self, exc: Exception) -> None:
        # ICMP port unreachable when nobody listens on the remote port: normal for SITL.
        self.counters["send_errors"] += 1

    def datagram_received(self, data: bytes, addr: tuple[str | Any, int]) -> None:
        self.counters["datagrams_in"] += 1
        frames, junk = split_frames(data)
        if junk:
            self.counters["junk_bytes"] += junk
        msgs: list[Any] = []
        for frame in frames:
            parser = mavlink.MAVLink(None)
            parser.robust_parsing = True
            try:
                msgs.extend(parser.parse_buffer(frame) or [])
            except Exception:
                # Hostile input boundary: pymavlink can raise on odd bytes; never let it kill a link.
                self.counters["bad_messages"] += 1
        good = 0
        for msg in msgs:
            if isinstance(msg, mavlink.MAVLink_bad_data) or msg.get_type() in ("BAD_DATA", "UNKNOWN"):
                self.counters["bad_messages"] += 1
                continue
            src_system, src_component = msg.get_srcSystem(), msg.get_srcComponent()
            if src_system == self.sysid and src_component == 1:
                continue  # our own echo (a client relaying everything back)
            good += 1
            self.link.send(msg, src_system, src_component)
            if self.forward_to is not None and src_component != 1 and msg.get_type() in FORWARDED_TO_GCS:
                self.forward_to.send_raw(msg.get_msgbuf())
        if good:
            self.counters["messages_in"] += good
            self._peers[(str(addr[0]), int(addr[1]))] = time.monotonic()
            if len(self._peers) > MAX_PEERS:
                oldest = min(self._peers, key=self._peers.__getitem__)
                del self._peers[oldest]
        elif not msgs:
            self.counters["bad_datagrams"] += 1

    def send_raw(self, frame: bytes) -> None:
        """A frame from another system or component, passed on unchanged (MAVLink forwarding)."""
        if self.transport is None:
            return
        for addr in self.destinations():
            self.transport.sendto(frame, addr)
        self.counters["forwarded_out"] += 1

    def destinations(self) -> list[tuple[str, int]]:
        now = time.monotonic()
        for addr in [a for a, seen in self._peers.items() if now - seen > PEER_TIMEOUT_S]:
            del self._peers[addr]
        out = [self.default_remote]
        out.extend(a for a in self._peers if a != self.default_remote)
        return out

    def flush(self) -> None:
        """Pack and send everything the autopilot queued on this link."""
        msgs = self.link.receive()
        if not msgs or self.transport is None:
            return
        dests = self.destinations()
        sendto = self.transport.sendto
        # PX4 fills each UDP packet with as many MAVLink messages as fit (mavlink_main's network
        # buffer); so do we: a tenth of the syscalls, and every MAVLink parser reads them fine.
        chunk = bytearray()
        for msg in msgs:
            try:
                buf = msg.pack(self._packer)
            except Exception:
                self.counters["pack_errors"] += 1
                log.exception("%s: cannot pack %s", self.label, msg.get_type())
                continue
            if len(chunk) + len(buf) > DATAGRAM_BYTES and chunk:
                for addr in dests:
                    sendto(bytes(chunk), addr)
                chunk.clear()
            chunk += buf
            self.counters["messages_out"] += 1
        if chunk:
            for addr in dests:
                sendto(bytes(chunk), addr)


#: What a companion computer sends for the ground station, passed from a vehicle's API link to its GCS link.
FORWARDED_TO_GCS = frozenset({"STATUSTEXT", "ONBOARD_COMPUTER_STATUS"})
_MAGIC_V2 = 0xFD
_MAGIC_V1 = 0xFE


def split_frames(data: bytes) -> tuple[list[bytes], int]:
    """Cut a datagram into candidate MAVLink frames by their headers; returns (frames, junk bytes).

    Bytes before a start marker are skipped (counted as junk) and an incomplete frame at the end is
    dropped, so each frame goes to the CRC check on its own. This is much cheaper than letting
    pymavlink's robust parser resynchronise byte by byte through garbage, which matters when someone
    floods the port.
    """
    frames: list[bytes] = []
    junk = 0
    i, n = 0, len(data)
    while i < n:
        b = data[i]
        if b == _MAGIC_V2 and i + 10 <= n:
            size = 12 + data[i + 1] + (13 if data[i + 2] & 1 else 0)
        elif b == _MAGIC_V1 and i + 6 <= n:
            size = 8 + data[i + 1]
        else:
            nxt = min(
                (p for p in (data.find(b"\xfd", i + 1), data.find(b"\xfe", i + 1)) if p >= 0), default=n
            )
            junk += nxt - i
            i = nxt
            continue
        if i + size > n:
            junk += n - i
            break
        frames.append(data[i : i + size])
        i += size
    return frames, junk
