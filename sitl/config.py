"""The simulator's configuration (``config/sitl.toml``): frozen, strict and versioned like the service's.

Environment overrides use the ``SITL_`` prefix (``SITL_WORLD__SPEED_FACTOR=4``,
``SITL_MAVLINK__API_REMOTE_PORT_BASE=24540``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from pydantic import Field, ValidationError, field_validator, model_validator

from companion.kernel.config import Section, deep_merge, env_overrides, format_validation_error, read_toml
from companion.kernel.errors import ConfigError

SCHEMA_VERSION = 1


class WorldConfig(Section):
    """Time and randomness for the whole simulation."""

    speed_factor: float = Field(1.0, gt=0, le=100)
    seed: int = Field(0, ge=0, le=2**32 - 1)
    #: Physics and inner-loop rate. 200 Hz is PX4's IMU_INTEG_RATE: the rate at which EKF2 publishes
    #: attitude and mc_att_control runs; the rate loop runs on the same samples here.
    physics_rate_hz: float = Field(200.0, ge=100, le=2000)
    #: Home of the world frame (on the ground); vehicles spawn relative to it.
    home_lat_deg: float = Field(47.397742, ge=-80, le=80)
    home_lon_deg: float = Field(8.545594, ge=-180, le=180)
    home_alt_m: float = Field(488.0, ge=-400, le=9000)
    #: PX4's heading estimate off the true heading: a bias drawn per flight (1-sigma, deg) plus a slow wander
    #: (1-sigma, deg; time constant s); the camera's bearings turn with it. 0 and 0: a perfect estimate (the
    #: default). PX4 SITL's, as measured: 4, 3 and 15 s.
    heading_bias_deg: float = Field(0.0, ge=0.0, le=45.0)
    heading_wander_deg: float = Field(0.0, ge=0.0, le=45.0)
    heading_wander_tau_s: float = Field(15.0, gt=0.0, le=3600.0)
    #: A further isotropic linear drag on every vehicle, per unit mass (1/s: N/(m/s) per kg), on the
    #: air-relative velocity. 0: the airframe's own (a few degrees of tilt at 3 m/s). PX4 SIH's quadrotor
    #: has 1.0 (SIH_KDV 1 N/(m/s) on 1 kg): 11 deg of tilt at 2 m/s (config/profiles/px4-sih.toml).
    linear_drag_per_s: float = Field(0.0, ge=0.0, le=5.0)
    #: GPS's horizontal velocity off by a slow wander on every vehicle, 1-sigma per axis (m/s) with a time
    #: constant (s); 0: the receiver's white noise only. The autopilot's estimate follows it and its velocity
    #: loop tracks the estimate, so the vehicle strays from its commands by it. PX4 SITL's estimated velocity,
    #: against SIH's truth in formation flight: 0.18-0.26 m/s RMS per axis, 1/e time 3-4 s.
    gps_velocity_wander_m_s: float = Field(0.0, ge=0.0, le=2.0)
    gps_velocity_wander_tau_s: float = Field(3.0, gt=0.0, le=600.0)

    @field_validator("physics_rate_hz")
    @classmethod
    def _multiple_of_outer(cls, v: float) -> float:
        # The 50 Hz outer loop runs every N physics ticks.
        if abs(v / 50.0 - round(v / 50.0)) > 1e-9:
            raise ValueError("must be a multiple of 50 Hz")
        return v


class MavlinkConfig(Section):
    """Where each vehicle talks, PX4 SITL's convention for vehicle i (system id i+1).

    API link: bound to ``api_local_port_base + i``, sending to ``remote_host:api_remote_port_base + i``
    (so MAVSDK's ``udpin://0.0.0.0:14540`` works as with PX4). GCS link: bound to
    ``gcs_local_port_base + i``, sending to ``remote_host:gcs_remote_port`` (QGroundControl).
    """

    bind_host: str = "0.0.0.0"  # noqa: S104 - PX4 SITL listens on all interfaces too
    remote_host: str = "127.0.0.1"
    api_local_port_base: int = Field(14580, ge=1024, le=65000)
    api_remote_port_base: int = Field(14540, ge=1024, le=65000)
    gcs_enabled: bool = True
    gcs_local_port_base: int = Field(18570, ge=1024, le=65000)
    gcs_remote_port: int = Field(14550, ge=1024, le=65535)


class Px4Config(Section):
    """The PX4 backend (``sitl serve --autopilot px4``): one real PX4 SITL process per vehicle."""

    #: A PX4 SITL build's ``bin/px4`` (its ``etc/`` beside ``bin/``), or a name on PATH.
    #: Environment: ``SITL_PX4__BINARY``.
    binary: str = "px4"
    #: Where each vehicle's ULog flight log and PX4 console log are copied when it stops ("": nowhere).
    log_dir: str = ""
    #: PX4 instance number of the first vehicle (vehicle k is instance base + k: UDP 14540 + base + k ...);
    #: -1 picks the lowest base whose ports are all free.
    instance_base: int = Field(-1, ge=-1, le=9)


class VehicleConfig(Section):
    """One simulated vehicle."""

    name: str = Field(pattern=r"^[a-z][a-z0-9_]{0,31}$")
    role: str = "follower"
    #: Spawn position in the shared world NED frame, m (down is ignored: vehicles start on the ground).
    spawn_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    spawn_yaw_deg: float = Field(0.0, ge=-360, le=360)
    #: PX4 parameter overrides for this vehicle (name -> value).
    params: dict[str, float] = Field(default_factory=dict)


class SitlConfig(Section):
    """The whole simulator configuration."""

    schema_version: int = SCHEMA_VERSION
    world: WorldConfig = WorldConfig()
    mavlink: MavlinkConfig = MavlinkConfig()
    px4: Px4Config = Px4Config()
    vehicles: tuple[VehicleConfig, ...] = (
        VehicleConfig(name="leader", role="leader", spawn_ned_m=(8.0, 0.0, 0.0)),
        VehicleConfig(name="follower", role="follower"),
    )

    @model_validator(mode="after")
    def _unique_names(self) -> SitlConfig:
        names = [v.name for v in self.vehicles]
        if len(set(names)) != len(names):
            raise ValueError("vehicle names must be unique")
        if not 1 <= len(names) <= 16:
            raise ValueError("between 1 and 16 vehicles")
        return self


def load_sitl_config(path: Path | None, environ: Mapping[str, str] | None = None) -> SitlConfig:
    """Load ``config/sitl.toml``-style files with ``SITL_*`` overrides on top."""
    data = read_toml(path) if path is not None else {}
    data = deep_merge(data, env_overrides(os.environ if environ is None else environ, prefix="SITL_"))
    try:
        return SitlConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(str(path or "<defaults>"), format_validation_error(exc)) from None
