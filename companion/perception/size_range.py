"""Range from the box size, beyond the stereo range or in a depth hole; pure apart from the calibrator.

:func:`range_from_size` ranges mostly from the box's height (its width changes with the leader's yaw),
with the leader's apparent size and the box's per-frame noise learnt online from depth just inside the
stereo range (:class:`SizeCalibrator`). About 10-25 % per frame, white: weighted at the predicted range and
linearised there (the box side is linear in 1/z), so that the tracker averages it without a bias.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from companion.perception.pose import LeaderMeasurement

#: Smallest box side used for ranging from size, px (a pixel of box error is then under 15 %).
_MIN_SIZE_RANGE_PX = 7.0


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
