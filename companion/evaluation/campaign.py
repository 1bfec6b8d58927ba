"""``companion sim``'s work: one scenario, every scenario (real path, then lockstep), or a Monte Carlo.

* :func:`run_one` flies one scenario (real path by default, or lockstep) and writes its report and plots.
* :func:`run_many` runs several single runs as child processes (``companion sim`` itself), ``jobs`` at a
  time, shows one progress line for all of them, and writes ``summary.json`` / ``summary.md``.
* :mod:`companion.evaluation.ray_executor` runs a seeded campaign as Ray tasks instead (``--executor ray``);
  both executors share the summary (:func:`campaign_summary`), ``--resume`` (:func:`split_done`) and the
  progress text (:func:`progress_text`).

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
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, TextIO

from companion.evaluation.metrics import monte_carlo_summary
from companion.evaluation.report import write_json
from companion.kernel.config import deep_merge
from companion.kernel.errors import CompanionError, ConfigError

log = logging.getLogger(__name__)

Harness = Literal["real", "lockstep"]
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
    detector: DetectorChoice = "network"
    speed: float = 1.0
    duration_s: float | None = None
    plots: bool = True
    #: ``section.key=value`` service config overrides (TOML values) on top of the scenario's.
    overrides: tuple[str, ...] = ()


def effective_scenario(path: Path, duration_s: float | None) -> Any:
    """The scenario file's model, with the formation window reshaped to ``duration_s`` when given."""
    from sitl.scenario import load_scenario  # noqa: PLC0415 (pydantic models of the simulator)

    sc = load_scenario(path)
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
    from companion.evaluation.lockstep import LockstepOptions  # noqa: PLC0415 (numpy, the cores)
    from companion.evaluation.realpath import RealOptions, run_real  # noqa: PLC0415
    from companion.evaluation.setup import (  # noqa: PLC0415
        load_detect,
        run_lockstep,
        scenario_path,
        service_config,
        write_run,
    )
    from companion.evaluation.tomlw import dumps  # noqa: PLC0415

    path = scenario_path(spec.scenario)
    scenario = effective_scenario(path, spec.duration_s)
    spec.out_dir.mkdir(parents=True, exist_ok=True)
    run_file = spec.out_dir / "scenario.toml"
    run_file.write_text(dumps(scenario.model_dump(mode="json")))
    cfg = service_config(
        scenario.companion, deep_merge(parse_overrides(spec.overrides), _runtime_override(spec.detector))
    )
    if spec.detector == "network":
        _require_weights(cfg)
    wall0 = time.perf_counter()
    if spec.harness == "lockstep":
        stage = load_detect(cfg, spec.detector)
        description = stage.description
        result = run_lockstep(run_file, spec.seed, cfg, stage, LockstepOptions(progress=progress))
    else:
        description = "ground-truth boxes (NOT the network)" if spec.detector == "truth" else _describe(cfg)
        result = asyncio.run(
            run_real(
                run_file,
                scenario,
                spec.seed,
                cfg,
                spec.out_dir / "logs",
                RealOptions(speed=spec.speed, progress=progress),
            )
        )
    wall_s = time.perf_counter() - wall0
    extra = {"detector": description, "scenario_file": str(path), "formation_window_s": _window(scenario)}
    if spec.plots:
        return write_run(spec.out_dir, scenario.name, spec.seed, result, cfg, wall_s=wall_s, extra=extra)
    return write_run_without_plots(
        spec.out_dir, scenario.name, spec.seed, result, cfg, wall_s=wall_s, extra=extra
    )


def write_run_without_plots(
    out_dir: Path, name: str, seed: int, result: Any, cfg: Any, *, wall_s: float, extra: dict[str, Any]
) -> dict[str, Any]:
    """The report alone (Monte Carlo runs: fifty sets of plots would cost more than the runs' insight)."""
    from companion.evaluation.log import save_log  # noqa: PLC0415
    from companion.evaluation.metrics import compute_metrics  # noqa: PLC0415
    from companion.evaluation.report import build_report, write_report  # noqa: PLC0415

    metrics = compute_metrics(result.log, cfg.formation.offset_cam_m)
    report = build_report(name, seed, result.log, metrics, wall_s=wall_s, extra={**result.extra, **extra})
    write_report(out_dir, report)
    save_log(result.log, out_dir / "flight_log.npz")
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
    from companion.evaluation.setup import service_config  # noqa: PLC0415

    _require_weights(service_config({}, parse_overrides(overrides)))


def _require_weights(cfg: Any) -> None:
    from companion.evaluation.setup import REPO  # noqa: PLC0415
    from companion.perception.detector import model_files  # noqa: PLC0415

    pt, onnx = model_files(cfg.detector, REPO)
    if not pt.exists() and not onnx.exists():
        raise ConfigError(
            str(pt),
            ["no detector weights (train and ship them: companion detector train; --detector truth checks "
             "the harness without them, but its figures are not vision results)"],
        )  # fmt: skip


def _describe(cfg: Any) -> str:
    from companion.evaluation.setup import REPO  # noqa: PLC0415
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


def eta_s(done: int, total: int, elapsed_s: float) -> float | None:
    """Seconds left at the throughput so far (None before the first run ends)."""
    if done <= 0 or total <= done:
        return None if done <= 0 else 0.0
    return elapsed_s / done * (total - done)


def clock_text(seconds: float) -> str:
    """``m:ss`` (``h:mm:ss`` past an hour)."""
    whole = max(0, round(seconds))
    h, rest = divmod(whole, 3600)
    m, sec = divmod(rest, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


def progress_text(
    done: int, failed: int, total: int, running: Sequence[str], elapsed_s: float, *, label: str = "sim"
) -> str:
    """One progress line: ``sim: 3/8 done, 1 failed | <running> | 1:02, ETA 1:40``."""
    eta = eta_s(done, total, elapsed_s)
    head = f"{label}: {done}/{total} done" + (f", {failed} failed" if failed else "")
    tail = clock_text(elapsed_s) + (f", ETA {clock_text(eta)}" if eta is not None and done < total else "")
    return f"{head} | {' | '.join(running) or '-'} | {tail}"


@dataclass(slots=True)
class StatusLine:
    """One line, rewritten in place on a terminal (new lines elsewhere, at most every 10 s)."""

    out: TextIO
    tty: bool = False
    _last_s: float = -math.inf
    _width: int = 0

    def write(self, text: str, force: bool = False) -> None:
        now = time.monotonic()
        if not self.tty and not force and now - self._last_s < 10.0:
            return
        self._last_s = now
        if self.tty:
            pad = max(0, self._width - len(text))
            self.out.write("\r" + text + " " * pad)
            self._width = len(text)
        else:
            self.out.write(text + "\n")
        self.out.flush()

    def close(self) -> None:
        if self.tty:
            self.out.write("\n")
            self.out.flush()


@dataclass(slots=True)
class ProgressLine:
    """The child processes' progress: done/total, failures, each running run's sim time, ETA."""

    out: TextIO
    total: int
    tty: bool = False
    t0_s: float = field(default_factory=time.monotonic)
    _line: StatusLine | None = None

    def show(self, children: Sequence[_Child], force: bool = False) -> None:
        if self._line is None:
            self._line = StatusLine(self.out, self.tty)
        running = [
            f"{c.name} {c.t_s:.0f}/{c.end_s:.0f} s" if math.isfinite(c.end_s) else f"{c.name} starting"
            for c in children
            if c.proc is not None and not c.done
        ]
        done = sum(c.done for c in children)
        failed = sum(c.done and c.rc != 0 for c in children)
        text = progress_text(done, failed, self.total, running, time.monotonic() - self.t0_s)
        self._line.write(text, force)

    def close(self) -> None:
        if self._line is not None:
            self._line.close()


def child_args(spec: RunSpec) -> list[str]:
    """The ``companion sim`` command line of one child run."""
    args = [sys.executable, "-m", "companion", "sim", "--scenario", spec.scenario, "--seed", str(spec.seed)]
    args += ["--out", str(spec.out_dir), "--speed", repr(spec.speed), "--harness", spec.harness]
    args += ["--detector", spec.detector, "--progress", "json"]
    if spec.duration_s is not None:
        args += ["--duration", repr(spec.duration_s)]
    if not spec.plots:
        args += ["--no-plots"]
    for o in spec.overrides:
        args += ["--set", o]
    return args


async def _run_child(child: _Child, env: dict[str, str], line: ProgressLine, children: list[_Child]) -> None:
    child.spec.out_dir.mkdir(parents=True, exist_ok=True)
    (child.spec.out_dir / "report.json").unlink(missing_ok=True)  # a failed rerun leaves no stale report
    child.started_s = time.monotonic()
    with (child.spec.out_dir / "sim.log").open("ab") as err:
        from companion.evaluation.procs import die_with_parent  # noqa: PLC0415

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


async def _run_children(
    specs: Sequence[RunSpec], jobs: int, line: ProgressLine, env: dict[str, str]
) -> list[_Child]:
    children = [_Child(s.out_dir.name, s) for s in specs]

    async def lane(group: list[_Child], n: int) -> None:
        slots = asyncio.Semaphore(max(1, n))

        async def one(c: _Child) -> None:
            async with slots:
                await _run_child(c, env, line, children)

        async with asyncio.TaskGroup() as tg:
            for c in group:
                tg.create_task(one(c), name=f"sim.{c.name}")

    real = [c for c in children if c.spec.harness == "real"]
    lockstep = [c for c in children if c.spec.harness == "lockstep"]
    if real and lockstep:
        # Mixed harnesses ('all'): the real-path runs alone, one at a time (they run in real time and must
        # keep their camera and control rates), then the lockstep runs ``jobs`` at a time. A niced lockstep
        # run beside the real path still delayed the follower's start by ~0.25 s on two cores (straight
        # seed 1: 0.353 m against 0.247 m alone; measured with companion sim).
        await lane(real, 1)
        await lane(lockstep, jobs)
    else:
        await lane(children, jobs)
    return children


#: What the Monte Carlo summary keeps of each run.
_SEED_KEYS = (
    "seed",
    "outcome",
    "relative_position_rmse_m",
    "relative_yaw_rmse_deg",
    "formation_rmse_m",
    "formation_max_deviation_m",
    "min_separation_m",
    "min_obstacle_clearance_m",
    "touchdown_m_s",
)


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
    from companion.evaluation.report import write_summary  # noqa: PLC0415

    out_dir.mkdir(parents=True, exist_ok=True)
    line = ProgressLine(stream, len(specs), tty=stream.isatty())
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


def campaign_summary(
    specs: Sequence[RunSpec],
    reports: Mapping[str, Mapping[str, Any]],
    failed: Sequence[str],
    *,
    wall_s: float,
    executor: str,
    resumed: int = 0,
) -> dict[str, Any]:
    """The Monte Carlo summary of a campaign: every seed's report (by folder name) and the failed runs.

    ``wall_s`` is this invocation's; ``resumed`` counts the seeds whose reports an earlier one wrote.
    """
    first = specs[0] if specs else None
    return {
        "scenario": first.scenario if first else None,
        "seeds": [s.seed for s in specs],
        "harness": first.harness if first else None,
        "detector": next(iter(reports.values())).get("detector") if reports else None,
        "formation_duration_s": first.duration_s if first else None,
        "executor": executor,
        "wall_s": round(wall_s, 1),
        "resumed": resumed,
        "failed": list(failed),
        **monte_carlo_summary(reports.values()),
        "runs_by_seed": {name: {k: r.get(k) for k in _SEED_KEYS} for name, r in reports.items()},
    }


def write_campaign_summary(
    specs: Sequence[RunSpec],
    out_dir: Path,
    *,
    failed: Sequence[str],
    wall_s: float,
    executor: str,
    resumed: int = 0,
) -> dict[str, Any]:
    """Read every seed's report from its folder, write ``summary.json`` / ``summary.md``; the summary."""
    specs = sorted(specs, key=lambda s: s.seed)
    reports: dict[str, dict[str, Any]] = {}
    for s in specs:
        p = s.out_dir / "report.json"
        if p.exists():
            reports[s.out_dir.name] = json.loads(p.read_text())
    summary = campaign_summary(specs, reports, failed, wall_s=wall_s, executor=executor, resumed=resumed)
    write_json(out_dir / "summary.json", summary)
    (out_dir / "summary.md").write_text(monte_carlo_markdown(summary))
    return summary


def monte_carlo_markdown(summary: dict[str, Any]) -> str:
    """The Monte Carlo summary as a page: outcomes, then percentiles of each metric."""
    lines = [
        f"# Monte Carlo: `{summary['scenario']}`, {summary['runs']} seeds ({summary['harness']} harness)",
        "",
        f"Detector: {summary.get('detector')}. Formation window: "
        f"{summary.get('formation_duration_s') or 'the scenario default'} s.",
        "",
        "| outcome | runs |",
        "|---|---|",
    ]
    lines += [f"| {k} | {v} |" for k, v in summary["outcomes"].items()]
    lines += ["", "| metric | min | p5 | p50 | p95 | max |", "|---|---|---|---|---|---|"]
    for key in (
        "relative_position_rmse_m",
        "relative_yaw_rmse_deg",
        "formation_rmse_m",
        "formation_max_deviation_m",
        "min_separation_m",
        "min_obstacle_clearance_m",
        "detection_recall",
    ):
        v = summary.get(key)
        if v is None:
            lines.append(f"| {key} | n/a | n/a | n/a | n/a | n/a |")
        else:
            cells = " | ".join(f"{v[q]:.3f}" if q in v else "n/a" for q in ("min", "p5", "p50", "p95", "max"))
            lines.append(f"| {key} | {cells} |")
    if summary.get("failed"):
        lines += ["", "Runs without a report: " + "; ".join(summary["failed"])]
    executor = f" ({summary['executor']} executor)" if summary.get("executor") else ""
    resumed = (
        f"; {summary['resumed']} seeds' reports kept from an earlier run" if summary.get("resumed") else ""
    )
    lines += ["", f"Wall time: {summary['wall_s']:.0f} s{executor}{resumed}."]
    return "\n".join(lines) + "\n"


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
