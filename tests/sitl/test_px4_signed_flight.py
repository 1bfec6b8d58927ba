"""A signed flight against real PX4 SITL: the service keys PX4 and flies signed; unsigned input does nothing.

``companion sim --autopilot px4`` with ``link.signing`` and ``link.signing_provision``: the service's relay
gives the follower's PX4 the key (SETUP_SIGNING) while it is disarmed, then flies it over the signed link.
While the follower is in FOLLOW, this test, as another node on the same host:

- asks PX4 for a parameter at its ground-station port (``18570 + i``): unsigned, no answer; signed with the
  service's key from the same port, answered, and the answer is signed (PX4 keyed every link, not only
  the one SETUP_SIGNING came in on);
- sends an unsigned COMMAND_LONG NAV_LAND from system 200 there and at PX4's offboard API port
  (``14580 + i``): PX4 neither answers nor lands. The follower stays in formation (FOLLOW, or a HOVER of
  a second when perception stalls on a loaded host), PX4 in Offboard, in the air, and PX4 says nothing of
  landing;
- sends unsigned HEARTBEATs claiming the follower's system id to the service's port (``14540 + i``): the
  service reports an impostor and counts exactly those.

The follower's PX4 instance ``i`` and working folder come from the simulator's log (``logs/sitl.log``); the
service's state and its relay's counters from its status socket (``logs/service-config.json``). PX4 keeps
the key in its working folder's ``rootfs/mavlink/mavlink-signing-key.bin`` (checked during the flight), and
the folder is removed with PX4 at the end.

A second test keys one PX4 with a timestamp ten minutes old, as PX4 boots after it was keyed long ago,
and shows the service's relay hears it once PX4 has caught up from the relay's frames. Both are skipped
only when no PX4 build is found.
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import secrets
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

import pytest
from pymavlink.dialects.v20 import common as mavlink2

from companion.config import LinkConfig
from companion.kernel import compat
from companion.service.status import ServiceNotRunningError, query_status
from companion.vehicle.mavlink_signing import unix_to_units
from companion.vehicle.signing_relay import TIMESTAMP_FILE, SigningRelay
from sitl.px4.instance import Px4Build, Px4Instance, Px4Ports, free_instance_base
from tests.signing_probe import MavPeer, send_impostor_heartbeats, send_unsigned_land, write_key

REPO = Path(__file__).resolve().parents[2]
SHARED_PX4 = REPO.parent / "shared" / "px4-sitl" / "bin" / "px4"

FOLLOWER = 2
#: The other node: a system id that is neither vehicle's, a ground station's component.
OTHER = (200, 190)
PARAM = "MPC_XY_VEL_MAX"
IMPOSTOR_HEARTBEATS = 5
#: How long the follower is watched after the unsigned landing commands, s (wall).
WATCH_S = 8.0
#: Wall time for the whole run (PX4 at 1x: boot, 50 s of scenario, shutdown).
RUN_TIMEOUT_S = 280.0
#: How long before now PX4 was keyed in the second test, s.
KEYED_AGO_S = 600.0

SCENARIO = """
schema_version = 1
name = "px4-signed-straight"
description = "Leader north at 2 m/s; the follower flies over a signed link while unsigned commands come in."
seed = 1

[run]
duration_s = 50.0
formation_start_s = 24.0
formation_duration_s = 24.0
takeoff_altitude_m = 5.0
camera_rate_hz = 15.0

[leader]
type = "straight"
start_s = 24.0
altitude_m = 5.0
speed_m_s = 2.0

[wind]
mean_speed_m_s = 1.0
from_deg = 270.0
"""

BANNER = re.compile(r"sitl: follower \(system (\d+)\): PX4 instance (\d+)")
#: Each PX4's working folder (its rootfs, with the key), as the simulator logs it.
PX4_FOLDER = re.compile(r"px4 \w+: instance \d+ \(pid \d+\) in (\S+)")
WORK_DIR = re.compile(r"px4 follower: instance \d+ \(pid \d+\) in (\S+)")
#: PX4 modes that mean it landed, or chose a failsafe, by itself.
LANDING_MODES = {"Land", "Descend", "Return", "Altitude", "Position", "Termination"}
#: The mission's states while the service flies the follower in formation (HOVER: a perception stall of
#: a second or so, which a loaded two-core host gives now and then; the service holds the slot).
FLYING = ("follow", "hover")
#: The mission's states that mean the follower is landing, or that PX4 took over.
NOT_FLOWN = {"controlled_landing", "px4_hold", "px4_land", "px4_rtl", "px4_in_control", "link_lost"}
NOT_FLOWN |= {"landed", "disarmed"}

T = TypeVar("T")


def _px4_binary() -> str | None:
    named = os.environ.get("SITL_PX4__BINARY")
    if named:
        return named
    return str(SHARED_PX4) if SHARED_PX4.is_file() else None


class Run:
    """The ``companion sim`` child: its output folder and logs."""

    def __init__(self, proc: subprocess.Popen[bytes], out: Path, err_path: Path) -> None:
        self.proc = proc
        self.out = out
        self.logs = out / "logs"
        self.err_path = err_path

    def text(self, name: str) -> str:
        path = self.logs / name
        return path.read_text(errors="replace") if path.exists() else ""

    def tail(self) -> str:
        err = self.err_path.read_text(errors="replace") if self.err_path.exists() else ""
        return f"--- service ---\n{err[-4000:]}\n--- sitl ---\n{self.text('sitl.log')[-3000:]}"


async def until(what: str, run: Run, get: Callable[[], T | None], timeout_s: float) -> T:
    """Poll ``get`` until it gives something; fail with the run's logs if the run ends or time is up."""
    deadline = time.monotonic() + timeout_s
    while (value := get()) is None:
        if run.proc.poll() is not None:
            raise AssertionError(f"the run ended (exit {run.proc.returncode}) before {what}\n{run.tail()}")
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}\n{run.tail()}")
        await asyncio.sleep(0.2)
    return value


def status_of(path: Path) -> dict[str, Any] | None:
    try:
        return query_status(path, "status", timeout_s=2.0)
    except ServiceNotRunningError:
        return None


def flown_by_the_service(st: dict[str, Any], states: tuple[str, ...] = FLYING) -> bool:
    """The mission in one of ``states``, PX4 in Offboard, armed and in the air above 3 m."""
    link, pos = st["link"], st["position"]
    return bool(
        st["mission"]["state"].lower() in states
        and str(link["flight_mode"]).lower() == "offboard"
        and link["armed"]
        and link["in_air"]
        and (pos["altitude_m"] or 0.0) > 3.0
    )


async def probe_in_follow(run: Run, key: bytes) -> dict[str, Any]:
    """Everything the other node tries while the follower is in FOLLOW, and what came of it."""

    def banner() -> tuple[int, int] | None:
        m = BANNER.search(run.text("sitl.log"))
        return (int(m.group(1)), int(m.group(2))) if m else None

    sysid, instance = await until("the simulator's banner", run, banner, 120.0)
    assert sysid == FOLLOWER
    m = WORK_DIR.search(run.text("sitl.log"))
    assert m is not None, run.tail()
    px4_work = Path(m.group(1))
    cfg = json.loads(run.text("service-config.json"))
    status_path = Path(cfg["status"]["socket_path"])

    def following() -> dict[str, Any] | None:
        st = status_of(status_path)
        return st if st is not None and flown_by_the_service(st, ("follow",)) else None

    await until("FOLLOW over the signed link", run, following, 150.0)
    await asyncio.sleep(2.0)
    key_file = px4_work / "rootfs" / "mavlink" / "mavlink-signing-key.bin"
    px4_key = key_file.read_bytes()
    key_mode = key_file.stat().st_mode & 0o777

    gcs_port, api_port, service_port = 18570 + instance, 14580 + instance, 14540 + instance
    other = await MavPeer.open(("127.0.0.1", gcs_port), src=OTHER, key=key)
    try:
        other.sign_outgoing(False)
        unsigned_param = await other.param_answered(FOLLOWER, PARAM, timeout_s=2.0)
        other.sign_outgoing(True)
        signed_param = await other.param_answered(FOLLOWER, PARAM, timeout_s=2.0)
        answer_signed = other.last_signed("PARAM_VALUE")
        other.sign_outgoing(False)
        land = mavlink2.MAVLink_command_long_message(
            FOLLOWER, 1, mavlink2.MAV_CMD_NAV_LAND, 0, 0, 0, 0, 0, 0, 0, 0
        )
        for _ in range(3):
            other.send(land)
            send_unsigned_land(("127.0.0.1", api_port), FOLLOWER, *OTHER)
            await asyncio.sleep(0.2)
        send_impostor_heartbeats(("127.0.0.1", service_port), FOLLOWER, count=IMPOSTOR_HEARTBEATS)
        watched: list[dict[str, Any]] = []

        async def watch(until_s: float) -> None:
            while time.monotonic() < until_s:
                st = await asyncio.to_thread(status_of, status_path)
                assert st is not None, run.tail()
                watched.append(st)
                await asyncio.sleep(0.5)

        t_end = time.monotonic() + WATCH_S
        await watch(time.monotonic() + 2.0)  # any answer to the land would be back by now
        acks = [(m.command, m.result) for m in other.received if m.get_type() == "COMMAND_ACK"]
        streamed = (other.signed_from.get(FOLLOWER, 0), other.unsigned_from.get(FOLLOWER, 0))
    finally:
        other.close()  # PX4's GCS stream, parsed here, costs the loaded host: not longer than needed
    await watch(t_end)
    return {
        "instance": instance,
        "px4_work": px4_work,
        "px4_key": px4_key,
        "px4_key_mode": key_mode,
        "unsigned_param_answered": unsigned_param,
        "signed_param_answered": signed_param,
        "answer_signed": answer_signed,
        "acks": acks,
        "streamed": streamed,
        "watched": watched,
    }


@pytest.mark.sitl
@pytest.mark.render
@pytest.mark.slow
@pytest.mark.lab
@pytest.mark.timeout(330)
def test_px4_flies_signed_and_an_unsigned_land_from_another_node_does_nothing(tmp_path: Path) -> None:
    binary = _px4_binary()
    if binary is None:
        pytest.skip(f"no PX4 SITL build: set SITL_PX4__BINARY or put one at {SHARED_PX4}")
    scenario = tmp_path / "px4-signed-straight.toml"
    scenario.write_text(SCENARIO)
    key = secrets.token_bytes(32)
    key_file = write_key(tmp_path / "signing.key", key)
    out = tmp_path / "run"
    env = {**os.environ, "PYTHONPATH": str(REPO), "SITL_PX4__BINARY": binary}
    state_dir = tmp_path / "state"
    cmd = [sys.executable, "-m", "companion", "sim", "--scenario", str(scenario), "--autopilot", "px4",
           "--no-plots", "--out", str(out),
           "--set", "link.signing=true", "--set", f'link.signing_key_file="{key_file}"',
           "--set", "link.signing_provision=true", "--set", f'service.state_dir="{state_dir}"']  # fmt: skip
    err_path = tmp_path / "sim.err"
    with (tmp_path / "sim.out").open("wb") as stdout, err_path.open("wb") as stderr:
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=stdout, stderr=stderr)
    run = Run(proc, out, err_path)
    try:
        seen = asyncio.run(probe_in_follow(run, key))
        assert proc.wait(timeout=RUN_TIMEOUT_S) == 0, run.tail()
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGTERM)
            try:
                proc.wait(timeout=30)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait(timeout=10)
    service_log = err_path.read_text(errors="replace")
    report = json.loads((out / "report.json").read_text())
    ap = report["autopilot"]
    final = seen["watched"][-1]["mavlink_signing"] if seen["watched"] else {}
    print(
        f"\npx4 signed flight: {report['outcome']}, relative position RMSE "
        f"{report['relative_position_rmse_m']:.3f} m, formation max deviation "
        f"{report['formation_max_deviation_m']:.3f} m; follower modes "
        f"{[(m['mode'], m['armed']) for m in ap['follower_modes']]}\n"
        f"at PX4's GCS port: unsigned read answered {seen['unsigned_param_answered']}, signed read answered "
        f"{seen['signed_param_answered']} (answer signed {seen['answer_signed']}); frames from PX4 there "
        f"signed/unsigned {seen['streamed']}; COMMAND_ACKs to the unsigned land {seen['acks']}\n"
        f"signing relay: {json.dumps(final)}"
    )

    # The service keyed PX4 while it was disarmed; PX4 keeps the key (and a timestamp) in its rootfs, 0600.
    assert "sent the key to autopilot system 2" in service_log
    assert "MAVLink signing key accepted" in run.text("px4-follower.log")
    assert seen["px4_key"][:32] == key
    assert len(seen["px4_key"]) == 40
    assert seen["px4_key_mode"] == 0o600
    assert (state_dir / "mavlink-signing-timestamp").is_file()  # the service's side, kept across restarts

    # PX4 answers a signed request and drops the unsigned one, on a link the key did not come in on.
    assert seen["unsigned_param_answered"] is False
    assert seen["signed_param_answered"] is True
    assert seen["answer_signed"] is True
    signed_frames, unsigned_frames = seen["streamed"]
    assert signed_frames > 100
    assert unsigned_frames == 0, seen["streamed"]

    # The unsigned land: no answer, and the follower flew on in formation in Offboard.
    assert seen["acks"] == []
    watched = seen["watched"]
    assert len(watched) >= WATCH_S / 0.5 - 2
    seen_states = [
        (st["mission"]["state"], st["link"]["flight_mode"], st["position"]["altitude_m"]) for st in watched
    ]
    assert all(flown_by_the_service(st) for st in watched), seen_states
    assert sum(st["mission"]["state"] == "follow" for st in watched) >= 0.8 * len(watched), seen_states

    # The impostor's heartbeats: reported, counted exactly, never from PX4's own address.
    assert final["autopilot_signs"] is True
    assert final["provision_attempts"] >= 1
    assert final["counters"]["out_signed"] > 200
    assert final["counters"]["in_signed"] > 200
    assert sum(final["impostors"].values()) == IMPOSTOR_HEARTBEATS, final["impostors"]
    assert f"127.0.0.1:{14580 + seen['instance']}" not in final["impostors"]
    assert "claimed by a frame that is not signed with our key" in service_log

    # The whole flight: PX4 never landed or chose a failsafe, said nothing of landing, and the run ended in
    # formation. Its working folder, with the key, is gone.
    modes = [m["mode"] for m in ap["follower_modes"]]
    assert "Offboard" in modes
    assert not LANDING_MODES & set(modes), modes
    texts = [t["text"] for t in ap["texts"] if t["vehicle"] == "follower"]
    assert not [t for t in texts if "land" in t.lower()], texts
    assert ap["follower_failsafes"] == []
    states = [(t[1], t[2]) for t in report["transitions"]]
    assert ("ACQUIRE", "FOLLOW") in states
    assert not [s for s in states if s[1].lower() in NOT_FLOWN], states
    assert report["outcome"] == "completed", (report["outcome"], states)
    folders = [Path(m.group(1)) for m in PX4_FOLDER.finditer(run.text("sitl.log"))]
    assert seen["px4_work"] in folders
    assert len(folders) == 2
    assert not [f for f in folders if f.exists()]


async def _px4_keyed_long_ago_is_heard(tmp_path: Path, binary: str) -> dict[str, Any]:
    build = Px4Build.locate(binary)
    instance = free_instance_base(1)
    ports = Px4Ports(instance)
    px4 = Px4Instance(build, instance, "signing", {"MAV_SYS_ID": float(FOLLOWER)})
    key = secrets.token_bytes(32)
    loop = asyncio.get_running_loop()
    px4.start()
    try:
        # Keyed (disarmed) from the port the service listens on, as the relay does, ten minutes "ago".
        transport, keyer = await loop.create_datagram_endpoint(
            lambda: MavPeer(addr=("127.0.0.1", ports.api_local), src=(FOLLOWER, 195)),
            local_addr=("127.0.0.1", ports.api_remote),
        )
        try:
            deadline = time.monotonic() + 90.0
            while not any(m.get_type() == "HEARTBEAT" for m in keyer.received):
                assert px4.running, px4.tail()
                assert time.monotonic() < deadline, px4.tail()
                await asyncio.sleep(0.2)
            keyer.send(
                mavlink2.MAVLink_setup_signing_message(
                    FOLLOWER, 1, list(key), unix_to_units(time.time() - KEYED_AGO_S)
                )
            )
            deadline = time.monotonic() + 10.0
            while "MAVLink signing key accepted" not in px4.tail(20000):
                assert time.monotonic() < deadline, px4.tail()
                await asyncio.sleep(0.1)
        finally:
            transport.close()
        # The service's relay, its clock where the last flight left it (now), and MAVSDK's heartbeats.
        state = tmp_path / "state"
        state.mkdir()
        (state / TIMESTAMP_FILE).write_text(f"{unix_to_units(time.time())}\n")
        cfg = LinkConfig(
            url=f"udpin://127.0.0.1:{ports.api_remote}",
            system_id=FOLLOWER,
            signing=True,
            signing_key_file="given-below",
        )
        mavsdk = await MavPeer.open(("127.0.0.1", 0), src=(FOLLOWER, 195))
        t0 = time.monotonic()
        try:
            async with SigningRelay(cfg, key, state) as relay, compat.TaskGroup() as tg:
                mavsdk.addr = ("127.0.0.1", relay.local_port)
                task = tg.create_task(relay.run(), name="test.relay")
                deadline = time.monotonic() + 20.0
                while mavsdk.signed_from.get(FOLLOWER, 0) < 20:
                    assert time.monotonic() < deadline, relay.stats()
                    mavsdk.send(mavlink2.MAVLink_heartbeat_message(18, 8, 0, 0, 4, 3))
                    await asyncio.sleep(0.2)
                heard_after_s = time.monotonic() - t0
                answered = await mavsdk.param_answered(FOLLOWER, PARAM)
                task.cancel()
        finally:
            mavsdk.close()
        return {"stats": relay.stats(), "heard_after_s": heard_after_s, "answered": answered}
    finally:
        px4.remove()


@pytest.mark.sitl
@pytest.mark.slow
@pytest.mark.lab
@pytest.mark.timeout(180)
def test_px4_keyed_long_ago_is_heard_once_it_has_the_relays_frames(tmp_path: Path) -> None:
    """PX4 boots with the timestamp it was keyed with, far behind the service's: it still gets flown.

    PX4 keeps SETUP_SIGNING's timestamp in its key file and starts from it at every boot (measured: its first
    frames after a boot were as old as the key), moving on only as it sends and up to the newest signed
    frame it receives. Keyed ten minutes "ago", its frames are a new stream far behind the relay's clock
    and are dropped; the relay sends it MAVSDK's frames anyway, PX4 catches up, and from then on its frames
    pass: MAVSDK hears its heartbeats and reads a parameter. No impostor is reported.
    """
    binary = _px4_binary()
    if binary is None:
        pytest.skip(f"no PX4 SITL build: set SITL_PX4__BINARY or put one at {SHARED_PX4}")
    seen = asyncio.run(_px4_keyed_long_ago_is_heard(tmp_path, binary))
    stats = seen["stats"]
    print(f"px4 keyed {KEYED_AGO_S:.0f} s ago: heard after {seen['heard_after_s']:.1f} s; relay {stats}")
    assert stats["autopilot_signs"] is True
    assert stats["counters"]["in_behind"] >= 1
    assert stats["impostors"] == {}
    assert seen["answered"] is True
