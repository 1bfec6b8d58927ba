"""The service's configuration: frozen pydantic models loaded from TOML plus ``WINGMAN_*`` overrides.

Loaded once at the CLI edge and passed down explicitly; nothing below reads files or the environment.
Overrides use double underscores between levels and TOML literals as values, e.g.
``WINGMAN_LINK__URL=udpin://0.0.0.0:14541`` or ``WINGMAN_FORMATION__OFFSET_CAM_M='[0.0, 0.0, 6.0]'``.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from pydantic import Field, ValidationError, field_validator, model_validator

from companion.config.flight import FormationConfig, MissionConfig, SafetyConfig
from companion.config.formation_plan import FormationPlan, load_plan
from companion.config.paths import PATH_KEYS, ResolvedPath, resolve_path
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
from companion.config.slot import slot_refusal
from companion.config.viz import VizConfig
from companion.kernel.config import (
    Section,
    deep_merge,
    env_overrides,
    env_sources,
    read_toml,
    validation_problems,
)
from companion.kernel.errors import ConfigError

__all__ = [
    "SCHEMA_VERSION",
    "AutoLabelSection",
    "CameraConfig",
    "Config",
    "ConfigCheck",
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
    "VizConfig",
    "apply_plan",
    "check_config",
    "load_config",
    "load_plan",
    "resolve_state_dir",
    "slot_refusal",
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
    viz: VizConfig = VizConfig()

    @model_validator(mode="after")
    def _truth_needs_truth(self) -> Config:
        if self.detector.runtime == "truth" and self.camera.source == "realsense":
            raise ValueError("detector.runtime = 'truth' needs a source with ground truth (sim or file)")
        return self

    @model_validator(mode="after")
    def _external_position_needs_the_leader(self) -> Config:
        if (
            self.mission.gps_loss_policy == "vision_external_position"
            and self.leader.shared_position != "mqtt"
        ):
            raise ValueError(
                "mission.gps_loss_policy = 'vision_external_position' needs the leader's own position: "
                "set leader.shared_position = 'mqtt' (and [mqtt] enabled)"
            )
        return self

    @model_validator(mode="after")
    def _never_the_leader(self) -> Config:
        if self.link.system_id != 0 and self.link.system_id == self.leader.mavlink_system_id:
            raise ValueError(
                f"link.system_id: {self.link.system_id} is the leader's (leader.mavlink_system_id); "
                "the service never commands the leader"
            )
        return self

    @model_validator(mode="after")
    def _slot_in_bounds(self) -> Config:
        # The same rule as an operator's set_offset (companion/config/slot.py), so a slot the config flies
        # is one a command could have set.
        problem = slot_refusal(self.formation.offset_cam_m, self.safety.min_separation_m)
        if problem is not None:
            raise ValueError(f"formation.offset_cam_m: {problem}")
        return self

    @field_validator("schema_version")
    @classmethod
    def _known_schema(cls, v: int) -> int:
        if v > SCHEMA_VERSION:
            raise ValueError(f"written for a newer Wingman (schema {v} > {SCHEMA_VERSION}); upgrade")
        if v < 1:
            raise ValueError("must be >= 1")
        return v


@dataclass(frozen=True, slots=True)
class ConfigCheck:
    """Everything wrong with a config at once, each problem with where its value came from.

    ``config`` is the resolved config when there is no problem in it. ``detector`` is the detector section
    even when another section is wrong (the model files can still be checked), None when it is wrong itself.
    """

    config: Config | None
    problems: list[str]
    sources: list[str]
    paths: dict[tuple[str, str], ResolvedPath]
    detector: DetectorConfig | None
    #: The config file ("<defaults>" without one).
    label: str
    env_keys: dict[tuple[str, ...], str] = field(default_factory=dict)

    def source_of(self, loc: tuple[str, ...]) -> str:
        """Where the value at ``loc`` came from: ``$WINGMAN_...``, the file, or the file and variables."""
        for n in range(len(loc), 0, -1):
            if loc[:n] in self.env_keys:
                return "$" + self.env_keys[loc[:n]]
        below = sorted(v for k, v in self.env_keys.items() if k[: len(loc)] == loc)
        return " + ".join([self.label, *(f"${v}" for v in below)])

    def error(self) -> ConfigError:
        """The problems as one :class:`ConfigError` (one line each)."""
        return ConfigError(self.label, self.problems, self.sources)


def check_config(path: Path | None, environ: Mapping[str, str] | None = None) -> ConfigCheck:
    """Read the config and find every problem in it in one pass (an unreadable file ends it at once).

    Relative paths are resolved as :mod:`companion.config.paths` says, so the config holds absolute ones.
    """
    env = os.environ if environ is None else environ
    data = read_toml(path) if path is not None else {}
    data = deep_merge(data, env_overrides(env))
    label = str(path) if path is not None else "<defaults>"
    base = (path.parent, f"the config file's folder {path.parent.absolute()}") if path else None
    check = ConfigCheck(None, [], [], {}, None, label, env_sources(env))
    paths: dict[tuple[str, str], ResolvedPath] = {}
    for section, key in PATH_KEYS:
        table = data.get(section)
        given = table.get(key) if isinstance(table, dict) else _default_path(section, key)
        if isinstance(given, str) and given:
            from_env = (section, key) in check.env_keys or (section,) in check.env_keys
            where = (Path.cwd(), f"the working folder {Path.cwd()}") if from_env or base is None else base
            paths[section, key] = resolve_path(given, *where)
    check.paths.update(paths)
    resolved = deep_merge(
        data,
        _nested({(s, k): str(r.path) for (s, k), r in paths.items() if isinstance(data.get(s, {}), dict)}),
    )
    try:
        cfg: Config | None = Config.model_validate(resolved)
    except ValidationError as exc:
        cfg = None
        for loc, line in validation_problems(exc, Config):
            check.problems.append(line)
            check.sources.append(check.source_of(loc))
    detector = cfg.detector if cfg is not None else _detector_alone(resolved.get("detector"))
    plan = cfg.formation.plan if cfg is not None else _str_at(resolved, "formation", "plan")
    if plan and not Path(plan).is_file():
        rp = paths["formation", "plan"]
        check.problems.append(f"formation.plan: file not found: {rp.path}{rp.note()}")
        check.sources.append(check.source_of(("formation", "plan")))
    elif plan and cfg is not None:
        try:
            cfg = apply_plan(cfg, Path(plan))
        except ConfigError as exc:
            check.problems.extend(exc.problems)
            check.sources.extend(exc.sources)
    return ConfigCheck(
        cfg if not check.problems else None,
        check.problems,
        check.sources,
        check.paths,
        detector,
        label,
        check.env_keys,
    )


def load_config(path: Path | None, environ: Mapping[str, str] | None = None) -> Config:
    """Load the service config from ``path`` (defaults when None) with environment overrides on top.

    Raises :class:`ConfigError` with every problem, one line each (see :func:`check_config`).
    """
    check = check_config(path, environ)
    if check.config is None:
        raise check.error()
    return check.config


def _default_path(section: str, key: str) -> object:
    sub = Config.model_fields[section].default
    return getattr(sub, key, None)


def _nested(flat: Mapping[tuple[str, str], str]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for (section, key), value in flat.items():
        out.setdefault(section, {})[key] = value
    return out


def _str_at(data: Mapping[str, Any], section: str, key: str) -> str:
    table = data.get(section)
    value = table.get(key) if isinstance(table, dict) else None
    return value if isinstance(value, str) else ""


def _detector_alone(table: object) -> DetectorConfig | None:
    """The detector section on its own, for the model checks of a config that is wrong elsewhere."""
    known = {
        k: v
        for k, v in (table if isinstance(table, dict) else {}).items()
        if k in DetectorConfig.model_fields
    }
    for keys in (known, {k: v for k, v in known.items() if k in ("model_path", "model_sha256", "runtime")}):
        try:
            return DetectorConfig.model_validate(keys)
        except ValidationError:
            continue
    return None


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
    offset_cam_m = (0.0, 0.0 - down + 0.0, slot.range_h_m)
    problem = slot_refusal(offset_cam_m, cfg.safety.min_separation_m)
    if problem is not None:
        raise ConfigError(str(plan_path), [f"{cfg.vehicle_id}'s slot: {problem}"])
    formation = cfg.formation.model_copy(
        update={
            "plan": str(plan_path),
            "offset_cam_m": offset_cam_m,
            "slot_leader_m": slot.offset_m,
            "neighbour_slots_m": tuple(s.offset_m for s in plan.slots if s.follower != cfg.vehicle_id),
            "neighbour_ids": tuple(s.follower for s in plan.slots if s.follower != cfg.vehicle_id),
        }
    )
    return cfg.model_copy(update={"formation": formation})
