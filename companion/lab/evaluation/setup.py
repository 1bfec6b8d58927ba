"""Building a run: scenario files, the service config a scenario asks for, the detector, the report.

Shared by the lockstep harness and the real-path runner behind ``companion sim``.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from companion.config import Config
from companion.config.paths import resolve_path
from companion.kernel.config import deep_merge, format_validation_error, read_toml
from companion.kernel.errors import ConfigError
from companion.kernel.shipped import project_root
from companion.lab.evaluation.lockstep import LockstepOptions, LockstepRun, RunResult
from companion.lab.evaluation.log import save_log
from companion.lab.evaluation.metrics import compute_metrics
from companion.lab.evaluation.plots import write_plots
from companion.lab.evaluation.report import build_report, write_report
from companion.perception.types import DetectStage

log = logging.getLogger(__name__)

#: The folder with config/ and models/ (the working folder, the installed copy or the checkout).
REPO = project_root()
SCENARIO_DIR = REPO / "config" / "scenarios"
#: Scenarios beyond the eight of ``--scenario all`` (the GPS-loss and leader-loss policy variants).
VARIANT_DIR = SCENARIO_DIR / "variants"
DEFAULT_CONFIG = REPO / "config" / "wingman.toml"
SITL_CONFIG = REPO / "config" / "sitl.toml"


def all_scenarios(scenario_dir: Path = SCENARIO_DIR) -> list[str]:
    """The names ``--scenario all`` flies, paper scenarios first."""
    names = sorted(p.stem for p in scenario_dir.glob("*.toml"))
    first = [n for n in ("straight", "circle", "gps-loss", "visibility") if n in names]
    return first + [n for n in names if n not in first]


def scenario_path(name: str, scenario_dir: Path = SCENARIO_DIR) -> Path:
    """A scenario name (shipped or a variant) or a path -> the file; one clear error when there is none."""
    p = Path(name)
    if p.suffix == ".toml":
        candidates = [p]
    else:
        candidates = [scenario_dir / f"{name}.toml", scenario_dir / "variants" / f"{name}.toml"]
    for c in candidates:
        if c.exists():
            return c
    known = sorted(
        q.stem for q in [*scenario_dir.glob("*.toml"), *(scenario_dir / "variants").glob("*.toml")]
    )
    raise ConfigError(name, [f"no such scenario (known: {', '.join(known)})"])


def service_config(
    scenario_overrides: Mapping[str, Any], extra: Mapping[str, Any] | None = None, base: Path = DEFAULT_CONFIG
) -> Config:
    """The service config for a run: ``base`` + the scenario's ``[companion]`` table + ``extra``.

    The files it reads (the detector's weights, a formation plan) are resolved as the service resolves
    them (companion/config/paths.py, against ``base``'s folder), so a run finds them from any folder.
    """
    data = deep_merge(read_toml(base), scenario_overrides)
    if extra:
        data = deep_merge(data, extra)
    defaults = Config()
    for section, key in (("detector", "model_path"), ("formation", "plan")):
        table = data.setdefault(section, {})
        given = table.get(key, getattr(getattr(defaults, section), key))
        if isinstance(given, str) and given:
            table[key] = str(resolve_path(given, base.parent, f"{base.parent}").path)
    try:
        return Config.model_validate(data)
    except ValidationError as exc:
        raise ConfigError(f"{base} + scenario [companion]", format_validation_error(exc)) from None


def load_detect(cfg: Config, runtime: str) -> DetectStage:
    """The per-frame detection; ``runtime`` "truth" uses the simulator's boxes.

    "truth" exists to exercise the harness without trained weights: its figures are not vision results,
    and the report says so.
    """
    if runtime == "truth":
        from companion.perception.truth_detector import TruthDetector  # noqa: PLC0415 (only for this mode)

        truth = TruthDetector()
        return DetectStage(truth.detect_frame, description="ground-truth boxes (NOT the network)")
    from companion.perception.detector import detect_stage  # noqa: PLC0415 (onnxruntime/torch: heavy)

    return detect_stage(cfg.detector, REPO)


def leader_spawn_ned_m(
    cfg: Config, offset_ne_m: tuple[float, float] = (0.0, 0.0)
) -> tuple[float, float, float]:
    """Where the leader spawns (NED, m): the follower's slot plus ``offset_ne_m`` (north, east).

    The slot is ``formation.offset_cam_m`` in the level camera frame of a follower at the origin facing north.
    """
    x_right, _, z_forward = cfg.formation.offset_cam_m
    return (z_forward + offset_ne_m[0], x_right + offset_ne_m[1], 0.0)


def sitl_config(cfg: Config, base: Path = SITL_CONFIG, offset_ne_m: tuple[float, float] = (0.0, 0.0)) -> Any:
    """The simulator config for a run: ``base`` with the leader spawned in the follower's slot.

    The follower spawns at the origin facing north; the leader starts where the formation wants it, so
    formation flight starts without a transient, as the paper's runs do; ``offset_ne_m`` moves it off the
    slot (a join).
    """
    from sitl.config import load_sitl_config  # noqa: PLC0415 (the simulator is only needed here)

    sitl = load_sitl_config(base)
    spawn = leader_spawn_ned_m(cfg, offset_ne_m)
    vehicles = tuple(
        v.model_copy(update={"spawn_ned_m": spawn}) if v.role == "leader" else v for v in sitl.vehicles
    )
    return sitl.model_copy(update={"vehicles": vehicles})


def run_lockstep(
    path: Path,
    seed: int,
    cfg: Config,
    stage: DetectStage,
    options: LockstepOptions,
) -> RunResult:
    """Fly one scenario file in lockstep (blocking; builds the world and the renderer)."""
    import asyncio  # noqa: PLC0415

    from sitl.render.config import CameraModel, visual_from_mapping  # noqa: PLC0415
    from sitl.render.renderer import Renderer  # noqa: PLC0415 (the simulator is only needed here)
    from sitl.world.lockstep import World  # noqa: PLC0415
    from sitl.world.scenario import load_scenario  # noqa: PLC0415

    scenario = load_scenario(path)
    world = World(sitl_config(cfg, offset_ne_m=scenario.run.leader_spawn_offset_m), scenario, seed=seed)
    camera = CameraModel(rate_hz=scenario.run.camera_rate_hz)
    visual = visual_from_mapping(scenario.visual, f"{path} [visual]")
    with Renderer(camera=camera, visual=visual, mount=cfg.camera.mount, seed=seed) as renderer:
        return asyncio.run(LockstepRun(world, renderer, cfg, stage, options).run())


def write_run(
    out_dir: Path,
    scenario: str,
    seed: int,
    result: RunResult,
    cfg: Config,
    *,
    wall_s: float,
    extra: Mapping[str, Any] | None = None,
) -> dict[str, Any]:
    """Metrics, ``report.json``/``report.md`` and the plots of one run into ``out_dir``; the report."""
    offset = cfg.formation.offset_cam_m
    metrics = compute_metrics(result.log, offset)
    report = build_report(
        scenario,
        seed,
        result.log,
        metrics,
        wall_s=wall_s,
        extra={**result.extra, **(extra or {})},
        offset_cam_m=offset,
    )
    report["plots"] = write_plots(result.log, offset, result.snapshots, out_dir / "plots", scenario)
    write_report(out_dir, report)
    save_log(result.log, out_dir / "flight_log.npz")
    if result.trace is not None:
        result.trace.write_trace(out_dir / "trace.jsonl")
    return report


ProgressFn = Callable[[float], None]
