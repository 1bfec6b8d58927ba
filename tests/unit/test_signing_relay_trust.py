"""The signing relay against someone on the drone's network or the board: whom it sends to, whom it signs for.

Driven through its frame handlers with a recording transport and a stopped monotonic clock (the relay's
``time``); the local senders are real sockets, judged by who owns them (``companion.vehicle.local_peers``).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import secrets
import subprocess
import time
from pathlib import Path
from typing import Any

import pytest

from companion.vehicle import local_peers, signing_relay
from companion.vehicle.mavlink_signing import unix_to_units
from companion.vehicle.signing_provision import PROVISION_LISTEN_S, PROVISIONED_FILE
from companion.vehicle.signing_relay import SigningRelay
from tests.relay_attack_probe import (
    FOLLOWER,
    PX4,
    RACER,
    FakeMonotonic,
    Recorder,
    bind_mavsdk,
    command_long,
    heartbeat,
    local_socket,
    packer,
    relay,
    sent,
)

KEY = secrets.token_bytes(32)
SPOOF = ("10.0.0.66", 4444)


@pytest.fixture
def clock(monkeypatch: pytest.MonkeyPatch) -> FakeMonotonic:
    fake = FakeMonotonic()
    monkeypatch.setattr(signing_relay, "time", fake)
    return fake


def setups(r: SigningRelay) -> list[list[tuple[str, int]]]:
    return [dests for data, dests in sent(r) if data[7:10] == (256).to_bytes(3, "little")]


def test_unsigned_heartbeats_from_many_ports_never_displace_the_verified_autopilot(tmp_path: Path) -> None:
    r = relay(KEY, tmp_path, "udpin://0.0.0.0:14540")
    mav = local_socket()
    bind_mavsdk(r, mav)
    r._from_autopilot(heartbeat(packer(FOLLOWER, 1, KEY)), PX4)
    attacker = packer(99, 1)
    for i in range(10_000):
        r._from_autopilot(heartbeat(attacker), ("10.0.0.66", 40_000 + i % 1000))
    r._from_mavsdk(command_long(packer(FOLLOWER, 195)), mav.getsockname())
    mav.close()
    assert sent(r)[-1][1] == [PX4]
    assert r.counters["in_unsigned_passed"] == 10_000  # the other system's presence still reaches MAVSDK


def test_an_address_is_sent_to_only_once_a_frame_from_it_verified(
    tmp_path: Path, clock: FakeMonotonic
) -> None:
    r = relay(KEY, tmp_path, "udpin://0.0.0.0:14540")
    mav = local_socket()
    bind_mavsdk(r, mav)
    r._from_autopilot(heartbeat(packer(99, 1)), SPOOF)  # another system, unsigned: passes, proves nothing
    r._from_mavsdk(command_long(packer(FOLLOWER, 195)), mav.getsockname())
    assert sent(r)[-1][1] == []
    ground = ("10.0.0.9", 14550)  # a ground station that holds our key
    r._from_autopilot(heartbeat(packer(255, 190, KEY)), ground)
    r._from_autopilot(heartbeat(packer(FOLLOWER, 1, KEY)), PX4)
    r._from_mavsdk(command_long(packer(FOLLOWER, 195)), mav.getsockname())
    assert sent(r)[-1][1] == [PX4, ground]
    # Our autopilot moves only by proof: a verified frame from its new address.
    moved = ("10.0.0.2", 14999)
    r._from_autopilot(heartbeat(packer(FOLLOWER, 1, KEY)), moved)
    r._from_mavsdk(command_long(packer(FOLLOWER, 195)), mav.getsockname())
    mav.close()
    assert sent(r)[-1][1][0] == moved
    assert PX4 not in sent(r)[-1][1]


def test_impostors_cycling_ports_give_two_log_lines_and_a_bounded_status(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    r = relay(KEY, tmp_path, "udpin://0.0.0.0:14540")
    r._from_autopilot(heartbeat(packer(FOLLOWER, 1, KEY)), PX4)
    spoof = packer(FOLLOWER, 1)
    with caplog.at_level(logging.WARNING, logger="companion.vehicle.signing"):
        for i in range(10_000):
            r._from_autopilot(heartbeat(spoof), ("10.0.0.66", 30_000 + i))
    lines = [rec for rec in caplog.records if "claimed by a frame" in rec.getMessage()]
    assert len(lines) == 2
    assert sum(r.impostors.values()) == 10_000
    assert len(r.impostors) == signing_relay.MAX_REPORTED_ADDRESSES + 1
    assert len(json.dumps(r.stats())) < 2000


def test_the_key_never_goes_while_a_frame_signed_with_it_arrived(
    tmp_path: Path, clock: FakeMonotonic
) -> None:
    """PX4 keyed long ago (its frames behind our clock) and a spoofer's unsigned, disarmed heartbeats."""
    r = relay(KEY, tmp_path, "udpin://0.0.0.0:14540", provision=True)
    r.clock.next(time.time())
    r._from_autopilot(heartbeat(packer(FOLLOWER, 1, KEY, ts=unix_to_units(time.time() - 600))), PX4)
    for _ in range(10):
        r._from_autopilot(heartbeat(packer(FOLLOWER, 1)), ("127.0.0.1", 4444))
        clock.t += 1.0
        r._provision()
    assert r.key_seen
    assert setups(r) == []


@pytest.mark.parametrize(
    ("url", "claimants", "expected"),
    [
        ("udpin://0.0.0.0:14540", [SPOOF], False),  # a network address on a listening link proves nothing
        ("udpin://0.0.0.0:14540", [("127.0.0.1", 14580), ("127.0.0.1", 4444)], False),  # two claimants
        ("udpin://0.0.0.0:14540", [("127.0.0.1", 14580)], True),  # SITL on the board, alone
        ("udpout://10.0.0.2:14580", [("10.0.0.2", 14580)], True),  # one known address
    ],
)
def test_the_key_goes_only_to_one_plain_claimant(
    tmp_path: Path, clock: FakeMonotonic, url: str, claimants: list[tuple[str, int]], expected: bool
) -> None:
    r = relay(KEY, tmp_path, url, provision=True)
    for _ in range(int(PROVISION_LISTEN_S) + 1):
        for addr in claimants:
            r._from_autopilot(heartbeat(packer(FOLLOWER, 1)), addr)
        clock.t += 1.0
        r._provision()
    assert bool(setups(r)) == expected  # resent every PROVISION_RETRY_S until the autopilot signs
    assert all(dests == [claimants[0]] for dests in setups(r))


def test_the_key_goes_once_for_good(tmp_path: Path, clock: FakeMonotonic) -> None:
    """Once the autopilot signed, a restarted relay never sends the key again, even to an unsigned one."""
    r = relay(KEY, tmp_path, "serial:///dev/null:57600", provision=True)
    r._from_autopilot(heartbeat(packer(FOLLOWER, 1)), None)
    r._provision()
    assert len(setups(r)) == 1
    r._from_autopilot(heartbeat(packer(FOLLOWER, 1, KEY)), None)
    asyncio.run(r._mark_provisioned())
    assert (tmp_path / PROVISIONED_FILE).exists()
    again = relay(KEY, tmp_path, "serial:///dev/null:57600", provision=True)
    for _ in range(5):
        again._from_autopilot(heartbeat(packer(FOLLOWER, 1)), None)
        clock.t += PROVISION_LISTEN_S
        again._provision()
    assert setups(again) == []


def test_mavsdk_is_the_first_local_sender_the_service_owns_and_others_are_reported(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    stranger = ("127.0.0.1", 5555)
    problems = {stranger: "its socket belongs to another process (uid 65534)"}
    r = SigningRelay(
        relay(KEY, tmp_path, "udpin://0.0.0.0:14540").cfg, KEY, tmp_path, local_sender_problem=problems.get
    )
    r._autopilot = Recorder()
    r._from_autopilot(heartbeat(packer(FOLLOWER, 1, KEY)), PX4)
    with caplog.at_level(logging.WARNING, logger="companion.vehicle.signing"):
        r._from_mavsdk(command_long(packer(FOLLOWER, 195)), stranger)  # speaks first
        assert sent(r) == []
        r._from_mavsdk(command_long(packer(FOLLOWER, 195)), ("127.0.0.1", 6000))  # MAVSDK
        r._from_mavsdk(command_long(packer(FOLLOWER, 195)), ("127.0.0.1", 6001))  # a second one of ours
    assert len(sent(r)) == 1
    assert r.counters["local_refused"] == 1
    assert r.counters["local_foreign"] == 1
    assert r.stats()["mavsdk_address"] == "127.0.0.1:6000"
    text = caplog.text
    assert "127.0.0.1:5555 is not MAVSDK: its socket belongs to another process" in text
    assert "a second local sender at 127.0.0.1:6001 (MAVSDK is 127.0.0.1:6000): refused" in text


def test_a_socket_of_this_process_is_ours_and_a_free_port_is_not() -> None:
    mine = local_socket()
    try:
        assert local_peers.sender_problem(mine.getsockname()) is None
    finally:
        mine.close()
    free = local_socket()
    port = free.getsockname()[1]
    free.close()
    assert "no socket bound" in (local_peers.sender_problem(("127.0.0.1", port)) or "")
    assert "not the loopback" in (local_peers.sender_problem(("10.0.0.1", port)) or "")


@pytest.mark.skipif(os.geteuid() != 0, reason="holds a socket as another user (needs root)")
def test_another_users_socket_that_speaks_first_gets_nothing_signed(tmp_path: Path) -> None:
    racer = subprocess.Popen(
        ["/usr/bin/python3", "-c", RACER, "10"], stdout=subprocess.PIPE, user="nobody", text=True
    )
    assert racer.stdout is not None
    pid, port = (int(v) for v in racer.stdout.readline().split())
    racer.wait()
    try:
        r = relay(KEY, tmp_path, "udpin://0.0.0.0:14540")
        r._from_autopilot(heartbeat(packer(FOLLOWER, 1, KEY)), PX4)
        r._from_mavsdk(command_long(packer(FOLLOWER, 195)), ("127.0.0.1", port))
        assert sent(r) == []
        mav = local_socket()
        bind_mavsdk(r, mav)
        mav.close()
        assert len(sent(r)) == 1
        assert r.counters["local_refused"] == 1
    finally:
        os.kill(pid, 9)


def test_other_systems_reach_mavsdk_only_once_our_autopilot_signed(tmp_path: Path) -> None:
    """MAVSDK hearing only spoofed heartbeats of system 99 would end the service (wrong vehicle, exit 4)."""
    r = relay(KEY, tmp_path, "udpin://0.0.0.0:14540")
    mav = local_socket()
    bind_mavsdk(r, mav)
    mav.close()
    local: Any = r._local
    for _ in range(5):
        r._from_autopilot(heartbeat(packer(99, 1)), SPOOF)
    assert local.sent == []
    assert r.counters["in_unsigned_held"] == 5
    r._from_autopilot(heartbeat(packer(FOLLOWER, 1, KEY)), PX4)
    r._from_autopilot(heartbeat(packer(99, 1)), SPOOF)
    assert len(local.sent) == 2  # our autopilot's heartbeat, then system 99's
