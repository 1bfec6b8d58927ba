"""The leader's depth inside a detection box, from the aligned stereo depth image; pure.

Among the valid depth pixels inside the box, :func:`robust_depth` finds the nearest dense cluster (the
leader; background is behind it), or the one the tracker's predicted depth picks when something nearer
covers part of the box, then takes a trimmed mean in *disparity* (``f * baseline / z``), where stereo noise
is Gaussian with a constant sigma, so the mean is unbiased. Near ``depth_max_m`` the far half of the noise
falls out of range; that truncation is undone (truncated-normal mean). :func:`size_consistent_cluster`
searches again where the box size puts the leader when the first cluster is far behind it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.config import PoseConfig
from companion.kernel.camera import DepthImage

#: Trim window half-width in stereo-noise sigmas around the cluster centre.
_TRIM_SIGMAS = 2.5
#: A depth window is a candidate for the leader once it holds this fraction of the box's valid pixels.
_CLUSTER_FRACTION = 0.1
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


def size_consistent_cluster(
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
