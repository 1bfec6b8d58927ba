"""The depth guard: the nearest thing ahead in the depth image, other than where the tracker puts the leader.

Why: the separation barrier works on the tracker's estimate. When that estimate is wrong (a leader-sized
tree taken into a coasting track while the leader was hidden), the barrier keeps the follower off the
phantom, not off the leader. The depth image sees the leader, and anything else, whether the detector does
or not. Pixels where the tracker says the leader is, at the range it says, are left out: that leader is the
separation barrier's, with its velocity.

Pure: arrays in, a camera-frame point out. Hot path: a strided view of the central window, one boolean
mask, one partial sort of the near pixels.
"""

from __future__ import annotations

import numpy as np

from companion.kernel.camera import Intrinsics
from companion.kernel.frames import Vec3

#: Depth below this is the camera's own noise or the airframe, m.
MIN_RANGE_M = 0.3
#: Pixel stride of the search (640x480: a 320x144 window is 80x36 samples).
STRIDE = 4


def guard_range_m(
    v_ahead_m_s: float,
    *,
    min_range_m: float,
    max_range_m: float,
    separation_m: float,
    response_s: float,
    brake_m_s2: float,
) -> float:
    """How far ahead the depth guard looks, m: the follower's stopping distance, within the bounds.

    Stopping distance at ``v_ahead_m_s`` (speed toward what the camera looks at): ``separation_m`` to keep,
    ``response_s`` of the present speed before braking starts, then ``v^2 / 2 brake`` (the separation
    barrier's own numbers, so what the guard reports can still be braked for).
    """
    v = max(0.0, v_ahead_m_s)
    stop_m = separation_m + v * response_s + v * v / (2.0 * brake_m_s2)
    return min(max_range_m, max(min_range_m, stop_m))


def nearest_ahead(
    depth_m: np.ndarray,
    intrinsics: Intrinsics,
    *,
    max_range_m: float,
    window_frac: tuple[float, float],
    min_px: int,
    exclude_xyxy: tuple[float, float, float, float] | None = None,
    exclude_range_m: tuple[float, float] | None = None,
) -> Vec3 | None:
    """The nearest object in the central window, camera frame (x right, y down, z forward), m.

    Args:
        depth_m: depth along the optical axis, m, 0 = invalid.
        intrinsics: the colour camera's (depth is aligned to it).
        max_range_m: only what is nearer than this counts.
        window_frac: the window's width and height as fractions of the image, centred on the principal
            point (the ground stays out of a level camera's central band above ~2 m).
        min_px: how many sampled pixels an object needs (a few stray depth pixels are noise); the mean of
            the ``min_px`` nearest is returned.
        exclude_xyxy: where the tracked leader is in the image (x0, y0, x1, y1), px.
        exclude_range_m: the depths it may show there, m; pixels in the box at these depths are left out.

    Returns:
        The point, or None when fewer than ``min_px`` samples are nearer than ``max_range_m``.
    """
    h, w = depth_m.shape
    k = intrinsics
    fx, fy, cx, cy = k.fx_px, k.fy_px, k.cx_px, k.cy_px
    half_w, half_h = 0.5 * window_frac[0] * w, 0.5 * window_frac[1] * h
    x0, x1 = max(0, int(cx - half_w)), min(w, int(cx + half_w) + 1)
    y0, y1 = max(0, int(cy - half_h)), min(h, int(cy + half_h) + 1)
    sub = depth_m[y0:y1:STRIDE, x0:x1:STRIDE]
    near = (sub > MIN_RANGE_M) & (sub <= max_range_m)
    if exclude_xyxy is not None and exclude_range_m is not None:
        bx0, by0, bx1, by1 = exclude_xyxy
        c0 = max(0, int(np.ceil((bx0 - x0) / STRIDE)))
        c1 = max(0, int(np.floor((bx1 - x0) / STRIDE)) + 1)
        r0 = max(0, int(np.ceil((by0 - y0) / STRIDE)))
        r1 = max(0, int(np.floor((by1 - y0) / STRIDE)) + 1)
        if c1 > c0 and r1 > r0:
            box = sub[r0:r1, c0:c1]
            near[r0:r1, c0:c1] &= (box < exclude_range_m[0]) | (box > exclude_range_m[1])
    ys, xs = np.nonzero(near)
    if ys.size < min_px:
        return None
    z = sub[ys, xs]
    nearest = np.argpartition(z, min_px - 1)[:min_px]
    z_n = z[nearest].astype(np.float64)
    u = (x0 + xs[nearest] * STRIDE - cx) / fx
    v = (y0 + ys[nearest] * STRIDE - cy) / fy
    return np.array([float(np.mean(u * z_n)), float(np.mean(v * z_n)), float(np.mean(z_n))])
