"""The service's configuration: frozen pydantic models loaded from TOML plus ``WINGMAN_*`` overrides.

Loaded once at the CLI edge and passed down explicitly; nothing below reads files or the environment.
Overrides use double underscores between levels and TOML literals as values, e.g.
``WINGMAN_LINK__URL=udpin://0.0.0.0:14541`` or ``WINGMAN_FORMATION__OFFSET_CAM_M='[0.0, 0.0, 6.0]'``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path

from pydantic import Field, ValidationError, field_validator, model_validator

from companion.config.flight import FormationConfig, MissionConfig, SafetyConfig
from companion.config.formation_plan import FormationPlan, load_plan
from companion.config.perception import CameraConfig, DetectorConfig, LeaderConfig, PoseConfig, TrackerConfig
from companion.config.service import (
    AutoLabelSection,
    LinkConfig,
    LoggingConfig,
    MqttConfig,
    ServiceConfig,
    StatusConfig,
    resolve_state_dir,
    url_problem,
)
from companion.kernel.config import Section, deep_merge, env_overrides, format_validation_error, read_toml
from companion.kernel.errors import ConfigError

__all__ = [
    "SCHEMA_VERSION",
    "AutoLabelSection",
    "CameraConfig",
    "Config",
    "DetectorConfig",
    "FormationConfig",
    "FormationPlan",
    "LeaderConfig",
    "LinkConfig",
    "LoggingConfig",
    "MissionConfig",
    "MqttConfig",
    "PoseConfig",
    "SafetyConfig",
    "ServiceConfig",
    "StatusConfig",
    "TrackerConfig",
    "apply_plan",
    "load_config",
    "load_plan",
    "resolve_state_dir",
    "url_problem",
]

SCHEMA_VERSION = 1


class Config(Section):
    """The whole service configuration."""

    schema_version: int = SCHEMA_VERSION
    vehicle_id: str = Field("follower1", pattern=r"^[A-Za-z0-9_-]{1,32}$")
    link: LinkConfig = LinkConfig()
    camera: CameraConfig = CameraConfig()
    detector: DetectorConfig = DetectorConfig()
    leader: LeaderConfig = LeaderConfig()
    pose: PoseConfig = PoseConfig()
    tracker: TrackerConfig = TrackerConfig()
    formation: FormationConfig = FormationConfig()
    mission: MissionConfig = MissionConfig()
    safety: SafetyConfig = SafetyConfig()
    mqtt: MqttConfig = MqttConfig()
    status: StatusConfig = StatusConfig()
    service: ServiceConfig = ServiceConfig()
    logging: LoggingConfig = LoggingConfig()
    autolabel: AutoLabelSection = AutoLabelSection()

    @model_validator(mode="after")
    def _truth_needs_truth(self) -> Config:
        if self.detector.runtime == "truth" and self.camera.source == "realsense":
            raise ValueError("detector.runtime = 'truth' needs a source with ground truth (sim or file)")
        return self

    @model_validator(mode="after")
    def _never_the_leader(self) -> Config:
        if self.link.system_id != 0 and self.link.system_id == self.leader.mavlink_system_id:
            raise ValueError(
                f"link.system_id: {self.link.system_id} is the leader's (leader.mavlink_system_id); "
                "the service never commands the leader"
            )
        return self

    @field_validator("schema_version")
    @classmethod
    def _known_schema(cls, v: int) -> int:
        if v > SCHEMA_VERSION:
            raise ValueError(f"written for a newer Wingman (schema {v} > {SCHEMA_VERSION}); upgrade")
        if v < 1:
            raise ValueError("must be >= 1")
        return v


def load_config(path: Path | None, environ: Mapping[str, str] | None = None) -> Config:
    """Load the service config from ``path`` (defaults when None) with environment overrides on top."""
    data = read_toml(path) if path is not None else {}
    data = deep_merge(data, env_overrides(os.environ if environ is None else environ))
    try:
        cfg = Config.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(str(path or "<defaults>"), format_validation_error(exc)) from None
    if cfg.formation.plan:
        cfg = apply_plan(cfg, _plan_path(cfg.formation.plan, path))
    return cfg


def _plan_path(name: str, config_path: Path | None) -> Path:
    p = Path(name)
    if not p.is_absolute() and config_path is not None and (config_path.parent / p).exists():
        return config_path.parent / p
    return p


def apply_plan(cfg: Config, plan_path: Path) -> Config:
    """``cfg`` flying its ``vehicle_id``'s slot of the plan: facing the leader at the slot's range.

    The follower keeps the leader in the middle of the image (a wide V puts it outside the camera's field of
    view if the follower faced the leader's heading); ``slot_leader_m`` holds its place around the leader.
    """
    plan = load_plan(plan_path)
    try:
        slot = plan.slot(cfg.vehicle_id)
    except KeyError as exc:
        raise ConfigError(str(plan_path), [f"vehicle_id: {exc.args[0]}"]) from None
    down = slot.offset_m[2]
    formation = cfg.formation.model_copy(
        update={
            "plan": str(plan_path),
            "offset_cam_m": (0.0, 0.0 - down + 0.0, slot.range_h_m),
            "slot_leader_m": slot.offset_m,
            "neighbour_slots_m": tuple(s.offset_m for s in plan.slots if s.follower != cfg.vehicle_id),
            "neighbour_ids": tuple(s.follower for s in plan.slots if s.follower != cfg.vehicle_id),
        }
    )
    return cfg.model_copy(update={"formation": formation})
