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
image (the box is a view; only its valid pixels are gathered).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config import LeaderConfig, PoseConfig
from companion.kernel.camera import DepthImage, Intrinsics
from companion.kernel.frames import Mat3, Vec3
from companion.perception.types import Detection

#: Trim window half-width in stereo-noise sigmas around the cluster centre.
_TRIM_SIGMAS = 2.5
#: A depth window is a candidate for the leader once it holds this fraction of the box's valid pixels.
_CLUSTER_FRACTION = 0.1
_CAM_DOWN = np.array([0.0, 1.0, 0.0])
#: Smallest box side used for ranging from size, px (a pixel of box error is then under 15 %).
_MIN_SIZE_RANGE_PX = 7.0
#: Size-ranged readings are limited to this many sigmas from the predicted range.
_SIZE_CLAMP_SIGMAS = 3.0
#: Depth clusters considered inside one box (leader, occluders in front, background behind).
_MAX_CLUSTERS = 3
#: A cluster fits the tracker's predicted depth within this many combined standard deviations.
_HINT_SIGMAS = 3.0
#: A cluster with less than this modelled fraction inside the valid range is too truncated to trust.
_MIN_KEPT_FRACTION = 0.3
#: Above this many valid pixels, the cluster search runs on an even subsample (the mean uses all).
_SEARCH_SAMPLES = 2048
#: The second search, where the box size puts the leader (``PoseConfig.size_suspect_ratio``): a sparser
#: cluster counts, centred on the size range times the usual box-to-leader ratio, within this fraction.
_SIZE_SEARCH_FRACTION = 0.02
_SIZE_SEARCH_RATIO = 1.25
_SIZE_SEARCH_REL_STD = 0.3


@dataclass(frozen=True, slots=True)
class DepthCluster:
    """The leader's depth inside a box: trimmed mean of its near cluster (camera z, m)."""

    z_m: float
    #: Pixels in the trimmed window, and all valid pixels inside the box.
    n_px: int
    n_valid_px: int
    #: Standard deviation of the pixels in the window, m (noise plus the leader's own depth extent).
    spread_m: float
    #: Modelled fraction of the leader's depth distribution inside the window and the valid range
    #: (below 1 near ``depth_max_m``, where the far half of the noise is cut off and was corrected for).
    kept_fraction: float = 1.0


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
    z_hint_m: float | None = None,
    z_hint_std_m: float = math.inf,
    min_fraction: float = _CLUSTER_FRACTION,
) -> DepthCluster | None:
    """Depth of the leader's cluster of valid pixels inside ``bounds``, or None.

    The leader is the nearest dense cluster: background between the arms is farther, isolated near
    pixels are too few to form a dense window, and the stereo noise sets how wide a window the leader
    occupies at its range. When something nearer covers part of the box (a branch, another aircraft),
    the tracker's predicted depth ``z_hint_m`` (with its standard deviation) picks the cluster instead.

    Args:
        depth_m: H x W depth along the optical axis, m, 0 = invalid (not copied).
        bounds: (x0, y0, x1, y1) from :func:`box_bounds`.
        focal_px: focal length for the noise model, px.
        body_depth_m: the leader's own extent along the view, m.
        cfg: valid range, noise model and minimum pixel count.
        z_hint_m: predicted depth of the leader's centre, m (None: no track to predict from).
        z_hint_std_m: its standard deviation, m.
        min_fraction: share of the box's valid pixels a cluster needs.
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
    need = max(float(cfg.min_valid_px) / step, min_fraction * s.size)
    dense = counts >= need
    if not dense.any():
        return None
    centres: list[float] = []
    start = 0
    while len(centres) < _MAX_CLUSTERS and start < s.size:
        hits = np.flatnonzero(dense[start:])
        if hits.size == 0:
            break
        i = start + int(hits[0])
        i += int(np.argmax(counts[i : i + int(counts[i])]))
        centres.append(float(s[i + (int(counts[i]) - 1) // 2]))
        start = i + int(counts[i])  # the next candidate lies beyond this cluster's window
    centre_m = centres[0]
    if z_hint_m is not None and len(centres) > 1:
        # Nearest cluster that fits the prediction; the nearest overall when none does.
        for c in centres:
            tol = math.hypot(z_hint_std_m, k_noise * c * c, 0.5 * body_depth_m)
            if abs(c - z_hint_m) <= _HINT_SIGMAS * tol:
                centre_m = c
                break
    # Refine in disparity (fB / z), where stereo noise is Gaussian with a constant sigma: the trimmed
    # mean there is unbiased, and the range limit is a plain lower truncation that can be undone.
    fb = focal_px * cfg.stereo_baseline_m
    sigma_d = cfg.stereo_subpixel_px
    d_min = fb / cfg.depth_max_m  # farther pixels were dropped: the window is cut below this
    disp = fb / valid.astype(np.float64)
    d_c = fb / centre_m
    sel = disp
    for _ in range(2):  # recentre twice: the first window starts on the cluster's near tail
        extent_d = fb * 0.5 * body_depth_m / (fb / d_c) ** 2
        half = extent_d + _TRIM_SIGMAS * sigma_d
        sel = disp[np.abs(disp - d_c) <= half]
        if sel.size == 0:
            return None
        d_c = float(sel.mean())
    if sel.size < cfg.min_valid_px:
        return None
    # The leader's own depth extent adds to the spread (uniform over +-extent: std extent / sqrt 3).
    sigma_eff = math.sqrt(sigma_d * sigma_d + (extent_d / math.sqrt(3.0)) ** 2)
    mu, kept = _untruncated_mean(d_c, sigma_eff, max(d_c - half, d_min), d_c + half)
    if kept < _MIN_KEPT_FRACTION or mu <= 0.0:
        return None
    z_sel = fb / sel
    return DepthCluster(
        z_m=fb / mu,
        n_px=int(sel.size),
        n_valid_px=n_valid,
        spread_m=float(z_sel.std()),
        kept_fraction=kept,
    )


def _phi(x: float) -> float:
    return math.exp(-0.5 * x * x) / math.sqrt(2.0 * math.pi)


def _Phi(x: float) -> float:
    return 0.5 * (1.0 + math.erf(x / math.sqrt(2.0)))


def _untruncated_mean(mean: float, sigma: float, lo: float, hi: float) -> tuple[float, float]:
    """Mean ``mu`` of N(mu, sigma^2) whose part inside [lo, hi] has mean ``mean``; and that part's mass.

    Fixed point ``mu <- mean - sigma (phi(a) - phi(b)) / (Phi(b) - Phi(a))``: it converges because the
    truncated mean moves slower than ``mu``. With a symmetric window it returns ``mean`` at once.
    """
    mu = mean
    kept = 1.0
    for _ in range(30):
        a, b = (lo - mu) / sigma, (hi - mu) / sigma
        kept = _Phi(b) - _Phi(a)
        if kept < 1e-6:
            return mu, kept
        new = mean - sigma * (_phi(a) - _phi(b)) / kept
        if abs(new - mu) < 1e-6 * sigma:
            return new, kept
        mu = new
    return mu, kept


@dataclass(frozen=True, slots=True)
class SizePrior:
    """The leader's apparent width and height (box side times depth over focal length), m.

    Ranging from a side has two errors: a per-frame one in pixels (box-edge noise and pixel
    quantisation, ``*_noise_px``: white, the tracker averages it out) and one relative to the size
    (``*_rel_std``: persistent). Height barely depends on the leader's yaw (it is level: props above,
    legs below), so its relative error is small; width changes by up to +-20 % with yaw and shrinks
    with range as thin arms and props vanish, so it counts little where height is usable.
    """

    width_m: float
    width_rel_std: float
    width_noise_px: float
    height_m: float
    height_rel_std: float
    height_noise_px: float


class _SideStats:
    """Exponential average of one apparent size (m) and of its per-frame residual (px^2)."""

    __slots__ = ("mean_m", "noise_px2", "updates")

    def __init__(self, mean_m: float, noise_px: float) -> None:
        self.mean_m = mean_m
        self.noise_px2 = noise_px * noise_px
        self.updates = 0

    def add(self, size_m: float, size_px: float, alpha: float) -> None:
        # Early on average fast (1/n), then settle to the exponential window.
        a = max(alpha, 1.0 / (self.updates + 1))
        if self.updates > 0 and size_m > 0.0:
            resid_px = (size_m - self.mean_m) * size_px / size_m  # px at this frame's scale
            w = max(alpha, 1.0 / self.updates)
            self.noise_px2 += w * (resid_px * resid_px - self.noise_px2)
        self.mean_m += a * (size_m - self.mean_m)
        self.updates += 1


class SizeCalibrator:
    """Learns the leader's apparent size from depth measurements, for ranging where depth fails.

    Beyond the stereo range (or in a depth hole) the box still gives range: ``z = f * size / px``,
    mostly from its height. The apparent size depends on the airframe, on its yaw and on range (thin
    parts vanish at low resolution: the box's width at 11 m is ~10 % under its width at 5 m), so it is
    learnt online from confirmed, untruncated depth measurements in ``[min_depth_m, max_depth_m]``,
    inside the stereo range, where depth is still ~0.5 % accurate (the service learns from half the
    stereo range out, ``pose.size_learn_min_frac``: the height, which the range mostly comes from, hardly
    changes with range but swings with the leader's tilt and yaw, so more frames give a better mean).
    The average is long (``1/alpha`` samples, ~2 s at 30 Hz): a 1 % bias in
    the height is 0.11 m at 11 m, for as long as the leader stays out there. The per-frame scatter of
    each side (px) is learnt too: it is the detector's box noise that range-from-size inherits. Until
    the band has ``min_updates`` samples, closer depth measurements stand in; before those,
    ``width_ratio`` and ``height_ratio`` times ``span_m`` with a loose uncertainty.
    """

    def __init__(
        self,
        span_m: float,
        *,
        width_ratio: float = 1.3,
        height_ratio: float = 0.65,
        prior_rel_std: float = 0.25,
        min_depth_m: float = 7.5,
        max_depth_m: float = 9.5,
        alpha: float = 0.02,
        min_updates: int = 10,
        width_rel_std: float = 1.0,
        height_rel_std: float = 0.03,
        min_noise_px: float = 0.5,
    ) -> None:
        self.span_m = span_m
        self.min_depth_m = min_depth_m
        self.max_depth_m = max_depth_m
        self.alpha = alpha
        self.min_updates = min_updates
        self.width_rel_std = width_rel_std
        self.height_rel_std = height_rel_std
        self.min_noise_px = min_noise_px
        self._prior = SizePrior(
            width_ratio * span_m, prior_rel_std, 2.0, height_ratio * span_m, prior_rel_std, 2.0
        )
        #: Per box scale (:func:`scale_key`): (width, height) learnt in the band near the cut-off, and
        #: from closer range.
        self._stats: dict[int, tuple[tuple[_SideStats, _SideStats], tuple[_SideStats, _SideStats]]] = {}

    def _sides(self) -> tuple[_SideStats, _SideStats]:
        return (_SideStats(self._prior.width_m, 2.0), _SideStats(self._prior.height_m, 2.0))

    @property
    def updates(self) -> int:
        """Depth measurements learnt from, in the band and closer, at every box scale."""
        return sum(band[0].updates + near[0].updates for band, near in self._stats.values())

    def update(self, m: LeaderMeasurement) -> None:
        """Learn from a depth measurement the tracker accepted (others are ignored)."""
        z = float(m.p_cam_leader_m[2])
        if m.range_source != "depth" or m.truncated or z > self.max_depth_m:
            return
        key = scale_key(m.box_scale)
        if key not in self._stats:
            self._stats[key] = (self._sides(), self._sides())
        band, near = self._stats[key]
        stats = band if z >= self.min_depth_m else near
        x0, y0, x1, y1 = m.box_xyxy_px
        stats[0].add(m.width_m, x1 - x0, self.alpha)
        stats[1].add(m.height_m, y1 - y0, self.alpha)

    def prior(self, scale: float = 1.0) -> SizePrior:
        """The apparent size of a box found at ``scale`` (the configured prior until enough updates there).

        A box found 1:1 is not as tight as one found magnified in the window: learnt from the window's
        boxes, the size read a 1:1 box's range as a jump (the 6-12 m band, docs/perception.md).
        """
        stats = self._stats.get(scale_key(scale))
        for w, h in () if stats is None else stats:
            if w.updates >= self.min_updates:
                return SizePrior(
                    w.mean_m,
                    self.width_rel_std,
                    max(self.min_noise_px, math.sqrt(w.noise_px2)),
                    h.mean_m,
                    self.height_rel_std,
                    max(self.min_noise_px, math.sqrt(h.noise_px2)),
                )
        return self._prior


def scale_key(scale: float) -> int:
    """Half-octave bucket of a box scale (0.5 -> -2, 1.0 -> 0, 1.5 -> 1, 2.0 -> 2)."""
    return round(2.0 * math.log2(max(scale, 1e-3)))


def range_from_size(
    w_px: float, h_px: float, focal_px: float, prior: SizePrior, z_ref_m: float | None = None
) -> tuple[float, float] | None:
    """Range (m) and its relative variance from the box size, fusing width and height.

    Each side's relative error combines its size's own spread and its per-frame noise over its length.
    With a predicted range ``z_ref_m`` the side (px, linear in 1/z, its noise symmetric) is the
    measurement, linearised there as in an extended Kalman filter: ``z = z_ref (2 - px / px_ref)``.
    ``f S / px`` itself would skew long (a 12 px side with 3 px noise averages 3-7 % long, and a cut
    on small boxes makes that depend on the noise) and weights from this box's own sides would favour
    the boxes that came out large; both would bias the track. Without a prediction: fused in log range.
    """
    z_sum = 0.0
    weight = 0.0
    for size_px, size_m, rel_std, noise_px in (
        (w_px, prior.width_m, prior.width_rel_std, prior.width_noise_px),
        (h_px, prior.height_m, prior.height_rel_std, prior.height_noise_px),
    ):
        if z_ref_m is None:
            if size_px < _MIN_SIZE_RANGE_PX:
                continue
            rel_var = rel_std * rel_std + (noise_px / size_px) ** 2
            z_sum += math.log(focal_px * size_m / size_px) / rel_var
        else:
            ref_px = focal_px * size_m / z_ref_m
            if ref_px < _MIN_SIZE_RANGE_PX:
                continue
            rel_var = rel_std * rel_std + (noise_px / ref_px) ** 2
            z_sum += z_ref_m * (2.0 - size_px / ref_px) / rel_var
        weight += 1.0 / rel_var
    if weight == 0.0:
        return None
    z = z_sum / weight
    return (math.exp(z) if z_ref_m is None else z), 1.0 / weight


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
            cluster = _size_consistent_cluster(
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


def _size_consistent_cluster(
    depth_m: DepthImage,
    bounds: tuple[int, int, int, int],
    *,
    focal_px: float,
    span_m: float,
    cfg: PoseConfig,
    z_size_m: float,
    first: DepthCluster,
) -> DepthCluster:
    """A sparser cluster nearer than ``first`` where the box size puts the leader, else ``first``.

    ``z_size_m``: the range at which a leader of span ``span_m`` fills the box (size ratio 1).
    """
    z_hint = _SIZE_SEARCH_RATIO * z_size_m
    std = _SIZE_SEARCH_REL_STD * z_hint
    found = robust_depth(
        depth_m,
        bounds,
        focal_px=focal_px,
        body_depth_m=span_m,
        cfg=cfg,
        z_hint_m=z_hint,
        z_hint_std_m=std,
        min_fraction=_SIZE_SEARCH_FRACTION,
    )
    # The search falls back to the nearest cluster when none fits the size: only a fit, in front, counts.
    if found is None or found.z_m > first.z_m - span_m or abs(found.z_m - z_hint) > _HINT_SIGMAS * std:
        return first
    return found


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
