"""The simulator's configuration (``config/sitl.toml``): frozen, strict and versioned like the service's.

Environment overrides use the ``SITL_`` prefix (``SITL_WORLD__SPEED_FACTOR=4``).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from pydantic import Field, ValidationError

from companion.config import Section, deep_merge, env_overrides, format_validation_error, read_toml
from companion.errors import ConfigError

SCHEMA_VERSION = 1


class WorldConfig(Section):
    """Time and randomness for the whole simulation."""

    speed_factor: float = Field(1.0, gt=0, le=100)
    seed: int = 0
    physics_rate_hz: float = Field(250.0, ge=100)
    #: Home of vehicle 0; the others are placed relative to it.
    home_lat_deg: float = 47.397742
    home_lon_deg: float = 8.545594
    home_alt_m: float = 488.0


class VehicleConfig(Section):
    """One simulated vehicle."""

    name: str
    role: str = "follower"
    #: Spawn position in the shared local NED frame, m.
    spawn_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    spawn_yaw_deg: float = 0.0


class SitlConfig(Section):
    """The whole simulator configuration."""

    schema_version: int = SCHEMA_VERSION
    world: WorldConfig = WorldConfig()
    vehicles: tuple[VehicleConfig, ...] = (
        VehicleConfig(name="leader", role="leader", spawn_ned_m=(8.0, 0.0, 0.0)),
        VehicleConfig(name="follower", role="follower"),
    )


def load_sitl_config(path: Path | None, environ: Mapping[str, str] | None = None) -> SitlConfig:
    """Load ``config/sitl.toml``-style files with ``SITL_*`` overrides on top."""
    data = read_toml(path) if path is not None else {}
    data = deep_merge(data, env_overrides(os.environ if environ is None else environ, prefix="SITL_"))
    try:
        return SitlConfig.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(str(path or "<defaults>"), format_validation_error(exc)) from None
