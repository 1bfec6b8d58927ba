"""The tilt probe's measurement on synthetic depth: a tilted bar and a slanted plate."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.lab.tilt_probe import silhouette_tilt

FY_PX = 400.0


def bar_depth(
    angle_deg: float, *, range_m: float = 5.0, slope: float = 0.0
) -> tuple[np.ndarray, tuple[float, float, float, float]]:
    """A 60 x 8 px bar turned by ``angle_deg`` at ``range_m`` on a far background, its depth growing by
    ``slope`` metres per metre of height below its centre; and its box (the detector's, tight)."""
    v, u = np.mgrid[0:100, 0:100].astype(np.float64)
    a = math.radians(angle_deg)
    du, dv = u - 50.0, v - 50.0
    along = du * math.cos(a) + dv * math.sin(a)
    across = -du * math.sin(a) + dv * math.cos(a)
    depth = np.full((100, 100), 30.0)
    on = (np.abs(along) <= 30.0) & (np.abs(across) <= 4.0)
    depth[on] = range_m + slope * dv[on] * range_m / FY_PX
    rows, cols = np.nonzero(on)
    return depth, (float(cols.min()), float(rows.min()), float(cols.max() + 1), float(rows.max() + 1))


@pytest.mark.parametrize("angle_deg", [-10.0, -3.0, 0.0, 4.0, 10.0])
def test_the_axis_angle_is_the_bars(angle_deg: float) -> None:
    m = silhouette_tilt(*bar_depth(angle_deg), FY_PX)
    assert m is not None
    assert m[0] == pytest.approx(angle_deg, abs=0.5)


@pytest.mark.parametrize("slope", [-0.3, 0.0, 0.2])
def test_the_depth_slope_is_the_plates(slope: float) -> None:
    m = silhouette_tilt(*bar_depth(90.0, slope=slope), FY_PX)
    assert m is not None
    assert m[1] == pytest.approx(math.degrees(math.atan(slope)), abs=0.5)


def test_too_few_leader_pixels_is_no_measurement() -> None:
    depth = np.full((100, 100), np.nan)
    depth[50, 40:60] = 5.0
    assert silhouette_tilt(depth, (0.0, 0.0, 100.0, 100.0), FY_PX) is None
