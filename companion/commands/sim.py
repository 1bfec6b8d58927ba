"""``companion sim``: closed-loop scenarios against the simulator, with reports and plots."""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

from companion.kernel.logs import setup_logging


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser(
        "sim",
        help="fly a scenario closed-loop in the simulator and write a report",
        description="Fly scenarios closed-loop: sitl serve + the real service (MAVSDK over UDP, the rendered "
        "camera, the detector, tracker and mission), or --seeds through the lockstep harness.",
    )
    p.add_argument(
        "--scenario", default="all", help="scenario name (config/scenarios/NAME.toml), a path, or 'all'"
    )
    p.add_argument(
        "--seed",
        type=int,
        default=None,
        help="the run's random seed (default: the scenario's own, `seed` in its file; a run's folder keeps "
        "its seed in scenario.toml, so `--scenario DIR/scenario.toml` flies it again)",
    )
    p.add_argument("--seeds", default=None, help="Monte Carlo over seeds, e.g. 1-50 (lockstep harness)")
    p.add_argument("--out", type=Path, default=Path("runs/sim"), help="output folder")
    p.add_argument("--speed", type=float, default=1.0, help="simulation speed factor (real path)")
    p.add_argument("--duration", type=float, default=None, help="formation time in s (scenario default)")
    p.add_argument(
        "--jobs",
        type=int,
        default=None,
        help="lockstep runs side by side for 'all' and --seeds (default 2); real-path runs (and every PX4 "
        "run) fly one at a time",
    )
    p.add_argument(
        "--harness",
        choices=("real", "lockstep"),
        default=None,
        help="real: sitl serve + the service over UDP; lockstep: no sockets. Default: real for one scenario, "
        "lockstep for --seeds; 'all' flies the paper's four real and the others lockstep",
    )
    p.add_argument(
        "--autopilot",
        choices=("builtin", "px4"),
        default="builtin",
        help="builtin: the simulator's own PX4-like autopilot (default); px4: real PX4 SITL with SIH "
        "physics, the real path only, 'all' = the paper's four (the build: SITL_PX4__BINARY or [px4] binary "
        "in config/sitl.toml)",
    )
    p.add_argument(
        "--detector",
        choices=("network", "truth"),
        default="network",
        help="network: the shipped weights (default); truth: the simulator's boxes (harness check only)",
    )
    p.add_argument(
        "--set",
        action="append",
        default=[],
        metavar="SECTION.KEY=VALUE",
        help="override a service config key for these runs (TOML value), e.g. formation.kp_xy=1.5",
    )
    p.add_argument(
        "--timing",
        type=Path,
        default=None,
        metavar="FILE",
        help="merge a timing profile into the scenario: [timing] (the lockstep camera pipeline) and "
        "[vehicles.NAME.link] (MAVLink latency, jitter, loss), e.g. config/timing/real-path.toml",
    )
    p.add_argument("--no-plots", action="store_true", help="write the report without plots")
    p.add_argument(
        "--executor",
        choices=("local", "ray"),
        default="local",
        help="--seeds on this machine's process pool (local, default) or as Ray tasks (ray: pip install "
        "'.[cluster]')",
    )
    p.add_argument(
        "--ray-address",
        default=None,
        metavar="HOST:PORT",
        help="join this Ray cluster (default: start a local Ray on 127.0.0.1 with --jobs CPUs)",
    )
    p.add_argument(
        "--ray-ship",
        action="store_true",
        help="ship this checkout to the Ray workers (runtime environment working_dir)",
    )
    p.add_argument(
        "--resume", action="store_true", help="--seeds: skip the seeds whose report.json is already in --out"
    )
    p.add_argument("--progress", choices=("line", "json"), default="line", help=argparse.SUPPRESS)
    p.set_defaults(handler=_sim)


def _sim(args: argparse.Namespace) -> int:
    from companion.lab.evaluation.campaign import (
        RunSpec,
        parse_seeds,
        read_timing_profile,
        require_weights,
        run_many,
        run_one,
        split_done,
    )
    from companion.lab.evaluation.report import summary_markdown
    from companion.lab.evaluation.setup import all_scenarios, scenario_path

    out: Path = args.out
    harness = args.harness or ("lockstep" if args.seeds or _is_formation(args.scenario) else "real")
    if args.autopilot == "px4" and args.harness == "lockstep":
        raise SystemExit("companion sim: --autopilot px4 flies the real path only (PX4 runs in real time)")
    if args.autopilot == "px4" and args.jobs is not None and args.jobs > 1:
        raise SystemExit(
            "companion sim: --autopilot px4 flies one run at a time (PX4 SITL runs in real time on this "
            "host and each instance takes its own ports); drop --jobs"
        )
    if args.autopilot == "px4":
        harness = "real"
    if args.jobs is None:
        args.jobs = 2
    if args.jobs < 1:
        raise SystemExit("companion sim: --jobs must be at least 1")
    common: dict[str, Any] = {
        "harness": harness,
        "autopilot": args.autopilot,
        "detector": args.detector,
        "speed": args.speed,
        "duration_s": args.duration,
        "plots": not args.no_plots,
        "overrides": tuple(args.set),
        "timing": None if args.timing is None else read_timing_profile(args.timing)[0],
    }
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join(p for p in (os.getcwd(), os.environ.get("PYTHONPATH")) if p),
    }
    if args.seeds is None and (args.executor != "local" or args.ray_address or args.ray_ship or args.resume):
        raise SystemExit("companion sim: --executor, --ray-address, --ray-ship and --resume go with --seeds")
    if args.executor == "ray" and harness != "lockstep":
        raise SystemExit("companion sim: --executor ray runs the lockstep harness only")
    if args.detector == "network":
        require_weights(tuple(args.set))  # one clear line now, not one per child run
    if args.seeds is not None:
        if args.scenario == "all":
            raise SystemExit("companion sim: --seeds needs one --scenario")
        scenario_path(args.scenario)  # fail fast on a typo
        specs = [
            RunSpec(args.scenario, s, out / f"seed-{s:03d}", **{**common, "plots": False})
            for s in parse_seeds(args.seeds)
        ]
        todo, done = split_done(specs, args.resume)
        if done:
            print(f"sim: {len(done)} of {len(specs)} seeds already have a report in {out}; running the rest")
        if args.executor == "ray":
            from companion.lab.evaluation.ray_executor import RayOptions, run_campaign

            options = RayOptions(
                address=args.ray_address,
                local_cpus=args.jobs,
                ship=args.ray_ship,
                local_env={"PYTHONPATH": env["PYTHONPATH"]},
            )
            summary = run_campaign(todo, out, options=options, stream=sys.stderr, already_done=done)
        else:
            summary = run_many(
                todo, out, jobs=args.jobs, env=env, stream=sys.stdout, monte_carlo=True, already_done=done
            )
        print(f"sim: {summary['runs']} runs, outcomes {summary['outcomes']}; {out / 'summary.md'}")
        return 0
    if args.scenario == "all":
        specs = [
            RunSpec(
                name,
                _seed(name, args.seed),
                out / name,
                **{**common, "harness": _all_harness(name, args.harness, args.autopilot)},
            )
            for name in (PAPER_SCENARIOS if args.autopilot == "px4" else all_scenarios())
        ]
        summary = run_many(specs, out, jobs=args.jobs, env=env, stream=sys.stdout, monte_carlo=False)
        # The paper's table beside ours on the terminal too: the first thing a user wants to see.
        print()
        print(summary_markdown(summary["reports"]), end="")
        print(f"sim: {len(specs)} scenarios; {out / 'summary.md'}, plots in {out}/*/plots")
        return 0
    # One scenario, in this process.
    out.mkdir(parents=True, exist_ok=True)
    _log_to(out / "sim.log" if args.progress == "json" else None, args)
    spec = RunSpec(args.scenario, _seed(args.scenario, args.seed), out, **common)
    end_s: list[float] = [float("nan")]
    wall0_s = time.monotonic()

    def progress(t_s: float) -> None:
        if args.progress == "json":
            print(json.dumps({"t_s": round(t_s, 1), "end_s": end_s[0]}), flush=True)
        else:
            print(f"\rsim: {spec.scenario} {_progress_line(t_s, end_s[0], time.monotonic() - wall0_s)}",
                  end="", flush=True)  # fmt: skip

    from companion.lab.evaluation.campaign import effective_scenario

    end_s[0] = effective_scenario(scenario_path(spec.scenario), spec.duration_s).run.duration_s
    report = run_one(spec, progress)
    if args.progress == "line":
        from companion.lab.evaluation.metrics import outcome_words

        print()
        print(
            f"sim: {report['scenario']}: {outcome_words(report)}, relative position RMSE "
            f"{_fmt(report['relative_position_rmse_m'])} m, formation max deviation "
            f"{_fmt(report['formation_max_deviation_m'])} m; {out / 'report.md'}"
        )
    return 0


#: The paper's scenarios: ``all`` flies them on the real path; the others in lockstep beside them, so that
#: ``all`` fits in 10 minutes on two cores (docs/evaluation.md). ``--harness`` forces one harness for all.
PAPER_SCENARIOS = ("straight", "circle", "gps-loss", "visibility")


def _all_harness(name: str, forced: str | None, autopilot: str = "builtin") -> str:
    if forced is not None:
        return forced
    if autopilot == "px4":
        return "real"
    return "real" if name in PAPER_SCENARIOS else "lockstep"


def _seed(name: str, given: int | None) -> int:
    """``--seed``, or the scenario file's own seed when it is not given."""
    if given is not None:
        return given
    from companion.lab.evaluation.campaign import effective_scenario
    from companion.lab.evaluation.setup import scenario_path

    return int(effective_scenario(scenario_path(name), None).seed)


def _is_formation(name: str) -> bool:
    """Whether a scenario flies a formation (those fly in lockstep by default)."""
    if name == "all":
        return False
    from companion.lab.evaluation.campaign import effective_scenario
    from companion.lab.evaluation.setup import scenario_path

    return bool(effective_scenario(scenario_path(name), None).formation)


def _progress_line(t_s: float, end_s: float, wall_s: float) -> str:
    """``sim time / total (percent), elapsed, ETA`` from the run's pace so far."""
    frac = t_s / end_s if end_s > 0 else 0.0
    eta = "?" if frac <= 0.02 else f"{wall_s * (1.0 - frac) / frac:.0f} s"
    return f"t = {t_s:5.1f} / {end_s:.0f} s sim ({100.0 * frac:3.0f} %), {wall_s:.0f} s elapsed, ETA {eta}   "


def _fmt(v: float | None) -> str:
    return "n/a" if v is None else f"{v:.3f}"


def _log_to(path: Path | None, args: argparse.Namespace) -> None:
    """Service and simulator-client logs: to stderr for a single run, to a file for a child of 'all'."""
    import logging

    setup_logging(args.log_format or "human", args.log_level or "WARNING")
    if path is not None:
        handler = logging.FileHandler(path)
        handler.setFormatter(logging.getLogger().handlers[0].formatter)
        logging.getLogger().handlers[:] = [handler]
