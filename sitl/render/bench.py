"""``sitl bench-render``: rendered RGB-D frames per second at 640x480 with the full sensor model.

A follow scene (default world, leader 5-8 m ahead and moving, follower hovering and turning slowly):
every frame is ``Renderer.render`` - scene, D435i noise and holes, colour noise, ground-truth box and
visible fraction - read back to numpy. Reports the median over frames (after a warm-up), p90 and the
process CPU time per frame (llvmpipe's threads included), which is steadier than wall time on a shared
machine. ``--json PATH`` writes the numbers.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path
from typing import Any

import numpy as np

from companion.kernel.frames import quat_from_euler
from sitl.render.config import CameraModel, VisualConfig
from sitl.render.geometry import VehiclePose
from sitl.render.renderer import Renderer

WARMUP_FRAMES = 10


def run_bench(
    frames: int, camera: CameraModel | None = None, visual: VisualConfig | None = None
) -> dict[str, Any]:
    """Time ``frames`` renders of the follow scene; returns the summary dict."""
    camera = camera or CameraModel()
    wall: list[float] = []
    cpu: list[float] = []
    with Renderer(camera, visual or VisualConfig(seed=1), seed=1) as r:
        renderer_name = r.gl_renderer
        for i in range(frames + WARMUP_FRAMES):
            t_s = i / camera.rate_hz
            yaw = 0.2 * t_s
            follower = VehiclePose(
                np.array([0.0, 0.0, -5.0]), quat_from_euler(0.0, 0.0, yaw), np.array([0.0, 0.0, 0.2])
            )
            ang = yaw + 0.3 * math.sin(0.7 * t_s)
            dist = 6.5 + 1.5 * math.sin(0.3 * t_s)
            leader = VehiclePose(
                np.array([dist * math.cos(ang), dist * math.sin(ang), -5.5]), quat_from_euler(0.05, -0.1, ang)
            )
            w0, c0 = time.perf_counter(), time.process_time()
            frame = r.render(follower, leader, t_s)
            w1, c1 = time.perf_counter(), time.process_time()
            if i >= WARMUP_FRAMES:
                wall.append(w1 - w0)
                cpu.append(c1 - c0)
            assert frame.truth is not None  # noqa: S101 (the bench renders truth too)
    med = float(np.median(wall))
    return {
        "frames": frames,
        "width_px": camera.width_px,
        "height_px": camera.height_px,
        "gl_renderer": renderer_name,
        "median_ms": round(1000.0 * med, 2),
        "p90_ms": round(1000.0 * float(np.percentile(wall, 90)), 2),
        "fps_median": round(1.0 / med, 1),
        "cpu_ms_median": round(1000.0 * float(np.median(cpu)), 2),
        "cpu_count": os.cpu_count(),
        "load_avg_1min": round(os.getloadavg()[0], 2),
    }


def main(args: argparse.Namespace) -> int:
    """Entry point of ``sitl bench-render``."""
    res = run_bench(args.frames)
    print(
        f"sitl bench-render: {res['width_px']}x{res['height_px']} RGB-D + noise + truth"
        f" on {res['gl_renderer']}: "
        f"median {res['median_ms']} ms ({res['fps_median']} fps), p90 {res['p90_ms']} ms, "
        f"CPU {res['cpu_ms_median']} ms/frame over {res['frames']} frames "
        f"(load average {res['load_avg_1min']} on {res['cpu_count']} cores)"
    )
    if args.json is not None:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(res, indent=2) + "\n")
    return 0
