"""``sitl bench``: the lockstep real-time factor for two vehicles, without rendering.

The leader flies the ``straight`` path through its own autopilot; the follower takes off and holds
(armed by MAVLink commands on its API link). Each repeat builds a fresh world and flies
``--sim-s`` seconds; the figure reported is the median over ``--repeats`` (sim seconds per wall
second). A second figure runs the same with both API links open, so every default PX4 stream is
built as a message object (but not packed or sent): the cost a lockstep harness pays for listening.
The real-time factor per CPU second of this process is printed too: on a shared host, wall time
includes waiting for a core, which says more about the neighbours than about the simulator.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

from sitl.config import SitlConfig
from sitl.world.lockstep import World
from sitl.world.scenario import LeaderSpec, RunSpec, Scenario


def _scenario() -> Scenario:
    return Scenario(
        name="bench",
        seed=7,
        run=RunSpec(duration_s=120.0, formation_start_s=20.0, formation_duration_s=60.0),
        leader=LeaderSpec(type="straight", start_s=20.0, speed_m_s=2.0),
    )


def run_once(sim_s: float, with_links: bool) -> dict[str, float]:
    """Fly one world for ``sim_s`` and time it (construction excluded)."""
    world = World(SitlConfig(), _scenario())
    links = [world.link(name) for name in world.names] if with_links else []
    follower = world.vehicle("follower")
    arm = mavlink.MAVLink_command_long_message(follower.sysid, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)
    takeoff = mavlink.MAVLink_command_long_message(follower.sysid, 1, 22, 0, *([math.nan] * 7))
    sent = False
    messages = 0
    steps_per_s = round(1.0 / world.dt_s)
    t0 = time.perf_counter()
    c0 = time.process_time()
    while world.t_s < sim_s:
        for _ in range(steps_per_s // 10):
            world.step()
        if not sent and world.t_s >= 12.0:
            follower.autopilot.mavlink.handle_message(arm, None, 245, 190)
            follower.autopilot.mavlink.handle_message(takeoff, None, 245, 190)
            sent = True
        for link in links:
            messages += len(link.receive())
    wall_s = time.perf_counter() - t0
    cpu_s = time.process_time() - c0
    return {
        "sim_s": world.t_s,
        "wall_s": wall_s,
        "cpu_s": cpu_s,
        "rtf": world.t_s / wall_s,
        "rtf_cpu": world.t_s / cpu_s,
        "messages": messages,
    }


def main(args: argparse.Namespace) -> int:
    """Entry point of ``sitl bench``."""
    sim_s = float(getattr(args, "sim_s", 60.0) or 60.0)
    repeats = int(getattr(args, "repeats", 3) or 3)
    bare = [run_once(sim_s, with_links=False) for _ in range(repeats)]
    linked = [run_once(sim_s, with_links=True) for _ in range(repeats)]
    result: dict[str, Any] = {
        "vehicles": 2,
        "physics_rate_hz": SitlConfig().world.physics_rate_hz,
        "sim_s_per_run": sim_s,
        "repeats": repeats,
        "rtf_median": statistics.median(r["rtf"] for r in bare),
        "rtf_runs": [round(r["rtf"], 2) for r in bare],
        "rtf_cpu_median": statistics.median(r["rtf_cpu"] for r in bare),
        "load_average_1min": os.getloadavg()[0],
        "cpu_count": os.cpu_count(),
        "rtf_with_api_streams_median": statistics.median(r["rtf"] for r in linked),
        "stream_messages_per_sim_s": statistics.median(r["messages"] / r["sim_s"] for r in linked),
        "python": platform.python_version(),
        "machine": platform.machine(),
    }
    print(
        f"sitl bench: 2 vehicles lockstep at {result['physics_rate_hz']:.0f} Hz physics, no rendering: "
        f"real-time factor {result['rtf_median']:.1f}x (median of {repeats} x {sim_s:.0f} s; runs "
        f"{result['rtf_runs']}); with both API links streaming: {result['rtf_with_api_streams_median']:.1f}x"
    )
    print(
        f"sitl bench: per CPU second of this process: {result['rtf_cpu_median']:.1f}x "
        f"(host load average {result['load_average_1min']:.1f} on {result['cpu_count']} CPUs: "
        "on a shared host the wall-clock figure is lower than the machine can do)"
    )
    if args.json is not None:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=2) + "\n")
    return 0
