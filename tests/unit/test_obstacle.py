"""The depth guard's search (pure): what counts as an obstacle ahead, and what is the tracked leader."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import Config
from companion.estimation.pipeline import PerceptionPipeline
from companion.kernel.camera import Intrinsics, RgbdFrame
from companion.mission.safety import SafetyLimits
from companion.perception.obstacle import guard_range_m, nearest_ahead

K = Intrinsics.from_hfov(640, 480, 69.0)
ARGS = {"max_range_m": 4.0, "window_frac": (0.6, 0.3), "min_px": 8}


def depth_with(*patches: tuple[int, int, int, int, float], background_m: float = 0.0) -> np.ndarray:
    """A depth image (m) with rectangles ``(x0, y0, x1, y1, depth)``; the rest ``background_m``."""
    d = np.full((480, 640), background_m, dtype=np.float32)
    for x0, y0, x1, y1, z in patches:
        d[y0:y1, x0:x1] = z
    return d


def test_nothing_near_gives_none() -> None:
    assert nearest_ahead(depth_with(background_m=0.0), K, **ARGS) is None  # no depth at all
    assert nearest_ahead(depth_with(background_m=9.0), K, **ARGS) is None  # all beyond the range


def test_an_object_ahead_right_is_found_at_its_range_and_bearing() -> None:
    p = nearest_ahead(depth_with((360, 220, 420, 260, 2.5), background_m=8.0), K, **ARGS)
    assert p is not None
    assert p[2] == pytest.approx(2.5)
    # Somewhere on the patch (the nearest samples of a flat patch are any of its pixels): right of the axis.
    assert (360 - K.cx_px) / K.fx_px * 2.5 <= p[0] <= (420 - K.cx_px) / K.fx_px * 2.5


def test_a_few_stray_pixels_are_not_an_object() -> None:
    assert nearest_ahead(depth_with((320, 240, 324, 244, 1.0), background_m=8.0), K, **ARGS) is None


def test_the_ground_below_the_window_is_not_an_object() -> None:
    assert nearest_ahead(depth_with((0, 400, 640, 480, 2.0), background_m=8.0), K, **ARGS) is None


def test_the_tracked_leader_is_left_out_but_something_nearer_in_its_box_is_not() -> None:
    box = (300.0, 220.0, 340.0, 260.0)
    leader = depth_with((305, 225, 335, 255, 3.0), background_m=8.0)
    assert nearest_ahead(leader, K, exclude_xyxy=box, exclude_range_m=(2.5, 3.5), **ARGS) is None
    # The track is on a phantom at 3 m, and the real leader shows up in the same direction at 1.5 m.
    real = depth_with((305, 225, 335, 255, 1.5), background_m=8.0)
    p = nearest_ahead(real, K, exclude_xyxy=box, exclude_range_m=(2.5, 3.5), **ARGS)
    assert p is not None
    assert p[2] == pytest.approx(1.5)


def test_the_guard_looks_out_to_the_stopping_distance_within_its_bounds() -> None:
    kw = {"min_range_m": 4.0, "max_range_m": 9.0, "separation_m": 2.0, "response_s": 1.0, "brake_m_s2": 1.5}
    assert guard_range_m(0.0, **kw) == 4.0  # hovering, or backing away
    assert guard_range_m(-3.0, **kw) == 4.0
    assert guard_range_m(2.0, **kw) == pytest.approx(2.0 + 2.0 + 4.0 / 3.0)  # 5.33 m
    assert guard_range_m(3.6, **kw) == 9.0  # 9.9 m wanted: the bound


def _pole_seen(v_ned_m_s: tuple[float, float, float] | None) -> bool:
    """A pole 7 m dead ahead of a level follower facing north, flying at ``v_ned_m_s``."""
    cfg = Config()
    brake_m_s2 = SafetyLimits.from_config(cfg.safety, cfg.formation.max_accel_m_s2).brake_m_s2
    pipeline = PerceptionPipeline.from_config(cfg, guard_brake_m_s2=brake_m_s2)
    pipeline.attitude.push(0.0, (1.0, 0.0, 0.0, 0.0))
    pipeline.attitude.push(1.0, (1.0, 0.0, 0.0, 0.0))
    if v_ned_m_s is not None:
        pipeline.velocity.push(0.0, v_ned_m_s)
        pipeline.velocity.push(1.0, v_ned_m_s)
    seen = False
    for stamp_s in (0.5, 0.567):  # two frames: the guard acts on what two frames in a row see
        frame = RgbdFrame(
            np.zeros((480, 640, 3), np.uint8), depth_with((300, 140, 340, 340, 7.0)), K, stamp_s=stamp_s
        )
        seen = pipeline.obstacle(frame, pipeline.track(stamp_s, [])) is not None
    return seen


def test_flying_fast_at_a_pole_the_guard_sees_it_beyond_its_resting_range() -> None:
    assert not _pole_seen(None)  # no velocity known: the 4 m range
    assert not _pole_seen((0.5, 0.0, 0.0))
    assert _pole_seen((3.6, 0.0, 0.0))  # 7 m is inside the 9 m it now looks out to
    assert not _pole_seen((0.0, 3.6, 0.0))  # flying sideways: not toward it


def test_one_frames_obstacle_waits_for_a_second_unless_it_is_within_the_separation() -> None:
    """One frame's depth 2 m short where the leader is read as an obstacle 3 m ahead: not acted on alone."""
    cfg = Config()
    pipeline = PerceptionPipeline.from_config(cfg, guard_brake_m_s2=None)
    pipeline.attitude.push(0.0, (1.0, 0.0, 0.0, 0.0))
    pipeline.attitude.push(2.0, (1.0, 0.0, 0.0, 0.0))

    def frame(stamp_s: float, depth_m: float) -> bool:
        f = RgbdFrame(
            np.zeros((480, 640, 3), np.uint8), depth_with((300, 140, 340, 340, depth_m)), K, stamp_s=stamp_s
        )
        return pipeline.obstacle(f, pipeline.track(stamp_s, [])) is not None

    assert not frame(0.5, 3.0)  # alone
    assert not frame(1.5, 3.0)  # a second later: not the same sighting, alone again
    assert frame(1.567, 3.0)  # the next frame sees it there too
    assert frame(1.8, 1.5)  # within min_separation_m (2 m): at once
