"""One world of PX4 SITL vehicles: what ``sitl serve --autopilot px4`` flies, with the scenario on top.

Each vehicle of the simulator config is a :class:`~sitl.px4.instance.Px4Instance`. They share one world
through SIH's home parameters: vehicle ``k`` starts with ``SIH_LOC_LAT0/LON0/H0`` at its spawn point in the
config's world frame, so its ground truth (``HIL_STATE_QUATERNION``, geodetic) maps back into that frame
with the same projection. Each PX4 keeps its own local NED frame with its origin where it booted, as on
the project's own autopilot and on real vehicles.

The scenario on top, through PX4's own interfaces only:

* the leader's path is flown by the same :class:`~sitl.world.pilot.TrajectoryPilot` as on the project's
  autopilot, over MAVLink (arm, take-off, offboard position + velocity + acceleration setpoints);
* wind: the scenario's mean wind as SIH's ``SIH_WIND_N`` / ``SIH_WIND_E`` at start. Gusts and turbulence
  are not flown: changing SIH's wind means a parameter write, and PX4 saves its parameters to file on each
  one (at a few hertz its parameter export failed and the instance stalled);
* GPS loss (``kind = "off"``): PX4's simulated GPS driver is stopped (``sensor_gps_sim stop``) at the
  outage's time and started again at its end. Stuck or wrong fixes, GPS jumps and link faults have no
  PX4-side equivalent here and are refused when the world is made.

Time: PX4 runs in lockstep with SIH, so its boot clock is the simulation's time. The world's ``t_s`` is
the follower's PX4 boot clock (the instances start within milliseconds of each other): scenario times
count from PX4's boot, as they count from the project's autopilot's start.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot.autopilot import AutopilotStatus
from sitl.autopilot.modes import NavState, nav_state_from_mode
from sitl.autopilot.state import GlobalEstimate, Home
from sitl.config import SitlConfig
from sitl.physics.dynamics import VehicleTruth
from sitl.physics.geo import LocalProjection
from sitl.physics.wind import WindParams
from sitl.px4.instance import MAX_INSTANCE, Px4Build, Px4Instance, Px4StartError, free_instance_base
from sitl.px4.link import Px4Link, StatusText
from sitl.serve.server import SEVERITY
from sitl.world.pilot import TrajectoryPilot
from sitl.world.scenario import Scenario

log = logging.getLogger(__name__)

#: Wall time allowed for every PX4 to boot, get a GPS fix and set home, s (times the speed factor).
READY_TIMEOUT_S = 90.0
#: Truth is extrapolated from the last sample by at most this much sim time, s.
MAX_EXTRAPOLATION_S = 0.05
#: The pilot's and the fault schedule's step, sim s.
PILOT_PERIOD_S = 0.02
#: GLOBAL_POSITION_INT's heading when the autopilot does not know it.
UINT16_UNKNOWN = 65535
#: A vehicle whose clock has not moved for this long (wall s) has stopped: the run ends with its log.
STALL_S = 10.0


class Px4ScenarioError(Px4StartError):
    """The scenario asks for something the PX4 backend cannot do."""

    exit_code = 2


def unsupported(scenario: Scenario | None) -> list[str]:
    """What in ``scenario`` the PX4 backend cannot fly, one line each (empty: all of it can)."""
    if scenario is None:
        return []
    out = []
    for name, faults in scenario.vehicles.items():
        if not faults.link.is_perfect:
            out.append(f"[vehicles.{name}.link]: link faults are not simulated with PX4")
        out.extend(
            f"[vehicles.{name}.gps.outages]: kind {o.kind!r} (PX4 SITL can only lose its GPS: 'off')"
            for o in faults.gps.outages
            if o.kind != "off"
        )
        if faults.gps.jumps:
            out.append(f"[vehicles.{name}.gps.jumps]: GPS jumps are not simulated with PX4")
    return out


def mode_name(custom_mode: int) -> str:
    """PX4's name for a HEARTBEAT ``custom_mode`` (main mode in bits 16-23, AUTO sub-mode in 24-31)."""
    main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
    nav = nav_state_from_mode(main, sub)
    return nav.ui_name if nav is not None else f"main {main} sub {sub}"


@dataclass(slots=True)
class Px4Vehicle:
    """One vehicle of the world: its PX4 process, its display link, and where it started."""

    name: str
    sysid: int
    role: str
    spawn_ned_m: tuple[float, float, float]
    instance: Px4Instance
    link: Px4Link


class Px4PilotPort:
    """What :class:`~sitl.world.pilot.TrajectoryPilot` needs of an autopilot, over PX4's MAVLink.

    The pilot reads only what a MAVLink client can (HEARTBEAT, SYS_STATUS, EXTENDED_SYS_STATE,
    LOCAL_POSITION_NED, HOME_POSITION) and writes messages from the vehicle's onboard computer.
    """

    def __init__(self, vehicle: Px4Vehicle, world: Px4World) -> None:
        self.vehicle = vehicle
        self.world = world
        self.name = vehicle.name
        self.sysid = vehicle.sysid

    @property
    def home(self) -> Home | None:
        h = self.vehicle.link.home
        if h is None:
            return None
        return Home(h.latitude * 1e-7, h.longitude * 1e-7, h.altitude * 1e-3, h.x, h.y, h.z)

    def time_boot_ms(self) -> int:
        return int(self.vehicle.link.boot_s * 1000.0)

    def handle_message(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        self.vehicle.link.send(msg, src_system, src_component)

    def status(self) -> AutopilotStatus:
        link = self.vehicle.link
        hb, lp, ext = link.heartbeat, link.local_position, link.extended_state
        armed = hb is not None and bool(hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)
        nav = NavState.AUTO_LOITER
        if hb is not None:
            cm = int(hb.custom_mode)
            nav = nav_state_from_mode((cm >> 16) & 0xFF, (cm >> 24) & 0xFF) or NavState.AUTO_LOITER
        gps_ok = link.gps_ok()
        return AutopilotStatus(
            t_s=self.world.t_s,
            armed=armed,
            nav_state=nav,
            landed=ext is None or ext.landed_state == mavlink.MAV_LANDED_STATE_ON_GROUND,
            global_position_ok=gps_ok,
            local_position_ok=link.horizontal_estimate_ok(),
            home_set=link.home is not None,
            p_ned_m=(lp.x, lp.y, lp.z) if lp is not None else (0.0, 0.0, 0.0),
            v_ned_m_s=(lp.vx, lp.vy, lp.vz) if lp is not None else (0.0, 0.0, 0.0),
            yaw_rad=0.0,
        )


class Px4World:
    """N PX4 SITL vehicles in one world, flying a scenario; :class:`~sitl.serve.server.SimHandle`'s interface.

    Components (the camera server, the run's recorders) see ``t_s``, ``names``, ``truth(name)``,
    ``wait_until(t_s)``, ``mode(name)``, ``status_texts(name)`` and ``scenario``, as on the project's own
    autopilot.
    """

    def __init__(
        self,
        cfg: SitlConfig,
        scenario: Scenario | None,
        build: Px4Build,
        *,
        speed_factor: float = 1.0,
        seed: int | None = None,
        log_dir: Path | None = None,
    ) -> None:
        problems = unsupported(scenario)
        if problems:
            raise Px4ScenarioError("scenario cannot be flown on PX4: " + "; ".join(problems))
        self.cfg = cfg
        self.scenario = scenario
        self.speed_factor = speed_factor
        self.seed = seed if seed is not None else (scenario.seed if scenario is not None else cfg.world.seed)
        self.log_dir = log_dir
        w = cfg.world
        self.projection = LocalProjection(w.home_lat_deg, w.home_lon_deg, w.home_alt_m)
        self.wind = scenario.wind.params() if scenario is not None else WindParams()
        base = cfg.px4.instance_base
        if base < 0:
            base = free_instance_base(len(cfg.vehicles))
        elif base + len(cfg.vehicles) - 1 > MAX_INSTANCE:
            raise Px4StartError(
                f"[px4] instance_base {base}: {len(cfg.vehicles)} vehicles need instances up to 9"
            )
        wp = self.wind
        to_rad = math.radians(wp.from_deg + 180.0)  # from_deg is where the wind comes from
        mean_n, mean_e = wp.mean_speed_m_s * math.cos(to_rad), wp.mean_speed_m_s * math.sin(to_rad)
        self.vehicles: list[Px4Vehicle] = []
        for k, vc in enumerate(cfg.vehicles):
            lat, lon, _ = self.projection.to_geodetic(vc.spawn_ned_m[0], vc.spawn_ned_m[1], 0.0)
            params = {
                "MAV_SYS_ID": float(k + 1),
                "SIH_LOC_LAT0": lat,
                "SIH_LOC_LON0": lon,
                "SIH_LOC_H0": w.home_alt_m,
                "SIH_WIND_N": mean_n,
                "SIH_WIND_E": mean_e,
                **vc.params,
            }
            inst = Px4Instance(build, base + k, vc.name, params, speed_factor=speed_factor)
            link = Px4Link(vc.name, k + 1, inst.ports.sih_local, inst.ports.sih_remote)
            self.vehicles.append(Px4Vehicle(vc.name, k + 1, vc.role, vc.spawn_ned_m, inst, link))
        self._by_name = {v.name: v for v in self.vehicles}
        self._clock = next((v for v in self.vehicles if v.role == "follower"), self.vehicles[0])
        self.ready = False
        self.flight_logs: list[Path] = []

    # ------------------------------------------------------------------ the SimHandle interface
    @property
    def names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.vehicles)

    @property
    def t_s(self) -> float:
        """World time, s: the follower's PX4 boot clock."""
        return self._clock.link.boot_s

    def vehicle(self, name: str) -> Px4Vehicle:
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"no vehicle {name!r} (have {', '.join(self._by_name)})") from None

    def truth(self, name: str) -> VehicleTruth:
        """PX4's ground truth of ``name`` now, in the config's world NED frame.

        The last ``HIL_STATE_QUATERNION`` (100 Hz), moved on at its velocity for the time since it arrived
        (at most :data:`MAX_EXTRAPOLATION_S`), so both vehicles are seen at the same instant.
        """
        s = self.vehicle(name).link.truth
        if s is None:
            raise Px4StartError(f"px4 {name}: no ground truth received yet")
        dt_s = min(MAX_EXTRAPOLATION_S, max(0.0, (time.monotonic() - s.mono_s) * self.speed_factor))
        n, e, d = self.projection.to_ned(s.lat_deg, s.lon_deg, s.alt_m)
        v = np.array(s.v_ned_m_s)
        return VehicleTruth(
            self.t_s,
            np.array([n, e, d]) + v * dt_s,
            v,
            np.array(s.q_wxyz),
            np.array(s.omega_body_rad_s),
        )

    async def wait_until(self, t_s: float) -> None:
        """Return once world time >= ``t_s`` (woken by the follower's ground-truth stream)."""
        link = self._clock.link
        while self.t_s < t_s:
            await link.received.wait()

    def on_time(self, callback: Callable[[float], None]) -> None:
        """Have ``callback(t_s)`` called with each new world time, from the thread that receives it.

        The run's clock for the service is published this way: straight from PX4's clock stream, however
        busy this process's event loop is.
        """
        self._clock.link.on_clock.append(callback)

    def global_estimate(self, name: str) -> GlobalEstimate | None:
        """PX4's own global position of ``name`` (its last GLOBAL_POSITION_INT, 10 Hz); None before one."""
        g = self.vehicle(name).link.global_position
        if g is None:
            return None
        hdg_deg = float(g.hdg) * 0.01 if g.hdg != UINT16_UNKNOWN else 0.0
        return GlobalEstimate(
            g.lat * 1e-7, g.lon * 1e-7, g.alt * 1e-3, (g.vx * 0.01, g.vy * 0.01, g.vz * 0.01), hdg_deg
        )

    def mode(self, name: str) -> tuple[str, bool]:
        """PX4's flight mode of ``name`` (its UI name) and whether it is armed, from its HEARTBEAT."""
        hb = self.vehicle(name).link.heartbeat
        if hb is None:
            return "unknown", False
        return mode_name(int(hb.custom_mode)), bool(hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)

    def status_texts(self, name: str) -> list[tuple[float, str, str]]:
        """Every STATUSTEXT of ``name`` so far: (world time s, severity, text)."""
        return [self._text_row(t) for t in self.vehicle(name).link.texts]

    def _text_row(self, t: StatusText) -> tuple[float, str, str]:
        sev = SEVERITY[t.severity] if 0 <= t.severity < len(SEVERITY) else str(t.severity)
        return t.time_s, sev, t.text

    # ------------------------------------------------------------------ running
    async def run(
        self,
        stop: asyncio.Event,
        components: Sequence[Callable[[Any], Awaitable[None]]] = (),
        on_ready: Callable[[], None] | None = None,
    ) -> None:
        """Start every PX4, wait until all are ready, then fly the scenario and run ``components``."""
        loop = asyncio.get_running_loop()
        try:
            for v in self.vehicles:
                v.link.open(loop)
                v.instance.start()
            await self._wait_ready(stop)
            if stop.is_set():
                return
            async with asyncio.TaskGroup() as tg:
                tasks = [
                    tg.create_task(self._watch(), name="px4.watch"),
                    tg.create_task(self._fly(), name="px4.scenario"),
                ]
                tasks += [
                    tg.create_task(_call(c, self), name=f"px4.component.{getattr(c, '__qualname__', i)}")
                    for i, c in enumerate(components)
                ]
                if on_ready is not None:
                    on_ready()
                await stop.wait()
                for task in tasks:
                    task.cancel()
        finally:
            self.close()

    def close(self) -> None:
        """Stop every PX4, keep its flight log (when ``log_dir`` is set) and remove its working folder."""
        for v in self.vehicles:
            v.link.close()
            self.flight_logs += v.instance.remove(self.log_dir)

    async def _wait_ready(self, stop: asyncio.Event) -> None:
        deadline = time.monotonic() + READY_TIMEOUT_S
        next_request = 0.0
        while not stop.is_set():
            for v in self.vehicles:
                if not v.instance.running:
                    raise Px4StartError(f"px4 {v.name} exited while starting; its log:\n{v.instance.tail()}")
            now = time.monotonic()
            if now >= next_request:
                next_request = now + 1.0
                for v in self.vehicles:
                    v.link.heartbeat_out()
                    if not v.link.streams_flowing():
                        v.link.request_streams()
            if all(
                v.link.streams_flowing() and v.link.gps_ok() and v.link.home is not None
                for v in self.vehicles
            ):
                break
            if now > deadline:
                waiting = [v.name for v in self.vehicles if v.link.home is None or not v.link.gps_ok()]
                raise Px4StartError(
                    f"PX4 not ready within {READY_TIMEOUT_S:.0f} s (no GPS fix or home: {', '.join(waiting)})"
                )
            await asyncio.sleep(0.05)
        self.ready = True
        log.info(
            "px4: %d vehicles ready (instances %s), world time %.1f s",
            len(self.vehicles),
            ", ".join(str(v.instance.instance) for v in self.vehicles),
            self.t_s,
        )

    async def _watch(self) -> None:
        """Mode changes into the log; a PX4 that dies ends the run with its log (never a silent stop)."""
        modes: dict[str, tuple[str, bool]] = {}
        clocks = {v.name: (v.link.boot_s, time.monotonic()) for v in self.vehicles}
        next_heartbeat = 0.0
        while True:
            now = time.monotonic()
            if now >= next_heartbeat:
                next_heartbeat = now + 1.0
                for v in self.vehicles:
                    v.link.heartbeat_out()
            for v in self.vehicles:
                last_s, since = clocks[v.name]
                if v.link.boot_s != last_s:
                    clocks[v.name] = (v.link.boot_s, now)
                elif now - since > STALL_S:
                    raise Px4StartError(
                        f"px4 {v.name} stopped at t = {last_s:.1f} s (its clock did not move for "
                        f"{STALL_S:.0f} s); its log:\n{v.instance.tail()}"
                    )
                mode = self.mode(v.name)
                if modes.get(v.name) != mode:
                    modes[v.name] = mode
                    log.info(
                        "px4 %s: %s (%s) at t = %.2f s",
                        v.name,
                        mode[0],
                        "armed" if mode[1] else "disarmed",
                        self.t_s,
                    )
                if not v.instance.running:
                    raise Px4StartError(
                        f"px4 {v.name} died at t = {self.t_s:.1f} s; its log:\n{v.instance.tail()}"
                    )
            await asyncio.sleep(0.2)

    async def _fly(self) -> None:
        """The leader's pilot and the GPS schedule, stepped on world time.

        A PX4 shell command takes a new process and can take seconds on a busy host, so each runs in a task
        of its own: the pilot's 20 Hz setpoints never wait for one.
        """
        pilots = []
        gps_events: list[tuple[float, Px4Vehicle, bool]] = []
        if self.scenario is not None:
            traj = self.scenario.leader.trajectory()
            leader = next((v for v in self.vehicles if v.role == "leader"), None)
            if traj is not None and leader is not None:
                pilots.append(TrajectoryPilot(Px4PilotPort(leader, self), self.scenario.leader, traj))
            for v in self.vehicles:
                for o in self.scenario.faults(v.name).gps.outage_windows():
                    gps_events.append((o.start_s, v, False))
                    if o.end_s is not None:
                        gps_events.append((o.end_s, v, True))
        gps_events.sort(key=lambda e: e[0])
        wp = self.wind
        if wp.gust_max_m_s > 0 or wp.turbulence_m_s > 0:
            log.warning(
                "px4: the scenario gusts (%.1f m/s) and turbulence (%.1f m/s) not flown: mean wind only",
                wp.gust_max_m_s,
                wp.turbulence_m_s,
            )
        while True:
            t_s = self.t_s
            for p in pilots:
                p.update(t_s)
            while gps_events and gps_events[0][0] <= t_s:
                at_s, v, on = gps_events.pop(0)
                log.info(
                    "px4 %s: GPS %s at t = %.2f s (scheduled %.2f s)",
                    v.name,
                    "on" if on else "OFF",
                    t_s,
                    at_s,
                )
                await v.instance.shell("sensor_gps_sim", "start" if on else "stop")
            await self.wait_until(t_s + PILOT_PERIOD_S)


async def _call(component: Callable[[Any], Awaitable[None]], world: Px4World) -> None:
    await component(world)


__all__ = ["Px4ScenarioError", "Px4World", "mode_name", "unsupported"]
