"""What a camera view holds, worked out on the CPU before drawing: culling, pixel spans and scissor boxes.

Pure numpy on bounding volumes (the bounding cubes of the leader and the other vehicles, the world
chunks' bounding spheres, distractor vertices), conservative everywhere: a box may hold pixels it need
not, never miss one.
Camera frame: x right, y down, z forward.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import Intrinsics
from sitl.render.config import CameraModel
from sitl.render.geometry import CameraPose, LeaderPose
from sitl.render.meshes import F32
from sitl.render.shaders import SHADOW_OFFSETS_PX
from sitl.render.surroundings import GROUND_HALF_M

NEAR_M = 0.05
FAR_M = 2.0 * GROUND_HALF_M
#: Corners of the cube [-1, 1]^3 (scaled by a bounding radius: the cube around a sphere).
UNIT_CUBE = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)

#: What could hide the leader: bounding spheres of the world chunks in view (centres in the camera frame,
#: radii), the distractor vertices (NED), if any, and the other vehicles (same bounding radius as the leader).
Blockers = tuple[NDArray[np.float64], NDArray[np.float64], F32 | None, Sequence[LeaderPose]]


def frustum_normals(intr: Intrinsics, margin_px: float) -> NDArray[np.float64]:
    """Inward unit normals (camera frame) of the view frustum's four side planes, widened by a margin."""
    W, H = intr.width_px, intr.height_px
    xl, xr = (-0.5 - margin_px - intr.cx_px) / intr.fx_px, (W - 0.5 + margin_px - intr.cx_px) / intr.fx_px
    yt, yb = (-0.5 - margin_px - intr.cy_px) / intr.fy_px, (H - 0.5 + margin_px - intr.cy_px) / intr.fy_px
    n = np.array([[1.0, 0.0, -xl], [-1.0, 0.0, xr], [0.0, 1.0, -yt], [0.0, -1.0, yb]])
    out: NDArray[np.float64] = n / np.linalg.norm(n, axis=1, keepdims=True)
    return out


def clip_half_plane(
    poly: list[tuple[float, float]], a: float, b: float, c: float
) -> list[tuple[float, float]]:
    """The part of a convex polygon where ``a x + b y + c >= 0`` (one Sutherland-Hodgman step)."""
    out: list[tuple[float, float]] = []
    for i, p in enumerate(poly):
        q = poly[(i + 1) % len(poly)]
        fp, fq = a * p[0] + b * p[1] + c, a * q[0] + b * q[1] + c
        if fp >= 0.0:
            out.append(p)
        if (fp >= 0.0) != (fq >= 0.0):
            t = fp / (fp - fq)
            out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def chunks_in_view(
    chunk_cam: NDArray[np.float64], radius_m: NDArray[np.float64], frustum_n: NDArray[np.float64]
) -> NDArray[np.bool_]:
    """Which world chunks' bounding spheres (centres in the camera frame) touch the view frustum.

    ``frustum_n``: the frustum's inward side-plane normals (:func:`frustum_normals`).
    """
    r = radius_m
    inside: NDArray[np.bool_] = np.all(chunk_cam @ frustum_n.T >= -r[:, None], axis=1) & (
        chunk_cam[:, 2] > NEAR_M - r
    )
    return inside


def may_hide_leader(
    cam: CameraPose,
    leader: LeaderPose,
    span: tuple[int, int, int, int],
    blockers: Blockers,
    *,
    intr: Intrinsics,
    bound_radius_m: float,
) -> bool:
    """Whether anything could stand between the camera and the leader's pixels (conservative).

    A world chunk or other vehicle whose bounding sphere starts nearer than the leader's far side and
    whose projected bounding cube overlaps the leader's pixel span; any distractor; the ground unless
    the camera and the whole leader are above it (then no line of sight between them crosses it).
    ``bound_radius_m``: the leader's (and every other vehicle's) bounding radius.
    """
    chunk_cam, radius, extra, others = blockers
    if extra is not None and len(extra):
        return True
    R = bound_radius_m
    if cam.p_ned_cam_m[2] >= 0.0 or leader.p_ned_m[2] + R >= 0.0:
        return True
    z_far = float(cam.to_cam(leader.p_ned_m)[2]) + R
    if others:
        chunk_cam = np.concatenate([chunk_cam, np.array([cam.to_cam(o.p_ned_m) for o in others])])
        radius = np.concatenate([radius, np.full(len(others), R)])
    front = chunk_cam[:, 2] - radius < z_far
    if not np.any(front):
        return False
    corners = chunk_cam[front][:, None, :] + radius[front][:, None, None] * UNIT_CUBE[None]
    if np.any(corners[..., 2] <= NEAR_M):
        return True
    u = intr.fx_px * corners[..., 0] / corners[..., 2] + intr.cx_px
    v = intr.fy_px * corners[..., 1] / corners[..., 2] + intr.cy_px
    x0, y0, x1, y1 = span
    overlap = (u.max(axis=1) >= x0 - 1) & (u.min(axis=1) <= x1 + 1)
    overlap &= (v.max(axis=1) >= y0 - 1) & (v.min(axis=1) <= y1 + 1)
    return bool(np.any(overlap))


def leader_span(
    cam: CameraPose, leader: LeaderPose | None, *, intr: Intrinsics, bound_radius_m: float
) -> tuple[tuple[int, int, int, int] | None, bool]:
    """Pixel rectangle (x0, y0, x1, y1) holding the leader (None: off screen); is it wholly in frame?

    The projection of the leader's bounding cube, a pixel wider on each side; the whole frame if the
    cube reaches behind the camera. ``bound_radius_m``: the leader's bounding radius.
    """
    if leader is None:
        return None, False
    W, H = intr.width_px, intr.height_px
    R = bound_radius_m
    corners = cam.to_cam(leader.p_ned_m) + R * UNIT_CUBE
    if np.any(corners[:, 2] <= NEAR_M):
        return (0, 0, W, H), False
    u = intr.fx_px * corners[:, 0] / corners[:, 2] + intr.cx_px
    v = intr.fy_px * corners[:, 1] / corners[:, 2] + intr.cy_px
    ux0, ux1 = math.floor(u.min()) - 1, math.ceil(u.max()) + 2
    vy0, vy1 = math.floor(v.min()) - 1, math.ceil(v.max()) + 2
    x0, x1, y0, y1 = max(ux0, 0), min(ux1, W), max(vy0, 0), min(vy1, H)
    if x1 <= x0 or y1 <= y0:
        return None, False
    return (x0, y0, x1, y1), (x0, x1, y0, y1) == (ux0, ux1, vy0, vy1)


def shadow_search_px(
    cam: CameraPose,
    leader: LeaderPose | None,
    extra: F32 | None,
    *,
    camera: CameraModel,
    intr: Intrinsics,
    Kinv: NDArray[np.floating[Any]],
    bound_radius_m: float,
    near_cam: NDArray[np.float64],
    near_r: NDArray[np.float64],
    others: Sequence[LeaderPose] = (),
) -> int:
    """Widest stereo shadow worth searching: disparity of the nearest thing in view, px.

    ``Kinv``: the inverse camera matrix; ``bound_radius_m``: the leader's (and the other vehicles')
    bounding radius; ``near_cam``, ``near_r``: bounding spheres (camera frame) of the world chunks
    within range; ``others``: the other vehicles.
    """
    z_near = 1e9
    for vehicle in (leader, *others):
        if vehicle is not None:
            z = float(cam.to_cam(vehicle.p_ned_m)[2]) - bound_radius_m
            if z > 0.0:
                z_near = min(z_near, z)
    # Ground seen along the image's bottom corners.
    h = -float(cam.p_ned_cam_m[2])
    if h > 0.0:
        W, H = intr.width_px, intr.height_px
        rays = cam.R_ned_cam @ Kinv @ np.array([[0.0, W - 1.0], [H - 1.0, H - 1.0], [1.0, 1.0]])
        down = rays[2]
        if np.any(down > 1e-6):
            z_near = min(z_near, float(np.min(h / down[down > 1e-6])))
    if near_r.size:
        z_near = min(z_near, float(max(np.min(near_cam[:, 2] - near_r), 0.3)))
    if extra is not None and len(extra):
        zs = (extra[:, :3].astype(np.float64) - cam.p_ned_cam_m) @ cam.R_ned_cam[:, 2]
        zs = zs[zs > NEAR_M]
        if zs.size:
            z_near = min(z_near, float(zs.min()))
    z_near = max(z_near, camera.depth_min_m)
    widest = math.ceil(camera.focal_baseline_px_m / z_near)
    return min((k for k in SHADOW_OFFSETS_PX if k >= widest), default=max(SHADOW_OFFSETS_PX))


def near_region(
    cam: CameraPose,
    leader: LeaderPose | None,
    extra: F32 | None,
    *,
    intr: Intrinsics,
    depth_max_m: float,
    bound_radius_m: float,
    shadow_px: int,
    near_cam: NDArray[np.float64],
    near_r: NDArray[np.float64],
    others: Sequence[LeaderPose] = (),
) -> tuple[int, int, int, int] | None:
    """Scissor box (x, y, w, h) around things near enough to have valid depth, or None.

    The leader and the other vehicles (their bounding cubes, ``bound_radius_m``), world chunks within
    range (their bounding spheres' cubes) and distractors; widened to the left by the stereo shadow.
    The whole frame if any of them straddles the image plane. The ground is :func:`ground_region`.
    """
    W, H = intr.width_px, intr.height_px
    z_max = depth_max_m
    pts: list[NDArray[np.float64]] = []
    R = bound_radius_m
    for vehicle in (leader, *others):
        if vehicle is not None:
            c = cam.to_cam(vehicle.p_ned_m)
            if c[2] - R < z_max:
                pts.append(c + R * UNIT_CUBE)
    if near_r.size:
        pts.append((near_cam[:, None, :] + near_r[:, None, None] * UNIT_CUBE[None]).reshape(-1, 3))
    if extra is not None and len(extra):
        pc = (extra[:, :3].astype(np.float64) - cam.p_ned_cam_m) @ cam.R_ned_cam
        pts.append(pc[pc[:, 2] < z_max + 1.0])
    if not pts:
        return None
    allp = np.concatenate(pts)
    if allp.size == 0:
        return None
    if np.any(allp[:, 2] <= NEAR_M):
        return (0, 0, W, H)
    u = intr.fx_px * allp[:, 0] / allp[:, 2] + intr.cx_px
    v = intr.fy_px * allp[:, 1] / allp[:, 2] + intr.cy_px
    x0 = max(math.floor(u.min()) - shadow_px - 3, 0)
    x1 = min(math.ceil(u.max()) + 3, W)
    y0 = max(math.floor(v.min()) - 3, 0)
    y1 = min(math.ceil(v.max()) + 3, H)
    if x1 <= x0 or y1 <= y0:
        return None
    return (x0, y0, x1 - x0, y1 - y0)


def ground_region(
    cam: CameraPose, *, intr: Intrinsics, Kinv: NDArray[np.floating[Any]], depth_max_m: float
) -> tuple[int, int, int, int] | None:
    """Scissor box (x, y, w, h) of the ground nearer than the depth range, or None.

    The ground (NED down = 0) at pixel (u, v) lies at depth ``h / g(u, v)``, with ``g`` the down
    component of the pixel's ray at unit depth, affine in (u, v): in range where
    ``g >= h / depth_max``, a half-plane of the image. ``Kinv``: the inverse camera matrix.
    """
    h = -float(cam.p_ned_cam_m[2])
    if h <= 0.0:
        return None  # at or below ground level: the ground is seen edge-on or from below (culled)
    W, H = intr.width_px, intr.height_px
    g = (cam.R_ned_cam @ Kinv)[2]
    frame = [(-0.5, -0.5), (W - 0.5, -0.5), (W - 0.5, H - 0.5), (-0.5, H - 0.5)]
    poly = clip_half_plane(frame, float(g[0]), float(g[1]), float(g[2]) - h / depth_max_m)
    if not poly:
        return None
    us, vs = [q[0] for q in poly], [q[1] for q in poly]
    x0, x1 = max(math.floor(min(us) + 0.5) - 1, 0), min(math.ceil(max(us) + 0.5) + 1, W)
    y0, y1 = max(math.floor(min(vs) + 0.5) - 1, 0), min(math.ceil(max(vs) + 0.5) + 1, H)
    if x1 <= x0 or y1 <= y0:
        return None
    return (x0, y0, x1 - x0, y1 - y0)
