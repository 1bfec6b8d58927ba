"""``SigningRelay``: MAVLink 2 signing between MAVSDK and the autopilot, which MAVSDK cannot do itself.

::

    autopilot <-- signed -->  relay (udpin / udpout / serial)  <-- plain, 127.0.0.1 -->  MAVSDK (udpout)

The relay opens the autopilot's link as ``link.url`` names it and a local UDP port for MAVSDK, which then
connects with ``udpout://127.0.0.1:<port>`` (:attr:`SigningRelay.mavsdk_url`). It works with any
autopilot that speaks MAVLink 2 signing on UDP or serial (PX4, the project's simulator):

- **Out** (MAVSDK to the autopilot): every frame is signed with ``link.signing_key_file``'s key and a
  timestamp that never goes backwards, across restarts too (kept in ``service.state_dir``).
- **In** (the autopilot to MAVSDK): a frame passes only with a valid signature; unsigned HEARTBEAT and
  RADIO_STATUS of *other* systems pass too (as PX4 lets them), so the leader's presence is still seen,
  once our autopilot has signed (before, they could make the service give up its link as the wrong one).
  Everything else is dropped and counted by reason. A frame that claims the follower's system id
  (``link.system_id``) without a valid signature is an impostor: a second vehicle with our id, or
  someone spoofing it; it is reported (one rate limit for all of them) and never reaches MAVSDK.
- **Trust by proof** (``udpin``): the relay sends only to addresses whose frames verified with our key,
  never to one that merely sent something (an unsigned HEARTBEAT of another system passes to MAVSDK, but
  its sender gets nothing). Once our autopilot's frames verify, the relay locks onto its address; nothing
  unverified can displace it.
- **MAVSDK's side**: the first local sender whose socket belongs to the service or its descendants (MAVSDK's
  server) is MAVSDK; a sender owned by any other process is refused and reported, before and after
  (:mod:`companion.vehicle.local_peers`), so arriving first at the relay's port gives nothing away.
- **An autopilot behind**: PX4 starts from the timestamp SETUP_SIGNING gave it at every boot and moves on
  only by one unit per frame it sends and up to the newest signed frame it receives. Its frames, signed
  with our key but old, are dropped like any old frame (they could be replayed), not reported as an
  impostor; while our autopilot is not heard current, that address gets our frames, so it catches up and
  passes again (a listening relay would otherwise never send it anything).
- **Provisioning** (``link.signing_provision``): a one-shot SETUP_SIGNING to an autopilot that sends
  unsigned, disarmed heartbeats, refused whenever in doubt (:mod:`companion.vehicle.signing_provision`).
  Until the autopilot signs, MAVSDK sees nothing of it: the service never flies over an unsigned link.
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
from companion.vehicle import local_peers
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
from companion.vehicle.relay_transports import (
    SERIAL,
    Addr,
    Datagrams,
    Transport,
    open_autopilot,
    where,
)
from companion.vehicle.signing_provision import (
    PROVISIONED_FILE,
    ProvisionScene,
    provision_refusal,
    write_marker,
)

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
#: Impostor addresses counted one by one in the status; the rest are counted together.
MAX_REPORTED_ADDRESSES = 16
#: The component id MAVSDK uses as a companion computer.
COMPANION_COMPONENT = 195
_AUTOPILOT_COMPONENT = 1
_OTHERS = "others"


class SigningRelay:
    """The relay for one autopilot link. ``async with``, then run :meth:`run` as a task.

    Args:
        cfg: the ``[link]`` section (``url``, ``system_id``, ``signing_*``).
        key: the 32-byte signing key.
        state_dir: where the signing timestamp is kept across restarts.
        wall_time_s: the wall clock (signing timestamps are wall time).
        local_sender_problem: why a local address is not MAVSDK (None: it is); reads /proc by default.
    """

    def __init__(
        self,
        cfg: LinkConfig,
        key: bytes,
        state_dir: Path,
        wall_time_s: Callable[[], float] = time.time,
        local_sender_problem: Callable[[Addr], str | None] = local_peers.sender_problem,
    ) -> None:
        self.cfg = cfg
        self.target = cfg.system_id
        self._wall_time_s = wall_time_s
        self._local_sender_problem = local_sender_problem
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
        self._mavsdk = local_peers.MavsdkSide(local_sender_problem)
        self._scheme = cfg.url.partition("://")[0]
        #: Our autopilot's address, from its last frame that verified (the one address we are locked onto).
        self._autopilot_addr: tuple[Addr, float] | None = None
        #: Other addresses whose frames verified with our key (a ground station holding it), by last seen.
        self._peers: dict[Addr, float] = {}
        #: True once a frame signed by our autopilot checked out: from then on, unsigned is an impostor.
        self.autopilot_signs = False
        #: True once any frame signed with our key arrived, from anywhere: the key is never sent then.
        self.key_seen = False
        self._unsigned_autopilot: dict[Addr, tuple[float, bool]] = {}
        #: Addresses that claimed our autopilot unsigned since the start, and when each was first heard.
        self._claimants: dict[Addr, float] = {}
        #: Where frames signed with our key but with old timestamps come from (an autopilot behind).
        self._behind: dict[Addr, float] = {}
        self._last_provision_s = -1e9
        self.provision_attempts = 0
        self._provisioned_path = state_dir / PROVISIONED_FILE
        self.provisioned = self._provisioned_path.exists()
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
            if self.autopilot_signs and self.cfg.signing_provision and not self.provisioned:
                await self._mark_provisioned()
            if time.monotonic() - last_save_s >= self._store.save_every_s:
                last_save_s = time.monotonic()
                try:
                    await asyncio.to_thread(self._store.save, self.clock.timestamp)
                except OSError as exc:
                    self._report("save", f"cannot keep the signing timestamp in {self._store.path}: {exc}")

    def stats(self) -> dict[str, Any]:
        """Counters for the status endpoint (bounded whatever arrives), and where the relay listens."""
        return {
            "autopilot_url": self.cfg.url,
            "mavsdk_port": self.local_port,
            "mavsdk_address": None if self._mavsdk.addr is None else where(self._mavsdk.addr),
            "autopilot_signs": self.autopilot_signs,
            "autopilot_address": None if self._autopilot_addr is None else where(self._autopilot_addr[0]),
            "counters": dict(self.counters),
            "impostors": dict(self.impostors),
            "provision_attempts": self.provision_attempts,
            "provisioned": self.provisioned,
            "timestamp": self.clock.timestamp,
        }

    # ------------------------------------------------------------------ MAVSDK -> autopilot
    def _from_mavsdk(self, data: bytes, addr: Addr) -> None:
        if addr != self._mavsdk.addr:
            refusal = self._mavsdk.judge(addr)
            if refusal is not None:
                self.counters[refusal[0]] += 1
                self._report(*refusal)
                return
            log.info("signing relay: MAVSDK is %s", where(addr))
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
        self._autopilot.send(data, self._destinations(time.monotonic()))

    def _destinations(self, now: float) -> list[Addr]:
        """Where our frames go on ``udpin``: proven addresses only, our autopilot's first."""
        for addr in [a for a, seen in self._peers.items() if now - seen > PEER_TIMEOUT_S]:
            del self._peers[addr]
        dests: list[Addr] = []
        locked = self._autopilot_addr is not None and now - self._autopilot_addr[1] <= PEER_TIMEOUT_S
        if self._autopilot_addr is not None and locked:
            dests.append(self._autopilot_addr[0])
        dests += [a for a in self._peers if a not in dests]
        if locked:
            return dests
        # Not (or no longer) hearing our autopilot verified: where frames signed with our key but old come
        # from (it catches up from ours), and before it ever signed, where its unsigned heartbeats come from.
        for addr, seen in self._behind.items():
            if now - seen < HEARTBEAT_FRESH_S and addr not in dests:
                dests.append(addr)
        for addr, (seen, _) in self._unsigned_autopilot.items():
            if now - seen < HEARTBEAT_FRESH_S and addr not in dests:
                dests.append(addr)
        return dests

    # ------------------------------------------------------------------ autopilot -> MAVSDK
    def _from_autopilot(self, data: bytes, addr: Addr | None) -> None:
        """Datagrams (``addr``) or serial bytes (``addr`` None, already cut into whole frames)."""
        frames, tail, junk = split_frames(data)
        if junk or tail:
            self.counters["in_junk_bytes"] += junk + len(tail)
        out = bytearray()
        for frame in frames:
            if self._accept(frame, addr):
                out += frame
        if out and self._local is not None and self._mavsdk.addr is not None:
            self._local.sendto(bytes(out), self._mavsdk.addr)

    def _accept(self, frame: bytes, addr: Addr | None) -> bool:
        info = parse_header(frame)
        if info is None or crc_ok(frame, info) is False:
            self.counters["in_malformed"] += 1
            return False
        ours = info.sys_id == self.target
        verdict = self._verifier.check(frame, info)
        if verdict is Verdict.OK:
            self.counters["in_signed"] += 1
            self._proven(addr, ours and info.comp_id == _AUTOPILOT_COMPONENT)
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
            # Another system's presence (the leader's, say): MAVSDK hears it, its sender gets nothing. Not
            # before our autopilot signed: MAVSDK hearing only others would end the service as on the
            # wrong vehicle (exit 4, not restarted), and anyone can send those heartbeats.
            if not self.autopilot_signs:
                self.counters["in_unsigned_held"] += 1
                return False
            self.counters["in_unsigned_passed"] += 1
            return True
        self.counters["in_unsigned_dropped"] += 1
        if ours:
            self._impostor("unsigned", info, addr)
        return False

    def _proven(self, addr: Addr | None, autopilot: bool) -> None:
        """A frame from ``addr`` verified with our key: it may be sent to (our autopilot's: locked onto)."""
        self.key_seen = True
        now = time.monotonic()
        if autopilot:
            if not self.autopilot_signs:
                self.autopilot_signs = True
                self._unsigned_autopilot.clear()
                log.info(
                    "signing relay: autopilot system %d signs with our key; its frames pass", self.target
                )
            if addr is not None:
                if self._autopilot_addr is not None and self._autopilot_addr[0] != addr:
                    log.info(
                        "signing relay: autopilot system %d now signs from %s (was %s)",
                        self.target,
                        where(addr),
                        where(self._autopilot_addr[0]),
                    )
                self._autopilot_addr = (addr, now)
                self._peers.pop(addr, None)
            return
        if addr is None or (self._autopilot_addr is not None and addr == self._autopilot_addr[0]):
            return
        self._peers[addr] = now
        if len(self._peers) > MAX_PEERS:
            del self._peers[min(self._peers, key=self._peers.__getitem__)]

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
            src = addr if addr is not None else SERIAL
            now = time.monotonic()
            if src in self._unsigned_autopilot or len(self._unsigned_autopilot) < MAX_PEERS:
                self._unsigned_autopilot[src] = (now, heartbeat_armed(info))
            if src not in self._claimants and len(self._claimants) < MAX_PEERS:
                self._claimants[src] = now
            self._say_not_signing()
        return False

    def _autopilot_behind(self, verdict: Verdict, addr: Addr | None) -> bool:
        """Our system's frame, signed with our key, older than its stream's last or than our clock: dropped.

        PX4 after a boot, with the timestamp it was keyed with: our frames go to where it sends from, so
        it catches up (see the module's docstring). A replayed frame of ours is dropped the same way.
        """
        self.counters["in_behind"] += 1
        self.key_seen = True
        src = addr if addr is not None else SERIAL
        if src not in self._behind and len(self._behind) >= MAX_PEERS:
            del self._behind[min(self._behind, key=self._behind.__getitem__)]
        self._behind[src] = time.monotonic()
        self._report(
            "behind",
            f"system {self.target} signs with our key but an old timestamp ({verdict.value}, from "
            f"{where(addr)}): dropped until it catches up from our frames (PX4 starts from the timestamp it "
            "was keyed with at every boot)",
        )
        return False

    def _impostor(self, why: str, info: FrameInfo, addr: Addr | None) -> None:
        source = where(addr)
        if source in self.impostors or len(self.impostors) < MAX_REPORTED_ADDRESSES:
            self.impostors[source] += 1
        else:
            self.impostors[_OTHERS] += 1
        # One rate limit for every impostor: a sender cycling its port must not flood the journal.
        self._report(
            "impostor",
            f"system {self.target} claimed by a frame that is not signed with our key ({why}, message "
            f"{info.msg_id}, component {info.comp_id}) from {source}: dropped. Another vehicle with this "
            "system id, or someone spoofing it",
        )

    def _say_not_signing(self) -> None:
        if self.cfg.signing_provision and not self.provisioned:
            return
        again = (
            f" (it was given the key before: remove {self._provisioned_path} to send it once more)"
            if self.provisioned
            else " (link.signing_provision = true, while it is disarmed)"
        )
        self._report(
            "not_signing",
            f"autopilot system {self.target} does not sign its frames: nothing of it reaches the service. "
            f"Give it the key{again} or set it up yourself",
        )

    # ------------------------------------------------------------------ provisioning
    def _provision(self) -> None:
        now = time.monotonic()
        if (
            self.autopilot_signs
            or not self.cfg.signing_provision
            or self._autopilot is None
            or self.provisioned
            or now - self._last_provision_s < PROVISION_RETRY_S
        ):
            return
        fresh = {
            a: armed
            for a, (seen, armed) in self._unsigned_autopilot.items()
            if now - seen < HEARTBEAT_FRESH_S
        }
        if not fresh:
            return
        refusal = provision_refusal(
            ProvisionScene(self.target, self._scheme, self.key_seen, self._claimants, fresh), now
        )
        if refusal is not None:
            self._report("provision", f"{refusal}: not sending the key")
            return
        addr = next(iter(fresh))
        self._last_provision_s = now
        self.provision_attempts += 1
        frame = setup_signing_frame(
            self._key,
            self.clock.next(self._wall_time_s()),
            src=(self.target, COMPANION_COMPONENT),
            target=(self.target, _AUTOPILOT_COMPONENT),
        )
        dest = [] if addr == SERIAL else [addr]
        self._autopilot.send(frame, dest)
        log.warning(
            "signing relay: sent the key to autopilot system %d at %s (SETUP_SIGNING, disarmed, attempt %d)",
            self.target,
            where(addr),
            self.provision_attempts,
        )

    async def _mark_provisioned(self) -> None:
        """The autopilot signs: provisioning is done for good (the key is never sent again)."""
        self.provisioned = True
        try:
            await asyncio.to_thread(write_marker, self._provisioned_path, self._key_id())
        except OSError as exc:
            self._report("save", f"cannot write {self._provisioned_path}: {exc}")
            return
        log.info(
            "signing relay: autopilot system %d signs with our key; provisioning is done and the key is "
            "not sent again (remove %s to allow it once more)",
            self.target,
            self._provisioned_path,
        )

    # ------------------------------------------------------------------ helpers
    def _report(self, key: str, text: str) -> None:
        suppressed = self._throttle.allow(key)
        if suppressed is not None:
            log.warning("signing relay: %s%s", text, and_more(suppressed))

    def _key_id(self) -> str:
        return hashlib.sha256(self._key).hexdigest()[:8]
