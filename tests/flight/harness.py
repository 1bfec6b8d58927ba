"""Flight tests against ``sitl serve``: the simulator process, ground truth, GPS fault injection, recording.

TEST-ONLY truth tracker: until the perception pipeline is wired in, :class:`TruthTracker` hands the
mission the *true* leader-relative state (from the simulator's truth stream) as if it were the tracker's
output. Figures from these tests measure the flight side (link, law, machine) against PX4-like behaviour;
they are not vision results.
"""

from __future__ import annotations

import asyncio
import contextlib
import importlib.util
import json
import math
import os
import socket
import sys
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from companion.config import Config
from companion.estimation.leader import LeaderEstimate, TrackStatus
from companion.kernel.clock import MonotonicClock
from companion.kernel.frames import R_from_quat, ned_to_heading
from companion.lab.evaluation.procs import Child
from companion.lab.evaluation.procs import SitlPorts as Ports
from companion.mission.geometry import Slot
from companion.mission.machine import MissionMachine
from companion.mission.types import MissionInputs, MissionState, SharedLeaderPosition, StepOutput, Transition
from companion.service.mission_runner import MissionRunner
from companion.vehicle.external_vision import ev_position_bits_for
from companion.vehicle.mavsdk_link import MavsdkVehicleLink

from .wiretap import WireTap, open_wiretap

REPO = Path(__file__).resolve().parents[2]
FOLLOWER = "follower"
LEADER = "leader"


def sitl_missing_reason() -> str | None:
    """Why the simulator cannot run here (None when it can)."""
    if importlib.util.find_spec("jsbsim") is None:
        return "jsbsim is not installed (pip install -e .[sim])"
    return None


# ---------------------------------------------------------------------- ports and the process
class SimProcess:
    """``sitl serve`` in a child process, stopped by its PID (SIGTERM, then SIGKILL) whatever happens."""

    def __init__(self, tmp_path: Path, ports: Ports, scenario_toml: str | None) -> None:
        self.tmp_path = tmp_path
        self.ports = ports
        self.scenario_toml = scenario_toml
        self.child: Child | None = None

    async def __aenter__(self) -> SimProcess:
        src = REPO
        run_dir = self.tmp_path / "sitl-run"
        run_dir.mkdir()
        # `python -m` puts the cwd first on sys.path: run from a directory holding only the sitl package.
        (run_dir / "sitl").symlink_to(src / "sitl")
        # ``sitl`` hosting the truth component (passed in, see tests.flight.truth_component).
        args = [
            sys.executable,
            "-m",
            "tests.flight.truth_component",
            "--log-level",
            "INFO",
            "serve",
            "--no-camera",
        ]
        args += (
            ["--config", str(src / "config" / "sitl.toml")] if (src / "config" / "sitl.toml").exists() else []
        )
        if self.scenario_toml is not None:
            scen = self.tmp_path / "scenario.toml"
            scen.write_text(self.scenario_toml)
            args += ["--scenario", str(scen)]
        env = dict(os.environ)
        env.update(
            {
                "PYTHONPATH": os.pathsep.join([str(run_dir), str(REPO)]),
                "SITL_MAVLINK__API_LOCAL_PORT_BASE": str(self.ports.api_local),
                "SITL_MAVLINK__API_REMOTE_PORT_BASE": str(self.ports.api_remote),
                "SITL_MAVLINK__GCS_LOCAL_PORT_BASE": str(self.ports.gcs_local),
                "SITL_MAVLINK__GCS_REMOTE_PORT": str(self.ports.gcs_remote),
                "SITL_MAVLINK__REMOTE_HOST": "127.0.0.1",
                "WINGMAN_TEST_TRUTH_PORT": str(self.ports.truth),
            }
        )
        self.child = Child(args, env, self.tmp_path / "sitl.log", cwd=run_dir)
        self.child.start()
        await self.child.wait_for_output("running at", 30.0)
        return self

    async def stop(self) -> None:
        if self.child is not None:
            await self.child.stop(timeout_s=5.0)

    async def __aexit__(self, *exc: object) -> None:
        await self.stop()


# ---------------------------------------------------------------------- truth
@dataclass
class VehicleTruth:
    t_s: float
    p: np.ndarray
    v: np.ndarray
    q: np.ndarray

    @property
    def yaw_rad(self) -> float:
        R = R_from_quat(self.q)
        return math.atan2(R[1, 0], R[0, 0])


class TruthFeed(asyncio.DatagramProtocol):
    """Receives the truth component's datagrams; keeps the latest, stamped on arrival (service clock)."""

    def __init__(self, clock: MonotonicClock) -> None:
        self.clock = clock
        self.latest: dict[str, VehicleTruth] = {}
        self.stamp_s = -math.inf
        self.sim_t_s = 0.0
        self.updated = asyncio.Event()

    def datagram_received(self, data: bytes, addr: tuple[str, int]) -> None:
        msg = json.loads(data)
        self.sim_t_s = float(msg["t_s"])
        self.latest = {
            name: VehicleTruth(self.sim_t_s, np.array(v["p"]), np.array(v["v"]), np.array(v["q"]))
            for name, v in msg["vehicles"].items()
        }
        self.stamp_s = self.clock.now_s()
        self.updated.set()
        self.updated = asyncio.Event()

    def rel(self) -> tuple[np.ndarray, np.ndarray]:
        lead, fol = self.latest[LEADER], self.latest[FOLLOWER]
        return lead.p - fol.p, lead.v - fol.v


@dataclass
class TruthTracker:
    """TEST-ONLY stand-in for the perception pipeline: the true relative state as a tracker output."""

    feed: TruthFeed
    runner: MissionRunner
    clock: MonotonicClock
    status: TrackStatus = TrackStatus.CONFIRMED
    paused: bool = False
    share_leader_position: bool = False
    min_leader_alt_m: float = 3.0
    #: Follower spawn in the world frame = its local NED origin (for the shared leader position).
    origin_ned_m: np.ndarray = field(default_factory=lambda: np.zeros(3))

    async def run(self) -> None:
        while True:
            await self.feed.updated.wait()
            if self.paused or FOLLOWER not in self.feed.latest:
                continue
            if -self.feed.latest[LEADER].p[2] < self.min_leader_alt_m:
                continue  # the leader is still on the ground, out of sight of a flying follower's camera
            p_rel, v_rel = self.feed.rel()
            now = self.clock.now_s()
            self.runner.submit_leader(
                LeaderEstimate(
                    stamp_s=now,
                    status=self.status,
                    p_ned_rel_m=(float(p_rel[0]), float(p_rel[1]), float(p_rel[2])),
                    v_ned_rel_m_s=(float(v_rel[0]), float(v_rel[1]), float(v_rel[2])),
                    last_measurement_s=now,
                    var_ned_rel_m2=(0.01, 0.01, 0.01),
                )
            )
            if self.share_leader_position:
                p_l = self.feed.latest[LEADER].p - self.origin_ned_m
                self.runner.submit_leader_shared(
                    SharedLeaderPosition(
                        now, (float(p_l[0]), float(p_l[1]), float(p_l[2])), (0.04, 0.04, 0.09)
                    )
                )


# ---------------------------------------------------------------------- GCS-side fault injection
async def inject_gps(ports: Ports, failure_type: int, timeout_s: float = 5.0) -> int:
    """MAV_CMD_INJECT_FAILURE (GPS, ``failure_type``: 0 ok, 1 off) on the follower's GCS link, as a GCS would.

    Returns the MAV_RESULT of the COMMAND_ACK.
    """
    mav = mavlink2.MAVLink(None, srcSystem=255, srcComponent=190)
    parser = mavlink2.MAVLink(None)
    loop = asyncio.get_running_loop()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.setblocking(False)
    sock.bind(("127.0.0.1", 0))
    try:
        dest = ("127.0.0.1", ports.follower_gcs)
        cmd = mavlink2.MAVLink_command_long_message(
            2, 1, mavlink2.MAV_CMD_INJECT_FAILURE, 0, 4, failure_type, 0, 0, 0, 0, 0
        )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            sock.sendto(cmd.pack(mav), dest)
            end = time.monotonic() + 0.5
            while time.monotonic() < end:
                try:
                    data = await asyncio.wait_for(
                        loop.sock_recv(sock, 4096), timeout=max(0.01, end - time.monotonic())
                    )
                except TimeoutError:
                    break
                for m in parser.parse_buffer(data) or []:
                    if m.get_type() == "COMMAND_ACK" and m.command == mavlink2.MAV_CMD_INJECT_FAILURE:
                        return int(m.result)
        raise TimeoutError("no COMMAND_ACK for MAV_CMD_INJECT_FAILURE")
    finally:
        sock.close()


# ---------------------------------------------------------------------- recording
@dataclass
class Row:
    """One control tick as the test sees it: the mission's view plus the truth."""

    t_s: float
    state: MissionState
    setpoint: str | None
    mode: str
    position_valid: bool | None
    gps_fix: int
    formation_err_m: float | None
    err_heading: tuple[float, float, float] | None
    separation_m: float | None
    alt_true_m: float | None
    vz_true_m_s: float | None
    speed_h_true_m_s: float | None
    #: PX4's velocity estimate minus the true velocity (NED), m/s.
    v_est_err_m_s: tuple[float, float, float] | None = None


@dataclass
class Recorder:
    """Collects a row per tick and every transition."""

    feed: TruthFeed
    slot: Slot
    rows: list[Row] = field(default_factory=list)
    transitions: list[Transition] = field(default_factory=list)
    state_events: dict[MissionState, asyncio.Event] = field(default_factory=dict)

    def on_transition(self, tr: Transition) -> None:
        self.transitions.append(tr)
        ev = self.state_events.get(tr.to_state)
        if ev is not None:
            ev.set()

    def on_step(self, inp: MissionInputs, out: StepOutput) -> None:
        truth = self.feed.latest
        err = sep = alt = vz = vh = None
        err_h = None
        v_err = None
        if LEADER in truth and FOLLOWER in truth:
            fol, lead = truth[FOLLOWER], truth[LEADER]
            rel = lead.p - fol.p
            h = ned_to_heading(rel, fol.yaw_rad)
            e = h - np.array([self.slot.forward_m, self.slot.right_m, self.slot.down_m])
            err = float(np.linalg.norm(e))
            err_h = (float(e[0]), float(e[1]), float(e[2]))
            sep = float(np.linalg.norm(rel))
            alt = float(-fol.p[2])
            vz = float(fol.v[2])
            vh = float(math.hypot(fol.v[0], fol.v[1]))
            dv = np.array(inp.vehicle.v_ned_m_s) - fol.v
            v_err = (float(dv[0]), float(dv[1]), float(dv[2]))
        self.rows.append(
            Row(
                t_s=inp.vehicle.stamp_s,
                state=out.state,
                setpoint=None if out.setpoint is None else type(out.setpoint).__name__,
                mode=inp.vehicle.flight_mode.value,
                position_valid=inp.vehicle.position_valid,
                gps_fix=inp.vehicle.gps_fix_type,
                formation_err_m=err,
                err_heading=err_h,
                separation_m=sep,
                alt_true_m=alt,
                vz_true_m_s=vz,
                speed_h_true_m_s=vh,
                v_est_err_m_s=v_err,
            )
        )

    def wait_for(self, state: MissionState) -> asyncio.Event:
        ev = self.state_events.setdefault(state, asyncio.Event())
        if any(t.to_state == state for t in self.transitions):
            ev.set()
        return ev

    def rows_in(self, *states: MissionState, since_s: float = -math.inf) -> list[Row]:
        return [r for r in self.rows if r.state in states and r.t_s >= since_s]

    def reasons(self) -> list[str]:
        return [f"{t.from_state.value}->{t.to_state.value}:{t.reason.name}" for t in self.transitions]


@dataclass
class Flight:
    """Everything a flight test body gets."""

    ports: Ports
    clock: MonotonicClock
    link: MavsdkVehicleLink
    runner: MissionRunner
    feed: TruthFeed
    tracker: TruthTracker
    rec: Recorder
    tap: WireTap

    async def sim_time(self, t_s: float, timeout_s: float = 120.0) -> None:
        """Until the simulator's clock reaches ``t_s``."""
        async with asyncio.timeout(timeout_s):
            while self.feed.sim_t_s < t_s:
                await self.feed.updated.wait()

    async def reach(self, state: MissionState, timeout_s: float) -> None:
        try:
            async with asyncio.timeout(timeout_s):
                await self.rec.wait_for(state).wait()
        except TimeoutError:
            now = self.runner.state.value
            raise AssertionError(
                f"never reached {state.value} in {timeout_s} s; now {now}; {self.rec.reasons()}"
            ) from None


async def fly(
    tmp_path: Path,
    cfg: Config,
    scenario_toml: str | None,
    body: Callable[[Flight], Awaitable[None]],
    *,
    start: bool = True,
) -> Flight:
    """Start the simulator, a MAVSDK link behind a wiretap, the runner and the truth tracker; run ``body``."""
    ports = Ports.pick()
    clock = MonotonicClock()
    loop = asyncio.get_running_loop()
    feed = TruthFeed(clock)
    transport, _ = await loop.create_datagram_endpoint(lambda: feed, local_addr=("127.0.0.1", ports.truth))
    tap = await open_wiretap(ports.follower_api, ports.client)
    link_cfg = cfg.link.model_copy(update={"url": f"udpin://127.0.0.1:{ports.client}"})
    flight: Flight | None = None
    try:
        ev_bits = ev_position_bits_for(cfg.mission.gps_loss_policy)
        async with (
            SimProcess(tmp_path, ports, scenario_toml),
            MavsdkVehicleLink(link_cfg, clock, ev_position_bits=ev_bits) as link,
        ):
            rec = Recorder(feed, Slot.from_offset_cam(cfg.formation.offset_cam_m))
            runner = MissionRunner(
                link,
                MissionMachine(cfg),
                clock,
                rate_hz=cfg.link.setpoint_rate_hz,
                command_timeout_s=cfg.link.command_timeout_s,
                on_transition=rec.on_transition,
                on_step=rec.on_step,
            )
            tracker = TruthTracker(feed, runner, clock)
            flight = Flight(ports, clock, link, runner, feed, tracker, rec, tap)
            if start:
                runner.request_start()
            try:
                async with asyncio.TaskGroup() as tg:
                    tasks = [
                        tg.create_task(link.run(), name="test.link"),
                        tg.create_task(tracker.run(), name="test.truth_tracker"),
                        tg.create_task(runner.run(), name="test.runner"),
                    ]
                    try:
                        await body(flight)
                    finally:
                        for t in tasks:
                            t.cancel()
            except* AssertionError as eg:
                raise eg.exceptions[0] from None
    finally:
        tap.close()
        transport.close()
        if flight is not None:
            dump(flight.rec, tmp_path / "flight.csv")
    assert flight is not None
    return flight


@contextlib.asynccontextmanager
async def bare_link(
    tmp_path: Path, cfg: Config, scenario_toml: str | None = None
) -> AsyncIterator[tuple[MavsdkVehicleLink, WireTap, TruthFeed, Ports]]:
    """The simulator and a real MAVSDK link (behind a wiretap), without the mission: for link-level tests."""
    ports = Ports.pick()
    clock = MonotonicClock()
    loop = asyncio.get_running_loop()
    feed = TruthFeed(clock)
    transport, _ = await loop.create_datagram_endpoint(lambda: feed, local_addr=("127.0.0.1", ports.truth))
    tap = await open_wiretap(ports.follower_api, ports.client)
    link_cfg = cfg.link.model_copy(update={"url": f"udpin://127.0.0.1:{ports.client}"})
    try:
        async with (
            SimProcess(tmp_path, ports, scenario_toml),
            MavsdkVehicleLink(link_cfg, clock) as link,
            asyncio.TaskGroup() as tg,
        ):
            task = tg.create_task(link.run(), name="test.link")
            try:
                async with asyncio.timeout(20):
                    await link.wait_ready()
                yield link, tap, feed, ports
            finally:
                task.cancel()
    finally:
        tap.close()
        transport.close()


def rmse(values: list[float]) -> float:
    a = np.array(values)
    return float(np.sqrt(np.mean(a**2))) if a.size else math.nan


def dump(rec: Recorder, path: Path) -> None:
    """Write the recorded rows as CSV next to the test (for looking at a failed flight)."""
    with path.open("w") as f:
        f.write(
            "t_s,state,setpoint,mode,position_valid,gps_fix,err_m,err_fwd,err_right,err_down,sep_m,alt_m,vz,vh,"
            "dvn,dve,dvd\n"
        )
        for r in rec.rows:
            eh = r.err_heading or (math.nan, math.nan, math.nan)
            dv = r.v_est_err_m_s or (math.nan, math.nan, math.nan)
            f.write(
                f"{r.t_s:.3f},{r.state.value},{r.setpoint},{r.mode},{r.position_valid},{r.gps_fix},"
                f"{r.formation_err_m},{eh[0]:.3f},{eh[1]:.3f},{eh[2]:.3f},{r.separation_m},{r.alt_true_m},"
                f"{r.vz_true_m_s},{r.speed_h_true_m_s},{dv[0]:.3f},{dv[1]:.3f},{dv[2]:.3f}\n"
            )


def any_row(rows: list[Row], pred: Callable[[Row], Any]) -> bool:
    return any(pred(r) for r in rows)
