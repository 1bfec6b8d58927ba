"""Pure pinhole pose of the leader from a detection box and the aligned depth image.

The paper takes the depth at the box centre. A quadrotor's box centre often shows background between
the arms, and stereo depth noise grows with Z^2, so instead:

1. **Robust depth** (:func:`robust_depth`): among the valid depth pixels inside the box, find the nearest
   dense cluster (the leader; background is behind it) and take a trimmed mean around it. The window
   is the leader's depth extent plus +-2.5 sigma of the stereo noise at that range.
2. **Surface to centre**: the cluster is the leader's visible surface; its centre lies
   ``surface_to_centre_m`` further along the viewing ray.
3. **Back-projection** of the box centre: ``p = K^-1 [u v 1]^T Z``.
4. **Covariance** from first-order propagation of box-centre jitter (pixels) and the depth error
   (``sigma_z = z^2 * subpixel / (f * baseline)`` per pixel, averaged over at most
   ``independent_depth_px`` pixels since stereo noise is spatially correlated, plus a shape term).
5. **Size prior**: ``size_ratio`` = box size / expected size of a leader of span ``span_m`` at that
   depth; the tracker rejects boxes whose ratio is off by more than its tolerance.

Everything here is pure: arrays and numbers in, a :class:`LeaderMeasurement` out; nothing copies the
image (the box is a view; only its valid pixels are gathered).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config import LeaderConfig, PoseConfig
from companion.frames import Mat3, Vec3
from companion.perception.types import DepthImage, Detection, Intrinsics

#: Trim window half-width in stereo-noise sigmas around the cluster centre.
_TRIM_SIGMAS = 2.5
#: A depth window is a candidate for the leader once it holds this fraction of the box's valid pixels.
_CLUSTER_FRACTION = 0.1
#: Above this many valid pixels, the cluster search runs on an even subsample (the mean uses all).
_SEARCH_SAMPLES = 2048


@dataclass(frozen=True, slots=True)
class DepthCluster:
    """The leader's depth inside a box: trimmed mean of its near cluster (camera z, m)."""

    z_m: float
    #: Pixels in the trimmed window, and all valid pixels inside the box.
    n_px: int
    n_valid_px: int
    #: Standard deviation of the pixels in the window, m (noise plus the leader's own depth extent).
    spread_m: float


@dataclass(frozen=True, slots=True)
class LeaderMeasurement:
    """One measurement of the leader's centre in the camera frame (x right, y down, z forward)."""

    stamp_s: float
    p_cam_leader_m: Vec3
    #: Covariance of ``p_cam_leader_m``, m^2 (symmetric positive definite).
    cov_cam_m2: Mat3
    #: Depth of the leader's visible surface (before the surface-to-centre correction), m.
    depth_surface_m: float
    n_depth_px: int
    #: Box size over the size a leader of the configured span would have at this depth (1 = as expected).
    size_ratio: float
    #: Bearing of the centre: azimuth positive right, elevation positive up, rad.
    azimuth_rad: float
    elevation_rad: float
    score: float
    box_xyxy_px: tuple[float, float, float, float]
    #: The box touches the image border: the leader may be cut off, its centre less certain.
    truncated: bool


def back_project(u_px: float, v_px: float, z_m: float, intr: Intrinsics) -> Vec3:
    """Camera-frame point at pixel (u, v) and depth z (along the optical axis): ``K^-1 [u v 1]^T z``."""
    return np.array(
        [(u_px - intr.cx_px) / intr.fx_px * z_m, (v_px - intr.cy_px) / intr.fy_px * z_m, z_m],
        dtype=np.float64,
    )


def project(p_cam_m: Vec3, intr: Intrinsics) -> tuple[float, float]:
    """Pixel (u, v) of a camera-frame point in front of the camera (z > 0)."""
    x, y, z = (float(c) for c in p_cam_m)
    return intr.fx_px * x / z + intr.cx_px, intr.fy_px * y / z + intr.cy_px


def bearing(p_cam_m: Vec3) -> tuple[float, float]:
    """(azimuth, elevation) in rad of a camera-frame point: azimuth positive right, elevation up."""
    x, y, z = (float(c) for c in p_cam_m)
    return math.atan2(x, z), math.atan2(-y, math.hypot(x, z))


def depth_sigma_m(z_m: float, focal_px: float, cfg: PoseConfig) -> float:
    """Per-pixel stereo depth noise at depth z: ``z^2 * subpixel / (f * baseline)``, m."""
    return cfg.stereo_subpixel_px / (focal_px * cfg.stereo_baseline_m) * z_m * z_m


def box_bounds(
    box_xyxy_px: tuple[float, float, float, float], width_px: int, height_px: int
) -> tuple[int, int, int, int]:
    """Integer pixel bounds (x0, y0, x1, y1), end-exclusive, of a box clipped to the image."""
    x0, y0, x1, y1 = box_xyxy_px
    return (
        max(0, math.floor(x0)),
        max(0, math.floor(y0)),
        min(width_px, math.ceil(x1)),
        min(height_px, math.ceil(y1)),
    )


def robust_depth(
    depth_m: DepthImage,
    bounds: tuple[int, int, int, int],
    *,
    focal_px: float,
    body_depth_m: float,
    cfg: PoseConfig,
) -> DepthCluster | None:
    """Depth of the nearest dense cluster of valid pixels inside ``bounds`` (the leader), or None.

    Background between the arms is farther than the leader, isolated near pixels are too few to form
    a dense window, and the stereo noise sets how wide a window the leader occupies at its range.

    Args:
        depth_m: H x W depth along the optical axis, m, 0 = invalid (not copied).
        bounds: (x0, y0, x1, y1) from :func:`box_bounds`.
        focal_px: focal length for the noise model, px.
        body_depth_m: the leader's own extent along the view, m.
        cfg: valid range, noise model and minimum pixel count.
    """
    x0, y0, x1, y1 = bounds
    if x1 <= x0 or y1 <= y0:
        return None
    roi = depth_m[y0:y1, x0:x1]
    valid = roi[(roi > cfg.depth_min_m) & (roi < cfg.depth_max_m)]
    n_valid = int(valid.size)
    if n_valid < cfg.min_valid_px:
        return None
    step = 1 + n_valid // _SEARCH_SAMPLES
    s = np.sort(valid[::step]).astype(np.float64)
    k_noise = cfg.stereo_subpixel_px / (focal_px * cfg.stereo_baseline_m)
    # Window starting at each sorted sample: the leader's extent plus the noise band at that depth.
    width = body_depth_m + 2.0 * _TRIM_SIGMAS * k_noise * s * s
    counts = np.searchsorted(s, s + width, side="right") - np.arange(s.size)
    # The nearest window holding a fair share of the pixels starts on the leader's near tail (lone
    # speckles in front are too few); the densest window starting inside it is the leader itself.
    need = max(float(cfg.min_valid_px) / step, _CLUSTER_FRACTION * s.size)
    dense = counts >= need
    if not dense.any():
        return None
    i = int(np.argmax(dense))
    i += int(np.argmax(counts[i : i + int(counts[i])]))
    centre = float(s[i + (int(counts[i]) - 1) // 2])
    sel = valid
    for _ in range(2):  # recentre twice: the first window starts on the cluster's near tail
        half = 0.5 * body_depth_m + _TRIM_SIGMAS * k_noise * centre * centre
        sel = valid[np.abs(valid - centre) <= half]
        if sel.size == 0:
            return None
        centre = float(sel.mean(dtype=np.float64))
    if sel.size < cfg.min_valid_px:
        return None
    return DepthCluster(
        z_m=centre, n_px=int(sel.size), n_valid_px=n_valid, spread_m=float(sel.std(dtype=np.float64))
    )


def measure_leader(
    depth_m: DepthImage,
    intr: Intrinsics,
    det: Detection,
    stamp_s: float,
    *,
    leader: LeaderConfig,
    cfg: PoseConfig,
) -> LeaderMeasurement | None:
    """The leader's centre in the camera frame from one detection, or None without enough depth."""
    bounds = box_bounds(det.box_xyxy_px, intr.width_px, intr.height_px)
    # A quad's visible surface spans about its motor-to-motor span in depth at the worst yaw.
    cluster = robust_depth(depth_m, bounds, focal_px=intr.fx_px, body_depth_m=leader.span_m, cfg=cfg)
    if cluster is None:
        return None
    u, v = det.center_px
    a = (u - intr.cx_px) / intr.fx_px
    b = (v - intr.cy_px) / intr.fy_px
    cos_ray = 1.0 / math.sqrt(1.0 + a * a + b * b)
    # The centre is surface_to_centre_m further along the ray than the visible surface.
    z = cluster.z_m + leader.surface_to_centre_m * cos_ray
    p_cam = np.array([a * z, b * z, z], dtype=np.float64)

    w_px, h_px = det.size_px
    x0, y0, x1, y1 = det.box_xyxy_px
    truncated = x0 <= 0.5 or y0 <= 0.5 or x1 >= intr.width_px - 1.5 or y1 >= intr.height_px - 1.5
    size_px = max(w_px, h_px)
    jitter = cfg.box_jitter_px + cfg.box_jitter_frac * size_px
    if truncated:  # the visible part's centre can be off by up to half the missing part
        jitter = max(jitter, 0.25 * size_px)
    n_eff = min(cluster.n_px, cfg.independent_depth_px)
    var_z = depth_sigma_m(z, intr.fx_px, cfg) ** 2 / n_eff + cfg.surface_model_std_m**2
    # p = (a z, b z, z) with a = (u - cx) / fx, b = (v - cy) / fy: Jacobian wrt (u, v, z).
    J = np.array([[z / intr.fx_px, 0.0, a], [0.0, z / intr.fy_px, b], [0.0, 0.0, 1.0]])
    cov = (J * np.array([jitter * jitter, jitter * jitter, var_z])) @ J.T
    az, el = bearing(p_cam)
    return LeaderMeasurement(
        stamp_s=stamp_s,
        p_cam_leader_m=p_cam,
        cov_cam_m2=0.5 * (cov + cov.T),
        depth_surface_m=cluster.z_m,
        n_depth_px=cluster.n_px,
        size_ratio=size_px * z / (intr.fx_px * leader.span_m),
        azimuth_rad=az,
        elevation_rad=el,
        score=det.score,
        box_xyxy_px=det.box_xyxy_px,
        truncated=truncated,
    )


def measure_all(
    depth_m: DepthImage,
    intr: Intrinsics,
    detections: list[Detection],
    stamp_s: float,
    *,
    leader: LeaderConfig,
    cfg: PoseConfig,
) -> list[LeaderMeasurement]:
    """:func:`measure_leader` for every detection of a frame; boxes without usable depth are dropped."""
    out = []
    for det in detections:
        m = measure_leader(depth_m, intr, det, stamp_s, leader=leader, cfg=cfg)
        if m is not None:
            out.append(m)
    return out
