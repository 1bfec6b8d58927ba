"""Rendered perception sequences: a hovering follower, the leader moving 3-12 m ahead (docs/perception.md).

Renders with the simulator's camera (``sitl.render``: D435i intrinsics, stereo noise on disparity,
holes, range cut-off) and records to the folder format with ground truth, for ``companion replay``::

    python -m tests.render_sequences runs/perception/weave --path weave --seconds 30 --seed 11
    companion replay --source file:runs/perception/weave --out runs/perception/weave.csv

Paths (leader relative to the follower, NED; the follower hovers with a 1-2 deg attitude wobble):
    weave: range 3 -> 12 -> 3 m over 24 s, weaving +-1.5 m sideways and +-0.6 m vertically.
    arc:   range 7.5 +- 4.5 m over 30 s, a wider sideways arc (+-2.5 m at 8 m) and +-1 m vertically.
The leader tilts along its acceleration and yaws at 0.3 rad/s, as a flying quad does.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import MountConfig, RgbdFrame
from companion.kernel.frames import quat_from_euler
from companion.perception.record import FolderRecorder

G_M_S2 = 9.81
PATHS = ("weave", "arc")


@dataclass(frozen=True)
class Pose:
    """What the renderer needs of a vehicle (its PoseTruth protocol)."""

    p_ned_m: NDArray[np.float64]
    q_ned_body_wxyz: NDArray[np.float64]


def leader_rel_ned(path: str, t_s: float) -> NDArray[np.float64]:
    """Leader position relative to the follower, NED, m."""
    if path == "weave":
        r = 7.5 - 4.5 * math.cos(2 * math.pi * t_s / 24.0)
        lat = 1.5 * math.sin(2 * math.pi * t_s / 9.0)
        up = 0.6 * math.sin(2 * math.pi * t_s / 7.0)
    elif path == "arc":
        r = 7.5 + 4.5 * math.sin(2 * math.pi * t_s / 30.0)
        lat = 2.5 * math.sin(2 * math.pi * t_s / 13.0) * (r / 8.0)
        up = 1.0 * math.sin(2 * math.pi * t_s / 11.0)
    else:
        raise ValueError(f"unknown path {path!r} (one of {PATHS})")
    return np.array([r, lat, -up])


def frames(
    path: str, seconds: float, *, seed: int, depth_max_m: float = 10.0, fps: float = 30.0, t0_s: float = 100.0
) -> Iterator[RgbdFrame]:
    """Rendered frames with ground truth (imports the renderer lazily: it needs an EGL context)."""
    from sitl.render.config import CameraModel, VisualConfig
    from sitl.render.renderer import Renderer

    follower_p = np.array([0.0, 0.0, -12.0])
    with Renderer(CameraModel(depth_max_m=depth_max_m), VisualConfig(), MountConfig(), seed=seed) as renderer:
        for k in range(round(seconds * fps)):
            t = k / fps
            roll = math.radians(1.0) * math.sin(2 * math.pi * t / 3.1)
            pitch = math.radians(1.0) * math.sin(2 * math.pi * t / 4.3)
            yaw = math.radians(2.0) * math.sin(2 * math.pi * t / 7.7)
            follower = Pose(follower_p, quat_from_euler(roll, pitch, yaw))
            p = leader_rel_ned(path, t)
            dt = 1e-3
            a = (leader_rel_ned(path, t + dt) - 2 * p + leader_rel_ned(path, t - dt)) / dt**2
            lyaw = 0.3 * t
            a_fwd = a[0] * math.cos(lyaw) + a[1] * math.sin(lyaw)
            a_right = -a[0] * math.sin(lyaw) + a[1] * math.cos(lyaw)
            q_leader = quat_from_euler(math.atan2(a_right, G_M_S2), -math.atan2(a_fwd, G_M_S2), lyaw)
            yield renderer.render(follower, Pose(follower_p + p, q_leader), t0_s + t)


def main(argv: list[str] | None = None) -> int:
    """Render one sequence to a folder recording."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--path", choices=PATHS, default="weave")
    ap.add_argument("--seconds", type=float, default=30.0)
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument(
        "--depth-max-m", type=float, default=10.0, help="the camera's depth cut-off (renderer: 10)"
    )
    args = ap.parse_args(argv)
    with FolderRecorder(args.out) as rec:
        for frame in frames(args.path, args.seconds, seed=args.seed, depth_max_m=args.depth_max_m):
            rec.write(frame)
    print(f"{rec.frames_written} frames -> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
