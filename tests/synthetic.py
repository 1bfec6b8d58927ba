"""Synthetic RGB-D views of a quad-X leader for perception tests (ray-cast boxes, D435-like noise).

Independent of the production code on purpose: it ray-casts the leader as boxes (body, arms, motors,
props) in its own frame, so tests compare the estimate with geometry, not with the estimator's maths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import GroundTruth, Intrinsics, RgbdFrame

D435_COLOR = Intrinsics.from_hfov(640, 480, 69.0)


@dataclass(frozen=True)
class Part:
    """A box in the leader frame (x right, y down, z forward at zero yaw), rotated by yaw_rad about y."""

    centre_m: tuple[float, float, float]
    half_m: tuple[float, float, float]
    yaw_rad: float = 0.0


def quad_parts(span_m: float = 0.45) -> list[Part]:
    """Body, four diagonal arms, motors and props of a quad-X with the given motor-to-motor span."""
    r = span_m / 2.0
    parts = [Part((0.0, 0.0, 0.0), (0.06, 0.04, 0.05))]
    for k in range(4):
        a = math.pi / 4 + k * math.pi / 2
        mx, mz = r * math.sin(a), r * math.cos(a)
        parts.append(Part((mx / 2, 0.0, mz / 2), (0.012, 0.01, r / 2), yaw_rad=a))
        parts.append(Part((mx, -0.02, mz), (0.018, 0.025, 0.018)))
        parts.append(Part((mx, -0.05, mz), (0.09, 0.004, 0.09), yaw_rad=a))
    return parts


def _ray_boxes(
    dirs: NDArray[np.float64], p_centre: NDArray[np.float64], yaw_rad: float, parts: list[Part]
) -> NDArray[np.float64]:
    """Smallest ray parameter t (rays from the origin along ``dirs`` with z = 1) hitting any part."""
    t_best = np.full(dirs.shape[0], np.inf)
    for part in parts:
        a = yaw_rad + part.yaw_rad
        c, s = math.cos(a), math.sin(a)
        # Rotation about y (down) mapping box-frame vectors to camera: x' = c x + s z, z' = -s x + c z.
        R_cam_box = np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])
        cy, sy = math.cos(yaw_rad), math.sin(yaw_rad)
        R_cam_leader = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
        centre_cam = p_centre + R_cam_leader @ np.array(part.centre_m)
        o = R_cam_box.T @ (-centre_cam)
        d = dirs @ R_cam_box  # rows: R_cam_box.T @ dir
        half = np.array(part.half_m)
        with np.errstate(divide="ignore", invalid="ignore"):
            t1 = (-half - o) / d
            t2 = (half - o) / d
        tmin = np.nanmax(np.minimum(t1, t2), axis=1)
        tmax = np.nanmin(np.maximum(t1, t2), axis=1)
        hit = (tmax >= tmin) & (tmax > 0)
        t_best = np.where(hit & (tmin < t_best), tmin, t_best)
    return t_best


@dataclass
class View:
    """One rendered view: depth (m, 0 invalid), the leader mask, its tight box and true centre."""

    depth_m: NDArray[np.float32]
    leader_mask: NDArray[np.bool_]
    box_xyxy_px: tuple[float, float, float, float]
    p_cam_leader_m: NDArray[np.float64]


def render(
    p_cam_leader_m: tuple[float, float, float] | NDArray[np.float64],
    *,
    intr: Intrinsics = D435_COLOR,
    yaw_rad: float = 0.3,
    span_m: float = 0.45,
    background_m: float | None = 25.0,
    rng: np.random.Generator | None = None,
    subpixel_px: float = 0.08,
    baseline_m: float = 0.05,
    hole_fraction: float = 0.0,
    depth_max_m: float | None = None,
) -> View:
    """Depth image of the leader at ``p_cam_leader_m`` in front of a wall (or sky when None).

    With ``rng``, each valid pixel's disparity ``f * baseline / z`` gets Gaussian noise of ``subpixel``
    px (so depth noise is ``z^2 * subpixel / (f * baseline)``), a ``hole_fraction`` of pixels becomes
    invalid, and noisy depths beyond ``depth_max_m`` are dropped, as a D435 does.
    """
    p = np.asarray(p_cam_leader_m, dtype=np.float64)
    w, h = intr.width_px, intr.height_px
    depth = np.zeros((h, w), dtype=np.float64)
    if background_m is not None:
        depth[:] = background_m
    mask = np.zeros((h, w), dtype=bool)
    # Only cast rays near the leader's projection: the rest is background.
    r_px = 0.8 * span_m * intr.fx_px / max(p[2] - span_m, 0.3) + 2.0
    u0 = intr.fx_px * p[0] / p[2] + intr.cx_px
    v0 = intr.fy_px * p[1] / p[2] + intr.cy_px
    x0, x1 = max(0, int(u0 - r_px)), min(w, int(u0 + r_px) + 1)
    y0, y1 = max(0, int(v0 - r_px)), min(h, int(v0 + r_px) + 1)
    if x1 > x0 and y1 > y0:
        vv, uu = np.mgrid[y0:y1, x0:x1]
        dirs = np.stack(
            [
                (uu.ravel() - intr.cx_px) / intr.fx_px,
                (vv.ravel() - intr.cy_px) / intr.fy_px,
                np.ones(uu.size),
            ],
            axis=1,
        )
        t = _ray_boxes(dirs, p, yaw_rad, quad_parts(span_m)).reshape(uu.shape)
        hit = np.isfinite(t)
        sub = depth[y0:y1, x0:x1]
        sub[hit] = t[hit]  # dirs have z = 1, so the ray parameter is the depth
        mask[y0:y1, x0:x1] = hit
    if not mask.any():
        raise ValueError("leader not visible")
    ys, xs = np.nonzero(mask)
    box = (float(xs.min()), float(ys.min()), float(xs.max() + 1), float(ys.max() + 1))
    if rng is not None:
        valid = depth > 0
        fb = intr.fx_px * baseline_m
        disp = (
            np.where(valid, fb / np.where(valid, depth, 1.0), 0.0)
            + rng.normal(size=depth.shape) * subpixel_px
        )
        depth = np.where(valid & (disp > 0), fb / np.where(disp > 0, disp, 1.0), 0.0)
        if hole_fraction > 0:
            depth[rng.random(depth.shape) < hole_fraction] = 0.0
    if depth_max_m is not None:
        depth[depth > depth_max_m] = 0.0
    return View(depth.astype(np.float32), mask, box, p)


def frame_from_view(view: View, stamp_s: float, seq: int, intr: Intrinsics = D435_COLOR) -> RgbdFrame:
    """An RgbdFrame (grey leader on a blue background) with ground truth from a view."""
    rgb = np.empty((intr.height_px, intr.width_px, 3), dtype=np.uint8)
    rgb[:] = (90, 140, 200)
    rgb[view.leader_mask] = (40, 40, 40)
    rgb[..., 0] = (rgb[..., 0].astype(np.int32) + seq) % 256  # frames differ: exact read-back is checked
    x, y, z = view.p_cam_leader_m
    truth = GroundTruth(
        box_xyxy_px=view.box_xyxy_px,
        visible_fraction=1.0,
        p_cam_leader_m=view.p_cam_leader_m.copy(),
        yaw_rel_rad=0.3,
        p_ned_follower_m=np.array([0.0, 0.0, -5.0]),
        p_ned_leader_m=np.array([z, x, -5.0 + y]),
        q_ned_follower_wxyz=np.array([1.0, 0.0, 0.0, 0.0]),
    )
    return RgbdFrame(rgb=rgb, depth_m=view.depth_m, intrinsics=intr, stamp_s=stamp_s, seq=seq, truth=truth)


def leader_path_cam(t_s: float) -> NDArray[np.float64]:
    """A leader weaving 4-7 m ahead of a hovering follower (camera frame), under 1 m/s^2 as flown."""
    return np.array([1.2 * math.sin(0.6 * t_s), 0.3 * math.sin(0.5 * t_s), 5.5 - 1.5 * math.cos(0.8 * t_s)])


def sequence_frames(n: int, *, fps: float = 30.0, seed: int = 0, t0_s: float = 50.0) -> list[RgbdFrame]:
    """``n`` noisy frames of the leader on :func:`leader_path_cam`, with ground truth."""
    rng = np.random.default_rng(seed)
    frames = []
    for k in range(n):
        t = k / fps
        view = render(leader_path_cam(t), rng=rng, yaw_rad=0.2 + 0.1 * t, hole_fraction=0.03)
        frames.append(frame_from_view(view, t0_s + t, seq=k))
    return frames
