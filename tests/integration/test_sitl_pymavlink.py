"""A plain pymavlink client against ``sitl serve``, and hostile datagrams on every port."""

from __future__ import annotations

import random
import re
import socket
import struct
import time
from collections.abc import Iterator
from typing import Any

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink

from tests.fuzz_messages import datagrams
from tests.integration.sitl_process import SitlProcess, sitl_serve

pytestmark = [pytest.mark.sitl, pytest.mark.slow, pytest.mark.timeout(240)]

SPEED = 4.0


@pytest.fixture
def sim() -> Iterator[SitlProcess]:
    with sitl_serve(speed=SPEED) as s:
        yield s


def client(port: int) -> Any:
    """pymavlink's mavutil, as a user would open it, talking straight to a vehicle's API port."""
    m = mavutil.mavlink_connection(
        f"udpout:127.0.0.1:{port}", source_system=255, source_component=190, dialect="common"
    )
    m.mav.heartbeat_send(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, 0)
    hb = m.wait_heartbeat(timeout=10)
    assert hb is not None, "no heartbeat"
    return m


def recv(m: Any, msg_type: str, timeout_s: float = 5.0, cond: Any = None) -> Any:
    end = time.monotonic() + timeout_s
    while time.monotonic() < end:
        msg = m.recv_match(type=msg_type, blocking=True, timeout=0.2)
        if msg is not None and (cond is None or cond(msg)):
            return msg
    raise AssertionError(f"no {msg_type} within {timeout_s} s")


def command(m: Any, sysid: int, cmd: int, *params: float) -> int:
    p = list(params) + [0.0] * (7 - len(params))
    m.mav.command_long_send(sysid, 1, cmd, 0, *p)
    return int(recv(m, "COMMAND_ACK", cond=lambda a: a.command == cmd).result)


def param_value(m: Any, sysid: int, name: str) -> Any:
    m.mav.param_request_read_send(sysid, 1, name.encode(), -1)
    return recv(m, "PARAM_VALUE", cond=lambda p: p.param_id == name)


def test_pymavlink_lists_reads_sets_params_and_changes_modes(sim: SitlProcess) -> None:
    m = client(sim.ports.api_local + 1)  # the follower, system 2
    assert m.target_system == 2
    assert m.messages["HEARTBEAT"].autopilot == mavlink.MAV_AUTOPILOT_PX4
    # List: every parameter arrives once with its index and the total count.
    m.mav.param_request_list_send(2, 1)
    first = recv(m, "PARAM_VALUE")
    seen = {first.param_id: first}
    while len(seen) < first.param_count:
        p = recv(m, "PARAM_VALUE")
        seen[p.param_id] = p
    for name in ("MIS_TAKEOFF_ALT", "COM_OF_LOSS_T", "COM_OBL_RC_ACT", "NAV_RCL_ACT", "EKF2_NOAID_TOUT"):
        assert name in seen
    assert sorted(p.param_index for p in seen.values()) == list(range(first.param_count))
    # INT32 parameters are bytewise-encoded, as PX4 sends them.
    tout = seen["EKF2_NOAID_TOUT"]
    assert tout.param_type == mavlink.MAV_PARAM_TYPE_INT32
    assert struct.unpack("<i", struct.pack("<f", tout.param_value))[0] == 5_000_000
    # Read and set a float, then an int (bytewise).
    assert param_value(m, 2, "MIS_TAKEOFF_ALT").param_value == pytest.approx(2.5)
    m.mav.param_set_send(2, 1, b"MIS_TAKEOFF_ALT", 7.5, mavlink.MAV_PARAM_TYPE_REAL32)
    assert recv(m, "PARAM_VALUE", cond=lambda p: p.param_id == "MIS_TAKEOFF_ALT").param_value == 7.5
    four = struct.unpack("<f", struct.pack("<i", 4))[0]
    m.mav.param_set_send(2, 1, b"COM_OBL_RC_ACT", four, mavlink.MAV_PARAM_TYPE_INT32)
    echo = recv(m, "PARAM_VALUE", cond=lambda p: p.param_id == "COM_OBL_RC_ACT")
    assert struct.unpack("<i", struct.pack("<f", echo.param_value))[0] == 4
    assert param_value(m, 2, "MIS_TAKEOFF_ALT").param_value == 7.5
    # Modes: disarmed, any mode is accepted (Offboard too); mavutil decodes PX4's custom modes.
    assert command(m, 2, mavlink.MAV_CMD_DO_SET_MODE, 1, 6, 0) == mavlink.MAV_RESULT_ACCEPTED
    recv(m, "HEARTBEAT", cond=lambda h: mavutil.interpret_px4_mode(h.base_mode, h.custom_mode) == "OFFBOARD")
    assert command(m, 2, mavlink.MAV_CMD_DO_SET_MODE, 1, 4, 3) == mavlink.MAV_RESULT_ACCEPTED
    recv(m, "HEARTBEAT", cond=lambda h: mavutil.interpret_px4_mode(h.base_mode, h.custom_mode) == "LOITER")
    assert command(m, 2, mavlink.MAV_CMD_DO_SET_MODE, 1, 99, 0) == mavlink.MAV_RESULT_DENIED
    assert command(m, 2, 31999) == mavlink.MAV_RESULT_UNSUPPORTED
    # Armed (once the estimator is ready): a mode that cannot run is refused, Land always goes.
    recv(m, "SYS_STATUS", timeout_s=30, cond=lambda s: s.onboard_control_sensors_health & 32)
    recv(m, "HOME_POSITION", timeout_s=10)
    assert command(m, 2, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert command(m, 2, mavlink.MAV_CMD_DO_SET_MODE, 129, 4, 4) == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    assert command(m, 2, mavlink.MAV_CMD_DO_SET_MODE, 129, 4, 6) == mavlink.MAV_RESULT_ACCEPTED
    recv(m, "HEARTBEAT", cond=lambda h: mavutil.interpret_px4_mode(h.base_mode, h.custom_mode) == "LAND")
    # Armed on the ground and never airborne: auto-disarm after COM_DISARM_PRFLT (10 s sim). The
    # wall-clock margin is wide because a loaded host slows the simulator down.
    recv(m, "HEARTBEAT", timeout_s=60, cond=lambda h: not h.base_mode & 128)
    m.close()


def test_ten_thousand_hostile_datagrams_per_port_change_nothing(sim: SitlProcess) -> None:
    ports = [sim.ports.api_local, sim.ports.api_local + 1, sim.ports.gcs_local, sim.ports.gcs_local + 1]
    rng = random.Random(20261122)
    # A pool of distinct hostile datagrams (building one costs ~0.3 ms), each sent with a fresh
    # random byte flipped half of the time, so no two ports see the same 10,000.
    pool = list(datagrams(rng, 3000))
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(0.5)
    parser = mavlink.MAVLink(None)
    probe_packer = mavlink.MAVLink(None, srcSystem=254, srcComponent=190)
    sent = 0
    for port in ports:
        for burst in range(50):
            for _ in range(200):
                data = bytearray(rng.choice(pool))
                if data and rng.random() < 0.5:
                    data[rng.randrange(len(data))] = rng.randrange(256)
                sock.sendto(bytes(data), ("127.0.0.1", port))
                sent += 1
            # A TIMESYNC probe after each burst: its answer proves the burst was processed (UDP on
            # localhost keeps order), so the kernel never drops what we want counted.
            tag = port * 1000 + burst
            sock.sendto(mavlink.MAVLink_timesync_message(0, tag).pack(probe_packer), ("127.0.0.1", port))
            deadline = time.monotonic() + 15.0
            answered = False
            while not answered:
                assert time.monotonic() < deadline, f"no answer to probe {tag} on port {port}"
                try:
                    reply = sock.recv(65536)
                except TimeoutError:
                    continue
                msgs = parser.parse_buffer(reply) or []
                answered = any(m.get_type() == "TIMESYNC" and m.ts1 == tag and m.tc1 != 0 for m in msgs)
    sock.close()
    assert sent == 40_000
    # Both vehicles still answer commands and parameter reads.
    for sysid, port in ((1, sim.ports.api_local), (2, sim.ports.api_local + 1)):
        m = client(port)
        assert command(m, sysid, mavlink.MAV_CMD_REQUEST_MESSAGE, 148) == mavlink.MAV_RESULT_ACCEPTED
        # PX4 sends the requested message before the ACK; mavutil keeps the latest of each type.
        assert m.messages["AUTOPILOT_VERSION"].capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        assert param_value(m, sysid, "COM_OF_LOSS_T").param_type == mavlink.MAV_PARAM_TYPE_REAL32
        m.close()
    assert sim.proc.poll() is None, "the simulator died"
    out = sim.stop()
    assert sim.proc.returncode == 0
    errors = [int(x) for x in re.findall(r"handler errors (\d+)", out)]
    assert errors, out[-2000:]
    assert errors == [0] * len(errors), errors
    assert "Traceback" not in out
    counts = [
        int(line.split("datagrams in ")[1].split()[0]) for line in out.splitlines() if "datagrams in" in line
    ]
    assert len(counts) == 4
    assert all(c >= 10_000 for c in counts), counts  # every datagram reached the parser
