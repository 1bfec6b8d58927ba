"""The lockstep simulation core: N vehicles, their autopilots, wind, scripted pilots. No sockets.

Use it directly for fast tests and evaluation (the UDP server in :mod:`sitl.serve.server` drives the same
object in real time)::

    from sitl.config import load_sitl_config
    from sitl.world.scenario import load_scenario
    from sitl.world.lockstep import World

    world = World(load_sitl_config(path), load_scenario(scenario_path), seed=3)
    api = world.link("follower")              # MessageLink: the follower's API link, streams on
    api.send(msg, src_system=245, src_component=190)   # any pymavlink message object
    while world.t_s < 60.0:
        world.step()                          # one physics tick (1 / physics_rate_hz)
        for m in api.receive(): ...           # what the autopilot sent (after link faults)
    truth = world.truth("leader")             # VehicleTruth: ground truth for renderer/evaluation

Frames: ``truth()`` is in the shared world NED frame (origin: ``[world] home``, on the ground).
Each autopilot reports in its own local NED frame with its origin at its spawn point, like separate
PX4 instances do; :meth:`World.origin_offset_ned_m` converts between the two.

Time: ``t_s`` starts at 0 and advances only through :meth:`step`; autopilots stamp ``time_boot_ms``
and SYSTEM_TIME from it. ``speed_factor`` only scales COM_OF_LOSS_T (as PX4_SIM_SPEED_FACTOR does);
leave it at 1 in lockstep, where clients produce setpoints in sim time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from sitl.autopilot.autopilot import Autopilot
from sitl.autopilot.state import LINK_API, LINK_GCS, AutopilotState
from sitl.config import SitlConfig
from sitl.physics.dynamics import QuadDynamics, VehicleTruth
from sitl.physics.geo import LocalProjection
from sitl.physics.gps import GpsNoise, GpsSensor
from sitl.physics.heading_error import HeadingError, HeadingErrorModel
from sitl.physics.wind import WindModel, WindParams
from sitl.world.links import LinkFaults, MessageLink
from sitl.world.pilot import AutopilotPort, TrajectoryPilot
from sitl.world.scenario import LinkSpec, Scenario

__all__ = ["LINK_API", "LINK_GCS", "VehicleTruth", "World"]

OUTER_RATE_HZ = 50.0
#: 2026-01-01T00:00:00Z: SYSTEM_TIME's epoch in lockstep runs (repeatable); serve uses the wall clock.
DEFAULT_EPOCH_UNIX_S = 1_767_225_600.0


@dataclass(slots=True)
class SimVehicle:
    """One vehicle: its dynamics, autopilot and message links."""

    name: str
    sysid: int
    role: str
    dyn: QuadDynamics
    autopilot: Autopilot
    links: tuple[MessageLink, MessageLink]
    spawn_ned_m: tuple[float, float, float]


def heading_error(cfg: SitlConfig, rng: np.random.Generator) -> HeadingError | None:
    """The heading-estimate error the config asks for (None: a perfect estimate)."""
    w = cfg.world
    if w.heading_bias_deg == 0.0 and w.heading_wander_deg == 0.0:
        return None
    return HeadingError(
        rng, HeadingErrorModel(w.heading_bias_deg, w.heading_wander_deg, w.heading_wander_tau_s)
    )


def gps_noise(cfg: SitlConfig, noise: GpsNoise) -> GpsNoise:
    """The scenario's GPS noise with the world's velocity wander (``[world] gps_velocity_wander_*``)."""
    w = cfg.world
    if w.gps_velocity_wander_m_s == 0.0:
        return noise
    return replace(noise, vel_bias_m_s=w.gps_velocity_wander_m_s, vel_bias_tau_s=w.gps_velocity_wander_tau_s)


class World:
    """The simulation in lockstep.

    Args:
        cfg: Simulator configuration (vehicles, rates, home).
        scenario: Optional scenario: leader path, faults, wind.
        seed: Random seed (default: the scenario's seed, else the config's).
        speed_factor: Sim/wall ratio the clients experience (only scales COM_OF_LOSS_T).
        epoch_unix_s: Unix time at sim time 0.
    """

    def __init__(
        self,
        cfg: SitlConfig,
        scenario: Scenario | None = None,
        *,
        seed: int | None = None,
        speed_factor: float = 1.0,
        epoch_unix_s: float = DEFAULT_EPOCH_UNIX_S,
    ) -> None:
        if scenario is not None and scenario.world:
            cfg = cfg.model_copy(update={"world": scenario.world_config(cfg.world)})
        self.cfg = cfg
        self.scenario = scenario
        if seed is None:
            seed = scenario.seed if scenario is not None else cfg.world.seed
        self.seed = seed
        self.dt_s = 1.0 / cfg.world.physics_rate_hz
        self._outer_every = round(cfg.world.physics_rate_hz / OUTER_RATE_HZ)
        self._outer_dt_s = self._outer_every * self.dt_s
        self._tick = 0
        self.projection = LocalProjection(
            cfg.world.home_lat_deg, cfg.world.home_lon_deg, cfg.world.home_alt_m
        )
        root = np.random.SeedSequence(seed)
        streams = root.spawn(len(cfg.vehicles) * 5 + 1)
        self.vehicles: list[SimVehicle] = []
        self._by_name: dict[str, SimVehicle] = {}
        for i, vc in enumerate(cfg.vehicles):
            faults = scenario.faults(vc.name) if scenario is not None else None
            s = streams[i * 5 : i * 5 + 5]
            dyn = QuadDynamics(
                self.projection,
                vc.spawn_ned_m,
                math.radians(vc.spawn_yaw_deg),
                self.dt_s,
                linear_drag_per_s=cfg.world.linear_drag_per_s,
            )
            gps = GpsSensor(
                self.projection,
                np.random.default_rng(s[0]),
                noise=gps_noise(cfg, faults.gps.noise() if faults is not None else GpsNoise()),
                outages=faults.gps.outage_windows() if faults is not None else (),
                jumps=faults.gps.jump_windows() if faults is not None else (),
            )
            ap = Autopilot(
                AutopilotState(
                    name=vc.name,
                    sysid=i + 1,
                    dyn=dyn,
                    world=self.projection,
                    spawn_ned_m=vc.spawn_ned_m,
                    rng=np.random.default_rng(s[1]),
                    gps=gps,
                    speed_factor=speed_factor,
                    epoch_unix_s=epoch_unix_s,
                    params=dict(vc.params),
                    heading_error=heading_error(cfg, np.random.default_rng(s[4])),
                )
            )
            link_spec = faults.link if faults is not None else LinkSpec()
            links = tuple(
                MessageLink(
                    ap,
                    k,
                    LinkFaults(link_spec, np.random.default_rng(s[2 + k])),
                    LinkFaults(link_spec, np.random.default_rng(s[2 + k].spawn(1)[0])),
                    self._now,
                )
                for k in (LINK_API, LINK_GCS)
            )
            v = SimVehicle(vc.name, i + 1, vc.role, dyn, ap, (links[0], links[1]), vc.spawn_ned_m)
            self.vehicles.append(v)
            self._by_name[vc.name] = v
        wind_params = scenario.wind.params() if scenario is not None else WindParams()
        self.wind = WindModel(wind_params, np.random.default_rng(streams[-1]))
        self._wind_active = wind_params != WindParams()
        self.pilots: list[TrajectoryPilot] = []
        if scenario is not None:
            traj = scenario.leader.trajectory()
            leader = next((v for v in self.vehicles if v.role == "leader"), None)
            if traj is not None and leader is not None:
                self.pilots.append(TrajectoryPilot(AutopilotPort(leader.autopilot), scenario.leader, traj))
        self.wind_ned_m_s: tuple[float, float, float] = (0.0, 0.0, 0.0)
        # Flat lists for the per-tick loop (attribute chains cost as much as the work here).
        self._pairs = [(v.autopilot, v.dyn) for v in self.vehicles]
        self._links = [link for v in self.vehicles for link in v.links]
        self._links_open = False

    def _now(self) -> float:
        return self._tick * self.dt_s

    @property
    def t_s(self) -> float:
        """Sim time, s (exact multiple of the physics step)."""
        return self._tick * self.dt_s

    @property
    def names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.vehicles)

    def vehicle(self, name: str) -> SimVehicle:
        try:
            return self._by_name[name]
        except KeyError:
            raise KeyError(f"no vehicle {name!r} (have {', '.join(self._by_name)})") from None

    def autopilot(self, name: str) -> Autopilot:
        return self.vehicle(name).autopilot

    def link(self, name: str, index: int = LINK_API) -> MessageLink:
        """The vehicle's MAVLink link ``index`` (0 API, 1 GCS), opened: its streams start."""
        self._links_open = True
        return self.vehicle(name).links[index].open()

    def truth(self, name: str) -> VehicleTruth:
        """Ground truth of ``name`` now (world NED frame)."""
        return self.vehicle(name).dyn.truth(self.t_s)

    def origin_offset_ned_m(self, name: str) -> tuple[float, float, float]:
        """World-frame position of ``name``'s local origin (add it to local NED to get world NED)."""
        n, e, _ = self.vehicle(name).spawn_ned_m
        return (n, e, 0.0)

    def step(self) -> None:
        """Advance one physics tick: inner loops, dynamics, and every 1/50 s the outer loops."""
        k = self._tick + 1
        t = k * self.dt_s
        dt = self.dt_s
        if self._links_open:
            for link in self._links:
                if link._inbound:
                    link.deliver_due(t)
        for ap, dyn in self._pairs:
            ap.set_time(t)
            dyn.step(*ap.inner_update(dt))
        self._tick = k
        if k % self._outer_every == 0:
            if self._wind_active:
                self.wind_ned_m_s = self.wind.sample(t)
                for v in self.vehicles:
                    v.dyn.set_wind_ned(*self.wind_ned_m_s)
            for v in self.vehicles:
                v.autopilot.outer_update(t, self._outer_dt_s)
            for p in self.pilots:
                p.update(t)
        if self._links_open:
            for v in self.vehicles:
                ap = v.autopilot
                if ap.any_link_active:
                    ap.mavlink.service_links(t)
                    for link in v.links:
                        if link.active:
                            link.collect(t)

    def run_until(self, t_s: float) -> None:
        """Step until sim time reaches ``t_s``."""
        n = round((t_s - self.t_s) / self.dt_s)
        for _ in range(max(0, n)):
            self.step()
