"""``companion sim``'s work: one scenario, every scenario (real path, then lockstep), or a Monte Carlo.

* :func:`run_one` flies one scenario (real path by default, or lockstep) and writes its report and plots.
* :func:`run_many` runs several single runs as child processes (``companion sim`` itself), ``jobs`` at a
  time, shows one progress line for all of them, and writes ``summary.json`` / ``summary.md``.
* :mod:`companion.lab.evaluation.ray_executor` runs a seeded campaign as Ray tasks instead
  (``--executor ray``); both executors share the summary (:mod:`companion.lab.evaluation.campaign_summary`),
  ``--resume`` (:func:`split_done`) and the progress text (:mod:`companion.lab.evaluation.progress`).

A child reports progress as JSON lines on its stdout (``--progress json``); everything else it says goes
to its log file in its own output folder.
"""

from __future__ import annotations

import asyncio
import json
import logging
import math
import sys
import time
import tomllib
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, TextIO

from pydantic import ValidationError

from companion.kernel.config import deep_merge, format_validation_error, read_toml
from companion.kernel.errors import CompanionError, ConfigError
from companion.lab.evaluation.campaign_summary import write_campaign_summary
from companion.lab.evaluation.progress import ProgressLine
from companion.lab.evaluation.report import write_json

log = logging.getLogger(__name__)

Harness = Literal["real", "lockstep"]
#: ``builtin``: the simulator's own PX4-like autopilot; ``px4``: real PX4 SITL (the real path only).
Autopilot = Literal["builtin", "px4"]
DetectorChoice = Literal["network", "truth"]
#: After the formation window a run keeps flying this long (s) when ``--duration`` reshapes it.
TAIL_S = 2.0


class SimError(CompanionError):
    """A run failed to produce a report."""

    exit_code = 1


@dataclass(frozen=True, slots=True)
class RunSpec:
    """One run: which scenario, seed, harness, detector, and where its report goes."""

    scenario: str
    seed: int
    out_dir: Path
    harness: Harness = "real"
    autopilot: Autopilot = "builtin"
    detector: DetectorChoice = "network"
    speed: float = 1.0
    duration_s: float | None = None
    plots: bool = True
    #: ``section.key=value`` service config overrides (TOML values) on top of the scenario's.
    overrides: tuple[str, ...] = ()
    #: A timing profile merged into the scenario (:func:`read_timing_profile`), or None.
    timing: Path | None = None


#: The tables a timing profile may set.
TIMING_TABLES = ("timing", "vehicles", "world")


def read_timing_profile(path: Path) -> tuple[Path, dict[str, Any]]:
    """A timing profile (``config/timing/*.toml``): its absolute path and tables; errors in one line each.

    It may hold ``[timing]`` (the lockstep harness's camera pipeline), ``[vehicles.NAME.link]`` (MAVLink
    latency, jitter and loss on that vehicle's links, both harnesses) and ``[world]`` (the simulator's world:
    an airframe's drag, the heading estimate's error), nothing else.
    """
    if not path.is_file():
        raise ConfigError(str(path), ["no such timing profile"])
    data = read_toml(path)
    problems = [
        f"{k}: not a timing table (a profile sets {', '.join(TIMING_TABLES)})"
        for k in data
        if k not in TIMING_TABLES
    ]
    for name, veh in data.get("vehicles", {}).items():
        extra = sorted(set(veh) - {"link"}) if isinstance(veh, dict) else ["(not a table)"]
        problems += [f"vehicles.{name}.{k}: a profile sets only vehicles.{name}.link" for k in extra]
    if problems:
        raise ConfigError(str(path), problems)
    return path.resolve(), data


def effective_scenario(path: Path, duration_s: float | None, timing: Path | None = None) -> Any:
    """The scenario file's model: a timing profile merged in, the formation window reshaped to ``duration_s``.

    The profile's keys replace the scenario's keys they name; the rest of the scenario stays.
    """
    from sitl.world.scenario import Scenario, load_scenario  # noqa: PLC0415 (pydantic models of the simulator)

    sc = load_scenario(path)
    if timing is not None:
        _, profile = read_timing_profile(timing)
        merged = deep_merge(sc.model_dump(mode="json", exclude_unset=True), profile)
        try:
            sc = Scenario.model_validate(merged)
        except ValidationError as exc:
            raise ConfigError(f"{path} with {timing}", format_validation_error(exc)) from None
    if duration_s is None:
        return sc
    if not (math.isfinite(duration_s) and duration_s > 0):
        raise ConfigError("--duration", [f"must be a positive number of seconds (got {duration_s})"])
    run = sc.run.model_copy(
        update={
            "formation_duration_s": duration_s,
            "duration_s": sc.run.formation_start_s + duration_s + TAIL_S,
        }
    )
    return sc.model_copy(update={"run": run})


def run_one(spec: RunSpec, progress: Callable[[float], None] | None = None) -> dict[str, Any]:
    """Fly one scenario and write ``report.json``, ``report.md`` and the plots; returns the report."""
    from companion.lab.evaluation.lockstep import LockstepOptions  # noqa: PLC0415 (numpy, the cores)
    from companion.lab.evaluation.realpath import RealOptions, run_real  # noqa: PLC0415
    from companion.lab.evaluation.runlog import RUN_LOG  # noqa: PLC0415
    from companion.lab.evaluation.setup import (  # noqa: PLC0415
        load_detect,
        run_lockstep,
        scenario_path,
        service_config,
        write_run,
    )
    from companion.lab.evaluation.tomlw import dumps  # noqa: PLC0415

    path = scenario_path(spec.scenario)
    # The run's own seed in its scenario.toml: the folder alone reproduces the run.
    scenario = effective_scenario(path, spec.duration_s, spec.timing).model_copy(update={"seed": spec.seed})
    spec.out_dir.mkdir(parents=True, exist_ok=True)
    run_file = spec.out_dir / "scenario.toml"
    run_file.write_text(dumps(scenario.model_dump(mode="json")))
    cfg = service_config(
        scenario.companion, deep_merge(parse_overrides(spec.overrides), _runtime_override(spec.detector))
    )
    if spec.detector == "network":
        _require_weights(cfg)
    if scenario.formation:
        return _run_formation(spec, run_file, scenario, cfg, path, progress=progress)
    wall0 = time.perf_counter()
    if spec.harness == "lockstep" and spec.autopilot != "builtin":
        raise ConfigError(spec.scenario, ["PX4 runs in real time: --autopilot px4 flies the real path only"])
    if spec.harness == "lockstep":
        stage = load_detect(cfg, spec.detector)
        description = stage.description
        options = LockstepOptions(progress=progress, mcap_path=spec.out_dir / RUN_LOG)
        result = run_lockstep(run_file, spec.seed, cfg, stage, options)
    else:
        description = "ground-truth boxes (NOT the network)" if spec.detector == "truth" else _describe(cfg)
        result = asyncio.run(
            run_real(
                run_file,
                scenario,
                spec.seed,
                cfg,
                spec.out_dir / "logs",
                RealOptions(
                    speed=spec.speed,
                    progress=progress,
                    autopilot=spec.autopilot,
                    mcap_path=spec.out_dir / RUN_LOG,
                ),
            )
        )
    wall_s = time.perf_counter() - wall0
    extra = {"detector": description, "scenario_file": str(path), "formation_window_s": _window(scenario)}
    if spec.plots:
        return write_run(spec.out_dir, scenario.name, spec.seed, result, cfg, wall_s=wall_s, extra=extra)
    return write_run_without_plots(
        spec.out_dir, scenario.name, spec.seed, result, cfg, wall_s=wall_s, extra=extra
    )


def _run_formation(
    spec: RunSpec,
    run_file: Path,
    scenario: Any,
    cfg: Any,
    path: Path,
    *,
    progress: Callable[[float], None] | None,
) -> dict[str, Any]:
    """A formation scenario: one leader, a follower per plan slot, lockstep only."""
    from companion.lab.evaluation.runlog import RUN_LOG  # noqa: PLC0415
    from companion.lab.formation.flight import run_formation  # noqa: PLC0415
    from companion.lab.formation.report import (  # noqa: PLC0415
        build_formation_report,
        plot_from_above,
        save_logs,
        write_formation_report,
    )
    from companion.lab.formation.run import FormationOptions  # noqa: PLC0415

    if spec.harness != "lockstep":
        raise ConfigError(
            spec.scenario, ["formation scenarios fly in the lockstep harness only (--harness lockstep)"]
        )
    runtime = "truth" if spec.detector == "truth" else cfg.detector.runtime
    options = FormationOptions(progress=progress, mcap_path=spec.out_dir / RUN_LOG)
    result, plan, configs = run_formation(run_file, spec.seed, cfg, runtime, options)
    extra: dict[str, Any] = {"scenario_file": str(path), "formation_window_s": _window(scenario)}
    extra["detector"] = "ground-truth boxes (NOT the network)" if spec.detector == "truth" else _describe(cfg)
    report = build_formation_report(scenario.name, spec.seed, plan, result, configs, extra=extra)
    if spec.plots:
        plot = spec.out_dir / "plots" / "formation.png"
        plot_from_above(result, plan, plot, scenario.name)
        report["plots"] = [str(plot)]
    write_formation_report(spec.out_dir, report)
    save_logs(result, spec.out_dir)
    return report


def write_run_without_plots(
    out_dir: Path, name: str, seed: int, result: Any, cfg: Any, *, wall_s: float, extra: dict[str, Any]
) -> dict[str, Any]:
    """The report alone (Monte Carlo runs: fifty sets of plots would cost more than the runs' insight)."""
    from companion.lab.evaluation.log import save_log  # noqa: PLC0415
    from companion.lab.evaluation.metrics import compute_metrics  # noqa: PLC0415
    from companion.lab.evaluation.report import build_report, write_report  # noqa: PLC0415

    metrics = compute_metrics(result.log, cfg.formation.offset_cam_m)
    report = build_report(
        name,
        seed,
        result.log,
        metrics,
        wall_s=wall_s,
        extra={**result.extra, **extra},
        offset_cam_m=cfg.formation.offset_cam_m,
    )
    write_report(out_dir, report)
    save_log(result.log, out_dir / "flight_log.npz")
    if result.trace is not None:
        result.trace.write_trace(out_dir / "trace.jsonl")
    return report


def _window(scenario: Any) -> list[float]:
    return [
        scenario.run.formation_start_s,
        scenario.run.formation_start_s + scenario.run.formation_duration_s,
    ]


def _runtime_override(detector: DetectorChoice) -> dict[str, Any]:
    return {"detector": {"runtime": "truth"}} if detector == "truth" else {}


def require_weights(overrides: Sequence[str] = ()) -> None:
    """Fail with one line when the network detector has no weights (checked before any run starts)."""
    from companion.lab.evaluation.setup import service_config  # noqa: PLC0415

    _require_weights(service_config({}, parse_overrides(overrides)))


def _require_weights(cfg: Any) -> None:
    from companion.lab.evaluation.setup import REPO  # noqa: PLC0415
    from companion.perception.detector import model_files  # noqa: PLC0415

    pt, onnx = model_files(cfg.detector, REPO)
    if not pt.exists() and not onnx.exists():
        raise ConfigError(
            str(pt),
            ["no detector weights (train and ship them: companion detector train; --detector truth checks "
             "the harness without them, but its figures are not vision results)"],
        )  # fmt: skip


def _describe(cfg: Any) -> str:
    from companion.lab.evaluation.setup import REPO  # noqa: PLC0415
    from companion.perception.detector import choose_runtime, window_note  # noqa: PLC0415

    runtime, path = choose_runtime(cfg.detector, REPO)
    where = path.relative_to(REPO) if path.is_relative_to(REPO) else path
    return f"{runtime}: {where}{window_note(cfg.detector)}"


# ---------------------------------------------------------------------- many runs, as child processes
@dataclass(slots=True)
class _Child:
    name: str
    spec: RunSpec
    proc: asyncio.subprocess.Process | None = None
    t_s: float = 0.0
    end_s: float = math.nan
    done: bool = False
    rc: int | None = None
    started_s: float = 0.0
    wall_s: float = 0.0

    @property
    def lane(self) -> str:
        """The harness: real-path runs fly one at a time, lockstep runs ``jobs`` at a time."""
        return self.spec.harness


def child_args(spec: RunSpec) -> list[str]:
    """The ``companion sim`` command line of one child run."""
    args = [sys.executable, "-m", "companion", "sim", "--scenario", spec.scenario, "--seed", str(spec.seed)]
    args += ["--out", str(spec.out_dir), "--speed", repr(spec.speed), "--harness", spec.harness]
    args += ["--autopilot", spec.autopilot, "--detector", spec.detector, "--progress", "json"]
    if spec.duration_s is not None:
        args += ["--duration", repr(spec.duration_s)]
    if not spec.plots:
        args += ["--no-plots"]
    for o in spec.overrides:
        args += ["--set", o]
    if spec.timing is not None:
        args += ["--timing", str(spec.timing)]
    return args


async def _run_child(child: _Child, env: dict[str, str], line: ProgressLine, children: list[_Child]) -> None:
    child.spec.out_dir.mkdir(parents=True, exist_ok=True)
    (child.spec.out_dir / "report.json").unlink(missing_ok=True)  # a failed rerun leaves no stale report
    child.started_s = time.monotonic()
    with (child.spec.out_dir / "sim.log").open("ab") as err:
        from companion.kernel.children import die_with_parent  # noqa: PLC0415

        child.proc = await asyncio.create_subprocess_exec(
            *child_args(child.spec),
            stdout=asyncio.subprocess.PIPE,
            stderr=err,
            env=env,
            preexec_fn=die_with_parent,  # prctl only, no locks
        )
        assert child.proc.stdout is not None  # noqa: S101 (PIPE)
        try:
            async for raw in child.proc.stdout:
                try:
                    msg = json.loads(raw)
                except json.JSONDecodeError:
                    continue
                child.t_s, child.end_s = float(msg.get("t_s", 0.0)), float(msg.get("end_s", math.nan))
                line.show(children)
            child.rc = await child.proc.wait()
        finally:
            if child.proc.returncode is None:
                child.proc.terminate()
                await child.proc.wait()
    child.done = True
    child.wall_s = time.monotonic() - child.started_s
    line.show(children, force=True)


def _length_s(spec: RunSpec) -> float:
    """The run's scenario length (sim s), NaN where the scenario cannot be read here (the run will say)."""
    from companion.lab.evaluation.setup import scenario_path  # noqa: PLC0415

    try:
        return float(
            effective_scenario(scenario_path(spec.scenario), spec.duration_s, spec.timing).run.duration_s
        )
    except (CompanionError, OSError, ValueError):
        return math.nan


async def _run_children(
    specs: Sequence[RunSpec], jobs: int, line: ProgressLine, env: dict[str, str]
) -> list[_Child]:
    children = [_Child(s.out_dir.name, s) for s in specs]
    for c in children:  # the scenarios' lengths, for the ETA before each run reports its own
        c.end_s = _length_s(c.spec)

    async def lane(group: list[_Child], n: int) -> None:
        slots = asyncio.Semaphore(max(1, n))

        async def one(c: _Child) -> None:
            async with slots:
                await _run_child(c, env, line, children)

        async with asyncio.TaskGroup() as tg:
            for c in group:
                tg.create_task(one(c), name=f"sim.{c.name}")

    # The real-path runs fly alone, one at a time (they run in real time and must keep their camera and
    # control rates; two PX4 runs at once also raced for the same free ports), then the lockstep runs
    # ``jobs`` at a time. A niced lockstep run beside the real path still delayed the follower's start by
    # ~0.25 s on two cores (straight seed 1: 0.353 m against 0.247 m alone; measured with companion sim).
    await lane([c for c in children if c.spec.harness == "real"], 1)
    await lane([c for c in children if c.spec.harness == "lockstep"], jobs)
    return children


def run_many(
    specs: Sequence[RunSpec],
    out_dir: Path,
    *,
    jobs: int,
    env: dict[str, str],
    stream: TextIO,
    monte_carlo: bool,
    already_done: Sequence[RunSpec] = (),
) -> dict[str, Any]:
    """Run ``specs`` as child processes, ``jobs`` at a time; write and return the summary.

    ``already_done``: a resumed campaign's seeds that have their report already (in the summary, not run).
    """
    from companion.lab.evaluation.report import write_summary  # noqa: PLC0415

    out_dir.mkdir(parents=True, exist_ok=True)
    line = ProgressLine(stream, len(specs), tty=stream.isatty(), jobs=jobs)
    wall0 = time.perf_counter()
    try:
        children = asyncio.run(_run_children(specs, jobs, line, env))
    finally:
        line.close()
    wall_s = time.perf_counter() - wall0
    reports: dict[str, dict[str, Any]] = {}
    failed: list[str] = []
    for c in children:
        p = c.spec.out_dir / "report.json"
        if c.rc == 0 and p.exists():
            reports[c.name] = json.loads(p.read_text())
        else:
            failed.append(f"{c.name} (exit {c.rc}; see {c.spec.out_dir / 'sim.log'})")
    if monte_carlo:
        summary = write_campaign_summary(
            [*already_done, *specs],
            out_dir,
            failed=failed,
            wall_s=wall_s,
            executor="local",
            resumed=len(already_done),
        )
    else:
        write_summary(out_dir, reports)
        summary = {"reports": reports, "failed": failed, "wall_s": round(wall_s, 1)}
        runs_wall_s = {c.name: round(c.wall_s, 1) for c in children}
        timing = {"wall_s": round(wall_s, 1), "jobs": jobs, "failed": failed, "runs": runs_wall_s}
        write_json(out_dir / "timing.json", timing)
    if failed:
        raise SimError("runs without a report: " + "; ".join(failed))
    return summary


def split_done(specs: Sequence[RunSpec], resume: bool) -> tuple[list[RunSpec], list[RunSpec]]:
    """(to run, already done): with ``resume``, a run whose ``report.json`` exists is done."""
    if not resume:
        return list(specs), []
    done = [s for s in specs if (s.out_dir / "report.json").exists()]
    return [s for s in specs if s not in done], done


def parse_overrides(items: Sequence[str]) -> dict[str, Any]:
    """``section.key=value`` strings (values parse as TOML, else strings) -> a nested dict."""
    out: dict[str, Any] = {}
    for item in items:
        key, sep, raw = item.partition("=")
        path = [k for k in key.strip().split(".") if k]
        if not sep or not path:
            raise ConfigError("--set", [f"expected SECTION.KEY=VALUE (got {item!r})"])
        try:
            value: Any = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw
        node = out
        for k in path[:-1]:
            node = node.setdefault(k, {})
        node[path[-1]] = value
    return out


def parse_seeds(text: str) -> list[int]:
    """``1-50`` or ``3,7,9`` or ``5`` -> the seeds."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            a, sep, b = part.strip().partition("-")
            seeds += list(range(int(a), int(b) + 1)) if sep else [int(a)]
    except ValueError:
        raise ConfigError(
            "--seeds", [f"expected a range like 1-50 or a list like 1,2,3 (got {text!r})"]
        ) from None
    if not seeds or any(s < 0 for s in seeds):
        raise ConfigError("--seeds", [f"no seeds in {text!r}"])
    return seeds
