"""Scenario files (``config/scenarios/*.toml``): leader path, faults, wind, renderer and harness.

Strict: unknown keys are errors, except inside the opaque ``[visual]`` table, which belongs to the
renderer, and ``[companion]``, which belongs to the service (``companion sim`` validates it).

Schema (all times are sim seconds from simulator start; all keys optional unless noted)::

    schema_version = 1
    name = "straight"                 # required
    description = "..."
    seed = 1                          # default seed; `--seed` / World(seed=) override it

    [run]                             # for the evaluation harness (companion sim)
    duration_s = 110.0                # total sim time to fly
    formation_start_s = 35.0          # when formation flight starts to count
    formation_duration_s = 70.0       # >= 60 s of formation in every shipped scenario
    takeoff_altitude_m = 5.0          # the follower's takeoff altitude
    camera_rate_hz = 30.0             # the simulated camera's frame rate (sim time)
    leader_hidden_s = [[50.0, 53.0]]  # windows when the camera does not see the leader at all

    [companion]                       # opaque to the simulator: service config overrides for companion sim
    mission = { gps_loss_policy = "land" }

    [formation]                       # opaque to the simulator: one leader and a follower per plan slot
    plan = "v"                        # config/formations/v.toml; followers named as in the plan
    leader_spawn_ned_m = [12.0, 0.0, 0.0]

    [leader]                          # flown through the leader's own autopilot (offboard)
    type = "straight"                 # none | straight | circle | figure8 | waypoints
    start_s = 35.0                    # the leader holds at its hover point until then
    altitude_m = 5.0
    speed_m_s = 2.0
    accel_m_s2 = 1.0                  # ramp from rest
    heading_deg = 0.0                 # initial direction of travel (0 = north)
    radius_m = 15.0                   # circle; figure8 (each loop)
    clockwise = true                  # circle
    waypoints_ne_m = [[0, 0], [20, 0], [20, 20]]   # waypoints, relative to the hover point
    loop = true                       # waypoints
    yaw = "path"                      # path (face the direction of travel) | fixed (keep heading_deg)
    end_s = 1000.0                    # optional: stop and hold after this time

    [vehicles.follower.gps]           # per vehicle, by name in config/sitl.toml
    noise_scale = 1.0                 # multiplies the default GPS error model
    [[vehicles.follower.gps.outages]]
    at_s = 75.0
    duration_s = 20.0                 # omit for a permanent loss
    kind = "off"                      # off | stuck | wrong
    [[vehicles.follower.gps.jumps]]
    at_s = 50.0
    duration_s = 3.0
    offset_ned_m = [3.0, 0.0, 0.0]

    [vehicles.follower.link]          # MAVLink faults on both of the vehicle's links, both directions
    loss = 0.0                        # baseline packet-loss probability
    latency_ms = 0.0
    jitter_ms = 0.0
    [[vehicles.follower.link.windows]]
    start_s = 50.0
    end_s = 60.0
    loss = 0.3                        # loss inside the window
    latency_ms = 50.0
    cut = false                       # true: nothing gets through

    [timing]                          # the lockstep harness's camera pipeline (the real path has its own)
    camera_latency_ms = 60.0          # frame capture -> its estimate at the mission
    camera_jitter_ms = 0.0            # standard deviation around that (never below 0 in all)
    frame_drop = 0.0                  # probability that a frame never reaches the detector
    detector_load_ms = 0.0            # mean of an exponential extra detection time (a loaded computer)

    [wind]
    mean_speed_m_s = 2.0
    from_deg = 270.0                  # where the wind comes from (meteorological)
    gust_max_m_s = 8.0                # peak gust on top of the mean
    gust_interval_s = 12.0
    turbulence_m_s = 0.3

    [visual]                          # opaque to the simulator: the renderer's table
    fog_density = 0.02
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, ValidationError, field_validator, model_validator

from companion.kernel.config import Section, format_validation_error, read_toml
from companion.kernel.errors import ConfigError
from sitl.config import WorldConfig
from sitl.physics.gps import GpsFailure, GpsJump, GpsNoise, GpsOutage
from sitl.physics.wind import WindParams
from sitl.world.trajectory import Circle, FigureEight, SpeedProfile, Straight, Trajectory, Waypoints

SCHEMA_VERSION = 1


class RunSpec(Section):
    """Timing for the evaluation harness."""

    duration_s: float = Field(120.0, gt=0, le=3600)
    formation_start_s: float = Field(35.0, ge=0)
    formation_duration_s: float = Field(60.0, gt=0)
    takeoff_altitude_m: float = Field(5.0, gt=1.0, le=100.0)
    #: The simulated camera's frame rate, frames per sim second (the D435i runs up to 30 Hz).
    camera_rate_hz: float = Field(30.0, gt=0.0, le=90.0)
    #: Windows [start_s, end_s) in which the camera does not see the leader at all (fault injection).
    leader_hidden_s: tuple[tuple[float, float], ...] = ()
    #: Where the leader spawns off the follower's slot (north, east; the follower faces north), m: the
    #: formation then starts with a join into the slot instead of in it.
    leader_spawn_offset_m: tuple[float, float] = (0.0, 0.0)

    @model_validator(mode="after")
    def _fits(self) -> RunSpec:
        if self.formation_start_s + self.formation_duration_s > self.duration_s + 1e-9:
            raise ValueError("formation_start_s + formation_duration_s exceeds duration_s")
        if any(not (0.0 <= a < b) for a, b in self.leader_hidden_s):
            raise ValueError("leader_hidden_s windows must be [start_s, end_s] with 0 <= start_s < end_s")
        return self

    def leader_hidden(self, t_s: float) -> bool:
        """Whether the camera is blind to the leader at sim time ``t_s``."""
        return any(a <= t_s < b for a, b in self.leader_hidden_s)


class LeaderSpec(Section):
    """The leader's path, flown through its own autopilot in offboard mode."""

    type: Literal["none", "straight", "circle", "figure8", "waypoints"] = "none"
    start_s: float = Field(35.0, ge=0)
    end_s: float | None = Field(None, gt=0)
    altitude_m: float = Field(5.0, gt=1.0, le=100.0)
    speed_m_s: float = Field(2.0, gt=0, le=12.0)
    accel_m_s2: float = Field(1.0, gt=0, le=5.0)
    heading_deg: float = Field(0.0, ge=-360.0, le=360.0)
    radius_m: float = Field(15.0, ge=2.0, le=500.0)
    clockwise: bool = True
    waypoints_ne_m: tuple[tuple[float, float], ...] = ()
    loop: bool = True
    yaw: Literal["path", "fixed"] = "path"

    @model_validator(mode="after")
    def _waypoints(self) -> LeaderSpec:
        if self.type == "waypoints" and len(self.waypoints_ne_m) < 2:
            raise ValueError("type 'waypoints' needs at least two waypoints_ne_m")
        if self.type != "waypoints" and self.waypoints_ne_m:
            raise ValueError("waypoints_ne_m given for a non-waypoint trajectory")
        if any(not (math.isfinite(n) and math.isfinite(e)) for n, e in self.waypoints_ne_m):
            raise ValueError("waypoints must be finite")
        return self

    def trajectory(self) -> Trajectory | None:
        """The path as a pure :class:`~sitl.world.trajectory.Trajectory` (None for ``type = "none"``)."""
        profile = SpeedProfile(self.speed_m_s, self.accel_m_s2)
        heading = math.radians(self.heading_deg)
        if self.type == "straight":
            return Straight(profile, heading)
        if self.type == "circle":
            return Circle(profile, self.radius_m, heading, self.clockwise)
        if self.type == "figure8":
            return FigureEight(profile, self.radius_m, heading)
        if self.type == "waypoints":
            return Waypoints(profile, self.waypoints_ne_m, self.loop)
        return None


class GpsOutageSpec(Section):
    """A GPS failure window (permanent without ``duration_s``)."""

    at_s: float = Field(ge=0)
    duration_s: float | None = Field(None, gt=0)
    kind: Literal["off", "stuck", "wrong"] = "off"


class GpsJumpSpec(Section):
    """A GPS position error added for a while (NED, m)."""

    at_s: float = Field(ge=0)
    duration_s: float = Field(gt=0)
    offset_ned_m: tuple[float, float, float]


class GpsSpec(Section):
    """A vehicle's GPS: noise level, outages, jumps."""

    noise_scale: float = Field(1.0, ge=0.0, le=20.0)
    outages: tuple[GpsOutageSpec, ...] = ()
    jumps: tuple[GpsJumpSpec, ...] = ()

    def noise(self) -> GpsNoise:
        base = GpsNoise()
        k = self.noise_scale
        return GpsNoise(
            white_h_m=base.white_h_m * k,
            bias_h_m=base.bias_h_m * k,
            white_v_m=base.white_v_m * k,
            bias_v_m=base.bias_v_m * k,
            bias_tau_s=base.bias_tau_s,
            vel_white_m_s=base.vel_white_m_s * k,
            eph_m=max(0.3, base.eph_m * k),
            epv_m=max(0.5, base.epv_m * k),
            satellites=base.satellites,
        )

    def outage_windows(self) -> tuple[GpsOutage, ...]:
        return tuple(
            GpsOutage(o.at_s, None if o.duration_s is None else o.at_s + o.duration_s, GpsFailure(o.kind))
            for o in self.outages
        )

    def jump_windows(self) -> tuple[GpsJump, ...]:
        return tuple(GpsJump(j.at_s, j.duration_s, j.offset_ned_m) for j in self.jumps)


class LinkWindowSpec(Section):
    """A window of worse MAVLink conditions (or a cut)."""

    start_s: float = Field(ge=0)
    end_s: float = Field(gt=0)
    loss: float = Field(0.0, ge=0.0, le=1.0)
    latency_ms: float = Field(0.0, ge=0.0, le=10_000.0)
    cut: bool = False

    @model_validator(mode="after")
    def _ordered(self) -> LinkWindowSpec:
        if self.end_s <= self.start_s:
            raise ValueError("end_s must be after start_s")
        return self


class LinkSpec(Section):
    """MAVLink faults on a vehicle's links, both directions."""

    loss: float = Field(0.0, ge=0.0, le=1.0)
    latency_ms: float = Field(0.0, ge=0.0, le=10_000.0)
    jitter_ms: float = Field(0.0, ge=0.0, le=10_000.0)
    windows: tuple[LinkWindowSpec, ...] = ()

    @property
    def is_perfect(self) -> bool:
        return self.loss == 0 and self.latency_ms == 0 and self.jitter_ms == 0 and not self.windows


class DepthGlitchSpec(Section):
    """One camera frame whose depth of the leader reads ``offset_m`` off (negative: nearer)."""

    at_s: float = Field(ge=0.0)
    offset_m: float = Field(ge=-20.0, le=20.0)


class CameraFaultSpec(Section):
    """The follower's camera: depth glitches on the leader (sitl/render/faults.py)."""

    depth_glitches: tuple[DepthGlitchSpec, ...] = ()

    def glitches(self) -> list[tuple[float, float]]:
        return [(g.at_s, g.offset_m) for g in self.depth_glitches]


class VehicleFaultSpec(Section):
    """All faults of one vehicle."""

    gps: GpsSpec = GpsSpec()
    link: LinkSpec = LinkSpec()
    camera: CameraFaultSpec = CameraFaultSpec()


class TimingSpec(Section):
    """The camera pipeline's timing in the lockstep harness, seeded by the run's seed.

    With the follower's ``[vehicles.follower.link]`` latency and jitter (telemetry and setpoints) this is
    what sockets and a loaded computer do to the real path, made repeatable.
    """

    camera_latency_ms: float = Field(60.0, ge=0.0, le=2_000.0)
    camera_jitter_ms: float = Field(0.0, ge=0.0, le=1_000.0)
    frame_drop: float = Field(0.0, ge=0.0, lt=1.0)
    detector_load_ms: float = Field(0.0, ge=0.0, le=1_000.0)

    @property
    def is_fixed(self) -> bool:
        """Every frame delivered after the same latency (no random draw at all)."""
        return self.camera_jitter_ms == 0 and self.frame_drop == 0 and self.detector_load_ms == 0


class WindSpec(Section):
    """Mean wind, gusts and turbulence."""

    mean_speed_m_s: float = Field(0.0, ge=0.0, le=20.0)
    from_deg: float = Field(0.0, ge=-360.0, le=360.0)
    gust_max_m_s: float = Field(0.0, ge=0.0, le=20.0)
    gust_interval_s: float = Field(15.0, gt=0.5)
    turbulence_m_s: float = Field(0.0, ge=0.0, le=5.0)

    def params(self) -> WindParams:
        return WindParams(
            mean_speed_m_s=self.mean_speed_m_s,
            from_deg=self.from_deg,
            gust_max_m_s=self.gust_max_m_s,
            gust_interval_s=self.gust_interval_s,
            turbulence_m_s=self.turbulence_m_s,
        )


class Scenario(Section):
    """One scenario file."""

    schema_version: int = SCHEMA_VERSION
    name: str = Field(pattern=r"^[a-z0-9][a-z0-9_-]{0,47}$")
    description: str = ""
    seed: int = Field(0, ge=0, le=2**32 - 1)
    run: RunSpec = RunSpec()
    leader: LeaderSpec = LeaderSpec()
    vehicles: dict[str, VehicleFaultSpec] = Field(default_factory=dict)
    wind: WindSpec = WindSpec()
    timing: TimingSpec = TimingSpec()
    #: Opaque to the simulator: fog, sun elevation, occluders, leader distance... for the renderer.
    visual: dict[str, Any] = Field(default_factory=dict)
    #: Opaque to the simulator: service config overrides (``companion sim`` validates them).
    companion: dict[str, Any] = Field(default_factory=dict)
    #: The simulator's ``[world]`` keys this scenario changes (an airframe's drag, the heading estimate's
    #: error: e.g. ``config/timing/px4-sih.toml``), applied over the simulator's config.
    world: dict[str, Any] = Field(default_factory=dict)
    #: Opaque to the simulator: a formation of followers (``companion sim`` flies one service per follower).
    formation: dict[str, Any] = Field(default_factory=dict)

    @field_validator("schema_version")
    @classmethod
    def _known_schema(cls, v: int) -> int:
        if not 1 <= v <= SCHEMA_VERSION:
            raise ValueError(f"unsupported scenario schema {v} (this simulator reads {SCHEMA_VERSION})")
        return v

    @field_validator("world")
    @classmethod
    def _world_keys(cls, v: dict[str, Any]) -> dict[str, Any]:
        WorldConfig.model_validate(v)  # each key a [world] key of the simulator, each value in its range
        return v

    def faults(self, vehicle: str) -> VehicleFaultSpec:
        return self.vehicles.get(vehicle, VehicleFaultSpec())

    def world_config(self, base: WorldConfig) -> WorldConfig:
        """``base`` with this scenario's ``[world]`` keys over it."""
        if not self.world:
            return base
        return WorldConfig.model_validate({**base.model_dump(), **self.world})

    @property
    def gps_loss_s(self) -> float | None:
        """When the follower's GPS first fails (for reports), or None."""
        starts = [o.at_s for o in self.faults("follower").gps.outages]
        return min(starts) if starts else None


def load_scenario(path: Path) -> Scenario:
    """Read and validate a scenario file; every problem becomes one line of a :class:`ConfigError`."""
    data = read_toml(path)
    try:
        return Scenario.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(str(path), format_validation_error(exc)) from None


def find_scenario(name_or_path: str, scenario_dir: Path) -> Path:
    """A scenario name (``straight``, or a variant's) or a path -> the file path.

    Names are looked up in ``scenario_dir`` and its ``variants`` folder; an unknown one is a one-line
    :class:`ConfigError` that lists the known names.
    """
    p = Path(name_or_path)
    if p.suffix == ".toml" or p.exists():
        return p
    for candidate in (
        scenario_dir / f"{name_or_path}.toml",
        scenario_dir / "variants" / f"{name_or_path}.toml",
    ):
        if candidate.exists():
            return candidate
    known = sorted(
        q.stem for q in [*scenario_dir.glob("*.toml"), *(scenario_dir / "variants").glob("*.toml")]
    )
    raise ConfigError(name_or_path, [f"no such scenario in {scenario_dir} (known: {', '.join(known)})"])
