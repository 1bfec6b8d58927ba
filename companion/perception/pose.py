"""Pure pinhole pose of the leader from a detection box and the aligned depth image.

The paper takes the depth at the box centre. A quadrotor's box centre often shows background between
the arms, and stereo depth noise grows with Z^2, so instead:

1. **Robust depth** (:func:`robust_depth`): among the valid depth pixels inside the box, find the nearest
   dense cluster (the leader; background is behind it), then take a trimmed mean in *disparity*
   (``f * baseline / z``), where stereo noise is Gaussian with a constant sigma, so the mean is unbiased.
   Near ``depth_max_m`` the far half of the noise falls out of range; that truncation is undone
   (truncated-normal mean), instead of reading the leader up to 0.2 m short at 10 m.
2. **Surface to centre**: the cluster is the leader's visible surface; its centre lies
   ``surface_to_centre_m`` further along the viewing ray. The box's middle sits ``box_centre_below_m``
   below the leader's centre (legs hang below, props sit above): moved up along gravity.
3. **Back-projection** of the box centre: ``p = K^-1 [u v 1]^T Z``.
4. **Covariance** from first-order propagation of box-centre jitter (pixels) and the depth error
   (``sigma_z = z^2 * subpixel / (f * baseline)`` per pixel, averaged over at most
   ``independent_depth_px`` pixels since stereo noise is spatially correlated, plus a shape term).
5. **Size prior**: ``size_ratio`` = box size / expected size of a leader of span ``span_m`` at that
   depth; the tracker rejects boxes whose ratio is off by more than its tolerance.
6. **Beyond the stereo range** (or in a depth hole) the range comes from the box size
   (:func:`range_from_size`), mostly its height (its width changes with the leader's yaw), with the
   leader's apparent size and the box's per-frame noise learnt online from depth just inside the
   stereo range (:class:`SizeCalibrator`). About 10-25 % per frame, white: weighted at the predicted
   range and linearised there (the box side is linear in 1/z), so that the tracker averages it
   without a bias.

Everything here is pure: arrays and numbers in, a :class:`LeaderMeasurement` out; nothing copies the
image (the box is a view; only its valid pixels are gathered). Steps 1 and 2's depth search is
:mod:`companion.perception.box_depth`, step 6's ranging :mod:`companion.perception.size_range`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config import LeaderConfig, PoseConfig
from companion.kernel.camera import DepthImage, Intrinsics
from companion.kernel.frames import Mat3, Vec3
from companion.perception.box_depth import box_bounds, depth_sigma_m, robust_depth, size_consistent_cluster
from companion.perception.size_range import SizeCalibrator, SizePrior, range_from_size
from companion.perception.types import Detection

_CAM_DOWN = np.array([0.0, 1.0, 0.0])
#: Size-ranged readings are limited to this many sigmas from the predicted range.
_SIZE_CLAMP_SIGMAS = 3.0


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
    #: Where the range came from: "depth" (stereo) or "size" (box size, beyond the stereo range).
    range_source: str = "depth"
    #: The box's width and height at the measured range, m (what the size calibration learns from).
    width_m: float = math.nan
    height_m: float = math.nan
    #: The detection's :attr:`~companion.perception.types.Detection.scale`.
    box_scale: float = 1.0


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


def measure_leader(
    depth_m: DepthImage,
    intr: Intrinsics,
    det: Detection,
    stamp_s: float,
    *,
    leader: LeaderConfig,
    cfg: PoseConfig,
    size_prior: SizePrior | None = None,
    down_cam: Vec3 | None = None,
    z_hint_m: float | None = None,
    z_hint_std_m: float = math.inf,
) -> LeaderMeasurement | None:
    """The leader's centre in the camera frame from one detection, or None without a usable range.

    Range comes from the box's depth cluster; without one (beyond the stereo range, a depth hole) and
    with a ``size_prior``, from the box size, with the size's uncertainty, unless the leader would have
    had depth there (``cfg.size_fallback_min_frac``): then there is no measurement. The box centre's point is
    moved up by ``leader.box_centre_below_m`` along ``down_cam`` (gravity in the camera frame at the
    frame's attitude; the camera's own y axis when None) to reach the leader's centre. ``z_hint_m``
    (the tracker's prediction) picks the leader's depth cluster when several share the box.
    """
    w_px, h_px = det.size_px
    x0, y0, x1, y1 = det.box_xyxy_px
    truncated = x0 <= 0.5 or y0 <= 0.5 or x1 >= intr.width_px - 1.5 or y1 >= intr.height_px - 1.5
    size_px = max(w_px, h_px)
    jitter = cfg.box_jitter_px + cfg.box_jitter_frac * size_px
    if truncated:  # the visible part's centre can be off by up to half the missing part
        jitter = max(jitter, 0.25 * size_px)
    u, v = det.center_px
    a = (u - intr.cx_px) / intr.fx_px
    b = (v - intr.cy_px) / intr.fy_px

    bounds = box_bounds(det.box_xyxy_px, intr.width_px, intr.height_px)
    # A quad's visible surface spans about its motor-to-motor span in depth at the worst yaw.
    cluster = robust_depth(
        depth_m,
        bounds,
        focal_px=intr.fx_px,
        body_depth_m=leader.span_m,
        cfg=cfg,
        z_hint_m=z_hint_m,
        z_hint_std_m=z_hint_std_m,
    )
    if cluster is not None and cfg.size_suspect_ratio > 0.0:
        z_size = intr.fx_px * leader.span_m / max(size_px, 1.0)
        if cluster.z_m > cfg.size_suspect_ratio * z_size:
            cluster = size_consistent_cluster(
                depth_m,
                bounds,
                focal_px=intr.fx_px,
                span_m=leader.span_m,
                cfg=cfg,
                z_size_m=z_size,
                first=cluster,
            )
    if cluster is not None:
        cos_ray = 1.0 / math.sqrt(1.0 + a * a + b * b)
        # The centre is surface_to_centre_m further along the ray than the visible surface.
        z = cluster.z_m + leader.surface_to_centre_m * cos_ray
        # A truncated sample has fewer effective pixels for the same count.
        n_eff = min(cluster.n_px, cfg.independent_depth_px) * cluster.kept_fraction
        var_z = depth_sigma_m(z, intr.fx_px, cfg) ** 2 / n_eff + cfg.surface_model_std_m**2
        source, surface_m, n_px = "depth", cluster.z_m, cluster.n_px
    elif size_prior is not None and not truncated:
        z_pred = z_hint_m if z_hint_m is not None and z_hint_m > 0.0 else None
        ranged = range_from_size(w_px, h_px, intr.fx_px, size_prior, z_pred)
        if ranged is None:
            return None
        z, rel_var = ranged
        near_m = cfg.size_fallback_min_frac * cfg.depth_max_m
        expect_depth = z < near_m if z_hint_m is None else z_hint_m + 2.0 * z_hint_std_m < near_m
        if expect_depth:
            return None
        # The error is relative to range; scale it by the predicted range when there is one, never by
        # this noisy range (short readings would weigh more and drag the track in).
        z_ref = z if z_hint_m is None else z_hint_m
        var_z = z_ref * z_ref * rel_var
        if z_hint_m is not None:
            # Box-size errors beyond 3 sigma (a box cut by an occluder, a merged box): limited, not
            # dropped, so the track still hears of them but cannot be dragged far by one frame.
            lim = _SIZE_CLAMP_SIGMAS * math.sqrt(var_z + z_hint_std_m * z_hint_std_m)
            z = max(z_hint_m - lim, min(z_hint_m + lim, z))
        source, surface_m, n_px = "size", math.nan, 0
    else:
        return None
    p_cam = np.array([a * z, b * z, z], dtype=np.float64)
    if leader.box_centre_below_m != 0.0:
        p_cam = p_cam - leader.box_centre_below_m * (_CAM_DOWN if down_cam is None else down_cam)
    # p = (a z, b z, z) with a = (u - cx) / fx, b = (v - cy) / fy: Jacobian wrt (u, v, z).
    J = np.array([[z / intr.fx_px, 0.0, a], [0.0, z / intr.fy_px, b], [0.0, 0.0, 1.0]])
    cov = (J * np.array([jitter * jitter, jitter * jitter, var_z])) @ J.T
    az, el = bearing(p_cam)
    return LeaderMeasurement(
        stamp_s=stamp_s,
        p_cam_leader_m=p_cam,
        cov_cam_m2=0.5 * (cov + cov.T),
        depth_surface_m=surface_m,
        n_depth_px=n_px,
        size_ratio=size_px * z / (intr.fx_px * leader.span_m),
        azimuth_rad=az,
        elevation_rad=el,
        score=det.score,
        box_xyxy_px=det.box_xyxy_px,
        truncated=truncated,
        range_source=source,
        width_m=w_px * z / intr.fx_px,
        height_m=h_px * z / intr.fy_px,
        box_scale=det.scale,
    )


def measure_all(
    depth_m: DepthImage,
    intr: Intrinsics,
    detections: list[Detection],
    stamp_s: float,
    *,
    leader: LeaderConfig,
    cfg: PoseConfig,
    size_prior: SizePrior | SizeCalibrator | None = None,
    down_cam: Vec3 | None = None,
    z_hint_m: float | None = None,
    z_hint_std_m: float = math.inf,
) -> list[LeaderMeasurement]:
    """:func:`measure_leader` for every detection of a frame; boxes without a usable range are dropped.

    ``size_prior``: one prior for every box, or the calibrator, asked for each box's own scale.
    """
    out = []
    for det in detections:
        prior = size_prior.prior(det.scale) if isinstance(size_prior, SizeCalibrator) else size_prior
        m = measure_leader(
            depth_m,
            intr,
            det,
            stamp_s,
            leader=leader,
            cfg=cfg,
            size_prior=prior,
            down_cam=down_cam,
            z_hint_m=z_hint_m,
            z_hint_std_m=z_hint_std_m,
        )
        if m is not None:
            out.append(m)
    return out
