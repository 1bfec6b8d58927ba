"""``SigningRelay``: MAVLink 2 signing between MAVSDK and the autopilot, which MAVSDK cannot do itself.

::

    autopilot <-- signed -->  relay (udpin / udpout / serial)  <-- plain, 127.0.0.1 -->  MAVSDK (udpout)

The relay opens the autopilot's link as ``link.url`` names it and a local UDP port for MAVSDK, which then
connects with ``udpout://127.0.0.1:<port>`` (:attr:`SigningRelay.mavsdk_url`). It works with any
autopilot that speaks MAVLink 2 signing on UDP or serial (PX4, the project's simulator):

- **Out** (MAVSDK to the autopilot): every frame is signed with ``link.signing_key_file``'s key and a
  timestamp that never goes backwards, across restarts too (kept in ``service.state_dir``).
- **In** (the autopilot to MAVSDK): a frame passes only with a valid signature; unsigned HEARTBEAT and
  RADIO_STATUS of *other* systems pass too (as PX4 lets them), so the leader's presence is still seen.
  Everything else is dropped and counted by reason. A frame that claims the follower's system id
  (``link.system_id``) without a valid signature is an impostor: a second vehicle with our id, or
  someone spoofing it; it is reported (rate-limited) and never reaches MAVSDK.
- **An autopilot behind**: PX4 keeps the timestamp SETUP_SIGNING gave it and starts from it at every boot;
  it moves on only by one unit per frame it sends and up to the newest signed frame it receives. Booted
  long after it was keyed, its frames are signed with our key but older than our clock (or than its own
  last ones, seen before a reboot). They are dropped like any old frame (they could be replayed), and
  not reported as an impostor: its address gets our frames, and once it has one it signs with a current
  timestamp and passes again. Without that, a relay that listens (``udpin``) would never send it
  anything and never hear it again.
- **Provisioning**: an autopilot that does not sign yet sends unsigned heartbeats. With
  ``link.signing_provision`` the relay sends it the key (SETUP_SIGNING) while those heartbeats say
  disarmed and come from one address only; PX4 refuses it while armed. Until the autopilot signs, MAVSDK
  sees nothing of it, so the service never flies an autopilot over an unsigned link.
"""

from __future__ import annotations

import asyncio
import contextlib
import hashlib
import logging
import time
from collections import Counter
from collections.abc import Callable
from pathlib import Path
from types import TracebackType
from typing import Any

from companion.config import LinkConfig
from companion.kernel.compat import Self
from companion.kernel.errors import LinkLostError
from companion.kernel.throttle import Throttle, and_more
from companion.vehicle.mavlink_signing import (
    MSG_HEARTBEAT,
    UNSIGNED_ALLOWED,
    FrameInfo,
    Signer,
    SigningClock,
    TimestampStore,
    Verdict,
    Verifier,
    crc_ok,
    heartbeat_armed,
    parse_header,
    setup_signing_frame,
    signature_matches,
    split_frames,
)
from companion.vehicle.relay_transports import Addr, Datagrams, Transport, open_autopilot

log = logging.getLogger("companion.vehicle.signing")

#: The file in ``service.state_dir`` holding the signing timestamp.
TIMESTAMP_FILE = "mavlink-signing-timestamp"
#: A peer that sent nothing valid for this long is no longer sent to, s.
PEER_TIMEOUT_S = 10.0
MAX_PEERS = 8
#: Provisioning: wait this long between SETUP_SIGNING attempts, s.
PROVISION_RETRY_S = 2.0
#: An autopilot heartbeat older than this says nothing about the armed state any more, s.
HEARTBEAT_FRESH_S = 3.0
#: The component id MAVSDK uses as a companion computer.
COMPANION_COMPONENT = 195
_AUTOPILOT_COMPONENT = 1
#: Where frames from a serial link come from (it has no address).
_SERIAL: Addr = ("serial", 0)


class SigningRelay:
    """The relay for one autopilot link. ``async with``, then run :meth:`run` as a task.

    Args:
        cfg: the ``[link]`` section (``url``, ``system_id``, ``signing_*``).
        key: the 32-byte signing key.
        state_dir: where the signing timestamp is kept across restarts.
        wall_time_s: the wall clock (signing timestamps are wall time).
    """

    def __init__(
        self,
        cfg: LinkConfig,
        key: bytes,
        state_dir: Path,
        wall_time_s: Callable[[], float] = time.time,
    ) -> None:
        self.cfg = cfg
        self.target = cfg.system_id
        self._wall_time_s = wall_time_s
        self._store = TimestampStore(state_dir / TIMESTAMP_FILE)
        try:
            floor = self._store.floor()
        except (OSError, ValueError) as exc:
            raise LinkLostError(f"signing: cannot read {self._store.path}: {exc}") from exc
        self.clock = SigningClock(floor)
        self._key = key
        self._signer = Signer(key, self.clock)
        self._verifier = Verifier(key, self.clock)
        self.counters: Counter[str] = Counter()
        self._throttle = Throttle(window_s=30.0, burst=2)
        self._autopilot: Transport | None = None
        self._local: asyncio.DatagramTransport | None = None
        self._mavsdk_addr: Addr | None = None
        self._peers: dict[Addr, float] = {}
        #: True once a frame signed by our autopilot checked out: from then on, unsigned is an impostor.
        self.autopilot_signs = False
        self._unsigned_autopilot: dict[Addr, tuple[float, bool]] = {}
        #: Where frames signed with our key but with old timestamps come from (an autopilot behind).
        self._behind: dict[Addr, float] = {}
        self._last_provision_s = -1e9
        self.provision_attempts = 0
        self.impostors: Counter[str] = Counter()
        self.local_port = 0

    # ------------------------------------------------------------------ lifecycle
    @property
    def mavsdk_url(self) -> str:
        """Where MAVSDK connects instead of the autopilot."""
        return f"udpout://127.0.0.1:{self.local_port}"

    async def __aenter__(self) -> Self:
        loop = asyncio.get_running_loop()
        self._autopilot = await open_autopilot(self.cfg.url, self._from_autopilot, self._key)
        try:
            transport, _ = await loop.create_datagram_endpoint(
                lambda: Datagrams(self._from_mavsdk), local_addr=("127.0.0.1", 0)
            )
        except OSError as exc:
            self._autopilot.close()
            raise LinkLostError(f"signing relay: cannot open a local port: {exc}") from exc
        self._local = transport
        self.local_port = int(self._local.get_extra_info("sockname")[1])
        log.info(
            "signing relay: %s (signed) <-> MAVSDK on 127.0.0.1:%d; key %s..., timestamp floor %d",
            self.cfg.url,
            self.local_port,
            self._key_id(),
            self.clock.timestamp,
        )
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._local is not None:
            self._local.close()
        if self._autopilot is not None:
            self._autopilot.close()
        with contextlib.suppress(OSError):
            await asyncio.to_thread(self._store.save, self.clock.timestamp)

    async def run(self) -> None:
        """Keep the timestamp on disk and provision the autopilot when asked to; until cancelled."""
        last_save_s = time.monotonic()
        while True:
            await asyncio.sleep(0.5)
            self._provision()
            if time.monotonic() - last_save_s >= self._store.save_every_s:
                last_save_s = time.monotonic()
                try:
                    await asyncio.to_thread(self._store.save, self.clock.timestamp)
                except OSError as exc:
                    self._report("save", f"cannot keep the signing timestamp in {self._store.path}: {exc}")

    def stats(self) -> dict[str, Any]:
        """Counters for the status endpoint."""
        return {
            "autopilot_signs": self.autopilot_signs,
            "counters": dict(self.counters),
            "impostors": dict(self.impostors),
            "provision_attempts": self.provision_attempts,
            "timestamp": self.clock.timestamp,
        }

    # ------------------------------------------------------------------ MAVSDK -> autopilot
    def _from_mavsdk(self, data: bytes, addr: Addr) -> None:
        if self._mavsdk_addr is None:
            self._mavsdk_addr = addr
        elif addr != self._mavsdk_addr:
            self.counters["local_foreign"] += 1  # another local process: not ours to sign for
            return
        frames, tail, junk = split_frames(data)
        if junk or tail:
            self.counters["out_malformed"] += 1
        now = self._wall_time_s()
        out = bytearray()
        for frame in frames:
            signed = self._signer.sign(frame, now)
            if signed is None:
                self.counters["out_unsignable"] += 1
                continue
            out += signed
        if out:
            self.counters["out_signed"] += len(frames)
            self._send_autopilot(bytes(out))

    def _send_autopilot(self, data: bytes) -> None:
        if self._autopilot is None:
            return
        now = time.monotonic()
        for addr in [a for a, seen in self._peers.items() if now - seen > PEER_TIMEOUT_S]:
            del self._peers[addr]
        dests = list(self._peers)
        for addr, (seen, _) in self._unsigned_autopilot.items():
            if now - seen < HEARTBEAT_FRESH_S and addr not in dests:
                dests.append(addr)
        for addr, seen in self._behind.items():
            if now - seen < HEARTBEAT_FRESH_S and addr not in dests:
                dests.append(addr)
        self._autopilot.send(data, dests)

    # ------------------------------------------------------------------ autopilot -> MAVSDK
    def _from_autopilot(self, data: bytes, addr: Addr | None) -> None:
        """Datagrams (``addr``) or serial bytes (``addr`` None, already cut into whole frames)."""
        frames, tail, junk = split_frames(data)
        if junk or tail:
            self.counters["in_junk_bytes"] += junk + len(tail)
        out = bytearray()
        accepted = False
        for frame in frames:
            if self._accept(frame, addr):
                out += frame
                accepted = True
        if accepted and addr is not None:
            self._peers[addr] = time.monotonic()
            if len(self._peers) > MAX_PEERS:
                del self._peers[min(self._peers, key=self._peers.__getitem__)]
        if out and self._local is not None and self._mavsdk_addr is not None:
            self._local.sendto(bytes(out), self._mavsdk_addr)

    def _accept(self, frame: bytes, addr: Addr | None) -> bool:
        info = parse_header(frame)
        if info is None or crc_ok(frame, info) is False:
            self.counters["in_malformed"] += 1
            return False
        ours = info.sys_id == self.target
        verdict = self._verifier.check(frame, info)
        if verdict is Verdict.OK:
            self.counters["in_signed"] += 1
            if ours and info.comp_id == _AUTOPILOT_COMPONENT and not self.autopilot_signs:
                self.autopilot_signs = True
                self._unsigned_autopilot.clear()
                log.info(
                    "signing relay: autopilot system %d signs with our key; its frames pass", self.target
                )
            return True
        if (
            ours
            and verdict in (Verdict.REPLAYED, Verdict.STALE_STREAM)
            and signature_matches(self._key, frame)
        ):
            return self._autopilot_behind(verdict, addr)
        if ours and not self.autopilot_signs:
            return self._before_signing(verdict, info, addr)
        if verdict is not Verdict.UNSIGNED:
            self.counters[f"in_{verdict.value}"] += 1
            if ours:
                self._impostor(verdict.value, info, addr)
            return False
        if info.msg_id in UNSIGNED_ALLOWED and not ours:
            self.counters["in_unsigned_passed"] += 1  # another system's presence (the leader's, say)
            return True
        self.counters["in_unsigned_dropped"] += 1
        if ours:
            self._impostor("unsigned", info, addr)
        return False

    def _before_signing(self, verdict: Verdict, info: FrameInfo, addr: Addr | None) -> bool:
        """Our system's frames before our autopilot has signed one: never to MAVSDK, never an impostor yet.

        Its heartbeats tell provisioning where it is and whether it is armed.
        """
        self.counters[f"in_{verdict.value}_before_signing"] += 1
        if verdict is Verdict.BAD_SIGNATURE:
            self._report(
                "other_key",
                f"system {self.target} signs with another key: nothing of it reaches the service (give it "
                "ours while disarmed, or set link.signing_key_file to its key)",
            )
        elif (
            verdict is Verdict.UNSIGNED
            and info.comp_id == _AUTOPILOT_COMPONENT
            and info.msg_id == MSG_HEARTBEAT
        ):
            where = addr if addr is not None else _SERIAL
            self._unsigned_autopilot[where] = (time.monotonic(), heartbeat_armed(info))
            self._say_not_signing()
        return False

    def _autopilot_behind(self, verdict: Verdict, addr: Addr | None) -> bool:
        """Our system's frame, signed with our key, older than its stream's last or than our clock: dropped.

        PX4 after a boot, with the timestamp it was keyed with: our frames go to where it sends from, so
        it catches up (see the module's docstring). A replayed frame of ours is dropped the same way.
        """
        self.counters["in_behind"] += 1
        where = addr if addr is not None else _SERIAL
        if where not in self._behind and len(self._behind) >= MAX_PEERS:
            del self._behind[min(self._behind, key=self._behind.__getitem__)]
        self._behind[where] = time.monotonic()
        source = "the serial link" if addr is None else f"{addr[0]}:{addr[1]}"
        self._report(
            "behind",
            f"system {self.target} signs with our key but an old timestamp ({verdict.value}, from {source}): "
            "dropped until it catches up from our frames (PX4 starts from the timestamp it was keyed with "
            "at every boot)",
        )
        return False

    def _impostor(self, why: str, info: FrameInfo, addr: Addr | None) -> None:
        where = "the serial link" if addr is None else f"{addr[0]}:{addr[1]}"
        self.impostors[where] += 1
        self._report(
            f"impostor:{where}",
            f"system {self.target} claimed by a frame that is not signed with our key ({why}, message "
            f"{info.msg_id}, component {info.comp_id}) from {where}: dropped. Another vehicle with this "
            "system id, or someone spoofing it",
        )

    def _say_not_signing(self) -> None:
        if self.cfg.signing_provision:
            return
        self._report(
            "not_signing",
            f"autopilot system {self.target} does not sign its frames: nothing of it reaches the service. "
            "Give it the key (link.signing_provision = true, while it is disarmed) or set it up yourself",
        )

    # ------------------------------------------------------------------ provisioning
    def _provision(self) -> None:
        if self.autopilot_signs or not self.cfg.signing_provision or self._autopilot is None:
            return
        now = time.monotonic()
        fresh = {
            a: armed
            for a, (seen, armed) in self._unsigned_autopilot.items()
            if now - seen < HEARTBEAT_FRESH_S
        }
        if not fresh or now - self._last_provision_s < PROVISION_RETRY_S:
            return
        if len(fresh) > 1:
            where = ", ".join(f"{a[0]}:{a[1]}" for a in fresh)
            self._report(
                "two_autopilots", f"system {self.target} heard unsigned from {where}: not sending the key"
            )
            return
        addr, armed = next(iter(fresh.items()))
        if armed:
            self._report(
                "armed",
                f"autopilot system {self.target} is armed, unsigned: the key goes only while disarmed",
            )
            return
        self._last_provision_s = now
        self.provision_attempts += 1
        frame = setup_signing_frame(
            self._key,
            self.clock.next(self._wall_time_s()),
            src=(self.target, COMPANION_COMPONENT),
            target=(self.target, _AUTOPILOT_COMPONENT),
        )
        dest = [] if addr == _SERIAL else [addr]
        self._autopilot.send(frame, dest)
        log.warning(
            "signing relay: sent the key to autopilot system %d (SETUP_SIGNING while disarmed, attempt %d)",
            self.target,
            self.provision_attempts,
        )

    # ------------------------------------------------------------------ helpers
    def _report(self, key: str, text: str) -> None:
        suppressed = self._throttle.allow(key)
        if suppressed is not None:
            log.warning("signing relay: %s%s", text, and_more(suppressed))

    def _key_id(self) -> str:
        return hashlib.sha256(self._key).hexdigest()[:8]
