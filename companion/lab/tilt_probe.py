"""How well one RGB-D frame shows the leader's tilt: the measurement its acceleration could come from.

Run: ``python -m companion.lab.tilt_probe [--range-m 5] [--frames 240]``.

A multirotor accelerates horizontally at g tan(tilt) (1 m/s^2 is 5.8 degrees), so its tilt is its
acceleration without differentiating positions, and without their lag. The probe renders the leader
straight ahead of a level follower (the simulator's renderer, sensor noise included) at random roll and
pitch (+-10 degrees) and heading (+-30 degrees from facing away), and measures in the depth image inside
the true box, on the leader's pixels (within 0.4 m of the box's near depth, its 20th percentile: the
leader is the nearest thing in its box and may cover less than half of it):

* the silhouette's principal axis against the image rows (the tilt across the line of sight, roll for a
  leader facing away), and
* the slope of depth over height (the tilt along the line of sight, pitch).

Each is regressed on the true roll and pitch (with the heading as a nuisance term); the residual, divided
by the gain, is the tilt a single frame resolves, printed also as acceleration.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.kernel.frames import quat_from_euler
from sitl.render.config import CameraModel, VisualConfig
from sitl.render.geometry import VehiclePose
from sitl.render.renderer import Renderer

#: Pixels further than this from the box's near depth are not the leader, m.
MASK_DEPTH_M = 0.4
#: The box's near depth: this percentile of its valid depths.
NEAR_PERCENTILE = 20.0
#: Fewer leader pixels than this: no measurement.
MIN_PIXELS = 30
G_M_S2 = 9.81


def silhouette_tilt(
    depth_m: NDArray[np.floating[Any]], box_xyxy_px: tuple[float, float, float, float], fy_px: float
) -> tuple[float, float] | None:
    """The leader's principal-axis angle and depth slope in a box, degrees, or None (too few pixels).

    The axis angle is against the image rows, positive turning from +u (right) towards +v (down); the
    slope is atan(d depth / d height below the centre), height in metres at the leader's depth.
    """
    x0, y0, x1, y1 = (round(b) for b in box_xyxy_px)
    d = np.asarray(depth_m[max(0, y0) : y1, max(0, x0) : x1], dtype=np.float64)
    valid = np.isfinite(d) & (d > 0.1)
    if valid.sum() < MIN_PIXELS:
        return None
    near_m = float(np.percentile(d[valid], NEAR_PERCENTILE))
    mask = valid & (np.abs(d - near_m) < MASK_DEPTH_M)
    if mask.sum() < MIN_PIXELS:
        return None
    v_px, u_px = np.nonzero(mask)
    u = u_px - u_px.mean()
    v = v_px - v_px.mean()
    axis_rad = 0.5 * math.atan2(2.0 * float(np.mean(u * v)), float(np.mean(u * u) - np.mean(v * v)))
    z = d[mask]
    below_m = v * float(np.median(z)) / fy_px
    spread = float(np.mean(below_m * below_m))
    if spread <= 0.0:
        return None
    slope = float(np.mean(below_m * (z - z.mean()))) / spread
    return math.degrees(axis_rad), math.degrees(math.atan(slope))


def run(frames: int, range_m: float, seed: int) -> dict[str, Any]:
    """Render ``frames`` leaders at ``range_m`` and regress the two measurements on the true tilt."""
    rng = np.random.default_rng(seed)
    camera = CameraModel()
    rows = []
    with Renderer(camera, VisualConfig(seed=seed), seed=seed) as r:
        for i in range(frames):
            roll, pitch = np.radians(rng.uniform(-10.0, 10.0, 2))
            yaw = math.radians(rng.uniform(-30.0, 30.0))
            follower = VehiclePose(np.array([0.0, 0.0, -5.0]), quat_from_euler(0.0, 0.0, 0.0))
            p_leader = np.array([range_m, rng.uniform(-0.3, 0.3), -5.0 + rng.uniform(-0.2, 0.2)])
            frame = r.render(follower, VehiclePose(p_leader, quat_from_euler(roll, pitch, yaw)), i / 15.0)
            box = frame.truth.box_xyxy_px if frame.truth is not None else None
            if box is None:
                continue
            m = silhouette_tilt(frame.depth_m, box, frame.intrinsics.fy_px)
            if m is not None:
                rows.append((math.degrees(roll), math.degrees(pitch), math.degrees(yaw), *m, box[2] - box[0]))
    a = np.asarray(rows)
    out: dict[str, Any] = {
        "frames": len(a),
        "range_m": range_m,
        "box_width_px_median": float(np.median(a[:, 5])),
    }
    for name, truth_col, meas_col in (("across", 0, 3), ("along", 1, 4)):
        x = np.column_stack([a[:, truth_col], a[:, 2], np.ones(len(a))])
        coef, *_ = np.linalg.lstsq(x, a[:, meas_col], rcond=None)
        resid = float(np.std(a[:, meas_col] - x @ coef))
        tilt_deg = resid / abs(coef[0])
        out[name] = {
            "gain": round(float(coef[0]), 3),
            "heading_term": round(float(coef[1]), 3),
            "residual_deg": round(resid, 2),
            "tilt_sigma_deg": round(tilt_deg, 2),
            "accel_sigma_m_s2": round(G_M_S2 * math.tan(math.radians(tilt_deg)), 2),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    """Run the probe and print (and optionally write) the figures."""
    ap = argparse.ArgumentParser(prog="python -m companion.lab.tilt_probe", description=__doc__)
    ap.add_argument("--frames", type=int, default=240)
    ap.add_argument("--range-m", type=float, default=5.0)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = ap.parse_args(argv)
    r = run(args.frames, args.range_m, args.seed)
    print(json.dumps(r, indent=2))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(r, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
