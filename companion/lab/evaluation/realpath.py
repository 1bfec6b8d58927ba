"""The real path: ``sitl serve`` in its own process, the service in this one, talking MAVLink over UDP.

One run (:func:`run_real`):

1. ``sitl serve`` starts with the scenario, the leader spawned in the follower's slot, a private block of UDP
   ports, and :mod:`companion.lab.evaluation.sitl_components` inside it (sim clock, truth recorder, the
   rendered camera on a Unix socket), passed in by :mod:`companion.lab.evaluation.sitl_host`.
2. :class:`~companion.app.FollowerService` runs here with the parts ``companion run`` builds
   (:func:`companion.service.wiring.make_parts_factory`): MAVSDK 4 over UDP, the simulator frame source, the
   detector, pose, tracker, mission runner. Its clock is the simulator's (:class:`SimClock`), so ``--speed``
   above 1 changes nothing the service can tell apart, and a host too slow for the speed only slows the run.
3. Two observers record what the service did: every control step (the mission's inputs and output) and
   every processed frame (detections, the tracker's estimate, the frame's ground truth). Neither feeds
   anything back.
4. At the scenario's end (or when the mission is over) the service is cancelled and the simulator stopped;
   the run is scored offline against the recorded truth
   (:class:`~companion.lab.evaluation.scoring.RunScorer`).

Every process started here is stopped here, by its PID, whatever happens.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import random
import resource
import shutil
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.config import Config
from companion.lab.evaluation.host import HostLoad
from companion.lab.evaluation.lockstep import LEADER_SHARE_HZ, RunResult
from companion.lab.evaluation.procs import REPO, Broker, Child, SimRunError
from companion.lab.evaluation.procs import SitlPorts as Ports
from companion.lab.evaluation.runlog import attach_run_log
from companion.lab.evaluation.scoring import RunScorer, snapshot_times
from companion.lab.evaluation.setup import leader_spawn_ned_m
from companion.lab.evaluation.simclock import SimClock
from companion.lab.evaluation.sitl_components import RUN_ENV
from companion.lab.evaluation.tomlw import toml_value
from companion.lab.evaluation.trace import RunObserver, TraceFrame
from companion.lab.evaluation.truthlog import TruthTrack, follower_of, leader_of
from companion.service.flight import Callbacks, FlightService
from companion.service.parts import PartsContext
from companion.viz.setup import health_flags

log = logging.getLogger(__name__)

SITL_BASE_CONFIG = REPO / "config" / "sitl.toml"
#: The module that runs ``sitl`` with the lab's components passed in.
SITL_HOST = "companion.lab.evaluation.sitl_host"
#: Truth samples per sim second (crash and landing detection, tick scoring).
TRUTH_RATE_HZ = 50.0
#: Wall time allowed for ``sitl serve`` (and its camera worker) to come up.
START_TIMEOUT_S = 90.0


def sitl_environment(
    cfg: Config,
    ports: Ports,
    base_vehicles: list[dict[str, Any]],
    offset_ne_m: tuple[float, float] = (0.0, 0.0),
) -> dict[str, str]:
    """``SITL_*`` overrides for this run: private ports, no GCS links, the leader spawned in its place.

    That is the follower's slot moved by the scenario's ``leader_spawn_offset_m`` (setup.leader_spawn_ned_m).
    """
    spawn = list(leader_spawn_ned_m(cfg, offset_ne_m))
    vehicles = [{**v, "spawn_ned_m": spawn} if v.get("role") == "leader" else v for v in base_vehicles]
    return {
        "SITL_MAVLINK__API_LOCAL_PORT_BASE": str(ports.api_local),
        "SITL_MAVLINK__API_REMOTE_PORT_BASE": str(ports.api_remote),
        "SITL_MAVLINK__REMOTE_HOST": "127.0.0.1",
        "SITL_MAVLINK__GCS_ENABLED": "false",
        "SITL_VEHICLES": toml_value(vehicles),
    }


def score(observer: RunObserver, truth: TruthTrack, scorer: RunScorer, end_s: float) -> None:
    """Feed the scorer in time order: truth samples, transitions, ticks and frames."""
    events: list[tuple[float, int, Any]] = [(float(t), 0, i) for i, t in enumerate(truth.t_s) if t <= end_s]
    events += [(tk.t_s, 1, tk) for tk in observer.ticks]
    events += [(fr.t_s, 2, fr) for fr in observer.frames]
    events.sort(key=lambda e: (e[0], e[1]))
    for t_s, kind, item in events:
        if kind == 0:
            row = truth.rows[item]
            fp, fv, fq = follower_of(row)
            lp, _, _ = leader_of(row)
            scorer.truth(t_s, fp, fv, fq, lp)
        elif kind == 1:
            for tr in item.transitions:
                scorer.transition(*tr)
            row = truth.at(t_s)
            fp, fv, fq = follower_of(row)
            lp, _, _ = leader_of(row)
            scorer.tick(
                t_s,
                fp,
                fv,
                fq,
                lp,
                item.rel_est_ned_m,
                yaw_service_rad=item.yaw_service_rad,
                v_cmd_ned_m_s=item.v_cmd_ned_m_s,
            )
        else:
            scorer.frame(
                t_s,
                item.truth,
                item.detections,
                item.rel_est_ned_m,
                latency_ms=item.compute_ms,
                rgb=item.rgb,
                range_meas_m=item.range_meas_m,
            )


@dataclass(frozen=True, slots=True)
class RealOptions:
    """Knobs of the real-path run."""

    speed: float = 1.0
    snapshots: int = 5
    #: ``builtin``: the simulator's own autopilot; ``px4``: a real PX4 SITL process per vehicle.
    autopilot: str = "builtin"
    #: Called now and then with the sim time (a progress line).
    progress: Callable[[float], None] | None = None
    #: The run's MCAP log, written by the service's recorder (:mod:`companion.lab.evaluation.runlog`).
    mcap_path: Path | None = None


async def run_real(  # noqa: PLR0917 (one call site, every argument needed)
    scenario_file: Path,
    scenario: Any,
    seed: int,
    cfg: Config,
    work_dir: Path,
    options: RealOptions,
) -> RunResult:
    """Fly ``scenario`` through the real service against ``sitl serve``; logs go to ``work_dir``."""
    from companion.app import FollowerService  # noqa: PLC0415 (the service's imports are heavy)
    from companion.service.systemd import NotifyConfig, SystemdNotifier  # noqa: PLC0415
    from companion.service.wiring import make_parts_factory  # noqa: PLC0415
    from sitl.config import load_sitl_config  # noqa: PLC0415

    work_dir.mkdir(parents=True, exist_ok=True)  # noqa: ASYNC240 (once, before anything runs)
    sock_dir = Path(tempfile.mkdtemp(prefix="wingman-sim-"))  # Unix socket paths must stay short
    rng = random.Random()  # noqa: S311 (port choice, not crypto)
    ports = Ports.pick(rng)
    clock_path = sock_dir / "clock"
    truth_path = work_dir / "truth.f64"
    settings = {
        "autopilot_log_path": str(work_dir / "autopilot.jsonl"),
        "camera_socket": str(sock_dir / "camera.sock"),
        "camera_rate_hz": scenario.run.camera_rate_hz,
        "clock_path": str(clock_path),
        "truth_path": str(truth_path),
        "truth_rate_hz": TRUTH_RATE_HZ,
        "seed": seed,
        "mount": cfg.camera.mount.model_dump(mode="json"),
        "leader_hidden_s": [list(w) for w in scenario.run.leader_hidden_s],
    }
    broker: Broker | None = None
    if cfg.leader.shared_position == "mqtt":
        # The leader's companion shares its autopilot's position over MQTT: a broker of the run's own.
        broker = Broker(work_dir, dict(os.environ))
        settings["leader_share"] = {
            "host": "127.0.0.1",
            "port": broker.port,
            "topic": cfg.mqtt.leader_topic,
            "rate_hz": LEADER_SHARE_HZ,
        }
    settings_path = work_dir / "sim.json"
    settings_path.write_text(json.dumps(settings, indent=2))
    base_vehicles = [
        v.model_dump(mode="json") for v in load_sitl_config(SITL_BASE_CONFIG, environ={}).vehicles
    ]
    env = {
        **os.environ,
        "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")]).rstrip(os.pathsep),
        RUN_ENV: str(settings_path),
        **sitl_environment(cfg, ports, base_vehicles, scenario.run.leader_spawn_offset_m),
    }
    follower_port = ports.follower_api
    if options.autopilot == "px4":
        follower_port = _px4_environment(env, base_vehicles, work_dir)
    args = [sys.executable, "-m", SITL_HOST, "--log-level", "INFO", "serve", "--no-camera"]
    args += ["--config", str(SITL_BASE_CONFIG), "--autopilot", options.autopilot]
    args += ["--scenario", str(scenario_file), "--speed", repr(options.speed), "--seed", str(seed)]
    sim = Child(args, env, work_dir / "sitl.log")
    service_cfg = cfg.model_copy(
        update={
            "link": cfg.link.model_copy(update={"url": f"udpin://0.0.0.0:{follower_port}"}),
            "camera": cfg.camera.model_copy(
                update={"source": "sim", "path": settings["camera_socket"], "stamps": "source"}
            ),
            "status": cfg.status.model_copy(update={"socket_path": str(sock_dir / "status.sock")}),
            # A simulated autopilot starts afresh each run (without a signing key): so does the service's
            # state (the signing timestamp, whether the key was given) unless a folder was named.
            "service": cfg.service.model_copy(
                update={"auto_start": True, "state_dir": cfg.service.state_dir or str(work_dir / "state")}
            ),
            "mqtt": cfg.mqtt.model_copy(
                update={"enabled": True, "host": "127.0.0.1", "port": broker.port}
                if broker is not None
                else {"enabled": False}
            ),
        }
    )
    (work_dir / "service-config.json").write_text(service_cfg.model_dump_json(indent=2))
    window = (
        scenario.run.formation_start_s,
        scenario.run.formation_start_s + scenario.run.formation_duration_s,
    )
    wall0 = time.perf_counter()
    cpu0 = _cpu_s()
    host = HostLoad()
    host.start()
    sim_clock: SimClock | None = None
    service: Any = None
    try:
        if broker is not None:
            await broker.start_and_wait()
        sim.start()
        sim_clock = await _wait_for_sim(
            sim,
            clock_path,
            Path(settings["camera_socket"]),
            options.speed,
            independent=options.autopilot == "px4",
        )
        observer = RunObserver(sim_clock, snapshot_times(window, options.snapshots))

        def on_flight(flight: FlightService, stack: contextlib.AsyncExitStack, ctx: PartsContext) -> None:
            # Frames reach the run's observer through the factory's on_frame, with their processing time.
            flight.observers.append(Callbacks(step=observer.on_step))
            if options.mcap_path is not None:
                recorder = attach_run_log(
                    service_cfg,
                    flight,
                    sim_clock,
                    options.mcap_path,
                    synchronous=False,
                    metadata={
                        "scenario": str(scenario.name),
                        "harness": "real",
                        "autopilot": options.autopilot,
                    },
                    health=health_flags(ctx.health),
                )
                if recorder is not None:
                    stack.enter_context(recorder)

        open_parts = make_parts_factory(
            service_cfg, sim_clock, on_frame=observer.on_frame, on_flight=on_flight
        )

        with SystemdNotifier(NotifyConfig()) as notifier:
            service = FollowerService(
                service_cfg,
                open_parts,
                clock=sim_clock,
                wall_time_s=time.time,
                notifier=notifier,
                freeze_heap=True,
            )
            await _fly(service, sim, sim_clock, scenario.run.duration_s, options.progress)
        end_s = sim_clock.now_s()
    finally:
        await sim.stop()
        if broker is not None:
            await broker.stop()
        if sim_clock is not None:
            sim_clock.close()
        shutil.rmtree(sock_dir, ignore_errors=True)
    truth = TruthTrack.read(truth_path)
    if len(truth) < 2:
        raise SimRunError(f"the simulator recorded no truth; its log:\n{sim.tail()}")
    scorer = RunScorer.for_scenario(scenario)
    score(observer, truth, scorer, end_s)
    scorer.snapshots = [_snapshot(fr) for fr in observer.frames if fr.rgb is not None]
    extra = scorer.extra()
    latency = service.latency.summary() if service is not None else {}
    extra.update(
        {
            "harness": "real",
            "speed": options.speed,
            "camera_rate_hz": scenario.run.camera_rate_hz,
            "service_latency_ms": latency,
            "control_tick_ages_ms": observer.timing(),
            "ticks_led_on_leader_share": observer.ticks_led_on_share,
            "ticks_coasted_on_leader_share": observer.ticks_coasted_on_share,
            "frames_received": service.frames() if service is not None else {},
            "run_wall_s": round(time.perf_counter() - wall0, 2),
            "run_cpu_s": {k: round(v - cpu0[k], 2) for k, v in _cpu_s().items()},
            "host": host.stop(sum(_cpu_s().values()) - sum(cpu0.values())),
            "sim_end_s": round(end_s, 2),
            "autopilot": read_autopilot_log(work_dir / "autopilot.jsonl", options.autopilot, work_dir),
        }
    )
    return RunResult(scorer.freeze(), scorer.snapshots, extra, observer)


def _px4_environment(env: dict[str, str], base_vehicles: list[dict[str, Any]], work_dir: Path) -> int:
    """``SITL_PX4__*`` for a PX4 run (free instance numbers, logs kept in ``work_dir``); the follower's port.

    The PX4 build comes from ``SITL_PX4__BINARY`` or the simulator config's ``[px4] binary``; a missing one
    is one line here, before anything starts.
    """
    from sitl.config import load_sitl_config  # noqa: PLC0415
    from sitl.px4.instance import Px4Build, Px4Ports, free_instance_base  # noqa: PLC0415

    binary = env.get("SITL_PX4__BINARY") or load_sitl_config(SITL_BASE_CONFIG, environ={}).px4.binary
    Px4Build.locate(binary)
    base = free_instance_base(len(base_vehicles))
    env["SITL_PX4__INSTANCE_BASE"] = str(base)
    env["SITL_PX4__LOG_DIR"] = str(work_dir)
    env["SITL_PX4__BINARY"] = binary
    index = next(i for i, v in enumerate(base_vehicles) if v.get("role") == "follower")
    return Px4Ports(base + index).api_remote


def _cpu_s() -> dict[str, float]:
    """CPU seconds (user + system) of this process (the service) and of its finished children (simulator)."""
    me, kids = resource.getrusage(resource.RUSAGE_SELF), resource.getrusage(resource.RUSAGE_CHILDREN)
    return {"service": me.ru_utime + me.ru_stime, "simulator": kids.ru_utime + kids.ru_stime}


#: Words in an autopilot's STATUSTEXT that mark a failsafe it chose by itself.
FAILSAFE_WORDS = ("failsafe", "blind land")


def read_autopilot_log(path: Path, backend: str, work_dir: Path) -> dict[str, Any]:
    """The follower's and leader's modes and texts as recorded by the simulator, and PX4's flight logs."""
    modes: list[dict[str, Any]] = []
    texts: list[dict[str, Any]] = []
    if path.exists():
        for line in path.read_text(encoding="utf-8").splitlines():
            with contextlib.suppress(ValueError):
                row = json.loads(line)
                (modes if "mode" in row else texts).append(row)
    failsafes = [
        t for t in texts if t["vehicle"] == "follower" and any(w in t["text"].lower() for w in FAILSAFE_WORDS)
    ]
    return {
        "backend": backend,
        "follower_modes": [m for m in modes if m["vehicle"] == "follower"],
        "leader_modes": [m for m in modes if m["vehicle"] == "leader"],
        "texts": texts,
        "follower_failsafes": failsafes,
        "flight_logs": sorted(str(p) for p in work_dir.glob("px4-*.ulg")),
    }


def _snapshot(fr: TraceFrame) -> Any:
    from companion.lab.evaluation.plots import Snapshot  # noqa: PLC0415

    best = max(fr.detections, key=lambda d: d.score, default=None)
    assert fr.rgb is not None  # noqa: S101 (filtered by the caller)
    return Snapshot(
        fr.t_s,
        fr.rgb,
        None if best is None else best.box_xyxy_px,
        None if fr.truth is None else fr.truth.box_xyxy_px,
        None if best is None else best.score,
    )


def _sim_ready(clock_path: Path, camera_socket: Path) -> bool:
    return clock_path.exists() and clock_path.stat().st_size > 0 and camera_socket.exists()


#: How far the service's clock may run past the last published time of an autopilot in its own process, s.
INDEPENDENT_CLOCK_LEAD_S = 0.5


async def _wait_for_sim(
    sim: Child, clock_path: Path, camera_socket: Path, speed: float, *, independent: bool = False
) -> SimClock:
    """Until the simulator runs, publishes its clock and serves the camera (its render worker is up).

    ``independent``: the autopilots keep their own time in their own processes (PX4), so the service's
    clock may run on past a late publication for longer: when a busy host held the publisher back, a
    clock stopped 50 ms after it fell behind PX4's, and the service stamped PX4's attitude a quarter of
    a second early (the frames then found no attitude and were dropped).
    """
    deadline = time.monotonic() + START_TIMEOUT_S
    while not _sim_ready(clock_path, camera_socket):
        if not sim.running:
            raise SimRunError(f"sitl serve exited while starting; its log:\n{sim.tail()}")
        if time.monotonic() > deadline:
            raise SimRunError(
                f"sitl serve did not start within {START_TIMEOUT_S:.0f} s; its log:\n{sim.tail()}"
            )
        await asyncio.sleep(0.1)
    return SimClock(clock_path, speed, max_lead_s=INDEPENDENT_CLOCK_LEAD_S if independent else 0.05)


async def _fly(
    service: Any, sim: Child, clock: SimClock, end_s: float, progress: Callable[[float], None] | None
) -> None:
    """Run the service until the scenario ends, the mission is over, or the simulator dies."""
    async with asyncio.TaskGroup() as tg:
        task = tg.create_task(service.run(), name="sim.service")
        next_progress_s = 0.0
        while not task.done():
            now_s = clock.now_s()
            if now_s >= end_s:
                break
            if not sim.running:
                task.cancel()
                raise SimRunError(f"sitl serve died at sim t = {now_s:.1f} s; its log:\n{sim.tail()}")
            if progress is not None and now_s >= next_progress_s:
                next_progress_s = now_s + 5.0
                progress(now_s)
            await asyncio.sleep(0.1)
        if not task.done():
            task.cancel()
