"""The own velocity the tracker takes: PX4's while GPS aids it, not PX4's dead reckoning after a loss.

Through ``FlightService.feed_telemetry`` and the mission's debounced GPS verdict (the runner's ticks), on a
scripted autopilot; :class:`~companion.estimation.own_velocity.OwnVelocity` on its own for the drag model.
"""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import Config, MissionConfig
from companion.estimation.own_velocity import OwnVelocity
from companion.kernel.clock import ManualClock
from companion.kernel.frames import R_from_euler
from companion.service.flight import FlightService

from .mission_harness import FakeAutopilot
from .test_mission_runner import RecordingLink

TICK_S = 0.05


async def _fly(flight: FlightService, clock: ManualClock, seconds: float) -> None:
    for _ in range(round(seconds / TICK_S)):
        clock.set(clock.now_s() + TICK_S)
        await flight.runner.tick()
        flight.feed_telemetry()


async def test_after_a_gps_loss_the_track_does_not_take_px4s_dead_reckoning() -> None:
    clock = ManualClock(100.0)
    ap = FakeAutopilot()
    ap.fly()
    ap.v_ned_m_s = (2.0, 0.0, 0.0)
    cfg = Config(mission=MissionConfig(gps_restore_s=0.0, gps_loss_confirm_s=0.5))
    flight = FlightService(cfg, RecordingLink(ap, clock), clock)  # type: ignore[arg-type]
    await _fly(flight, clock, 1.0)
    assert flight.machine.gps_ok
    v = flight.pipeline.velocity.v_at(clock.now_s())
    assert v is not None
    assert v == pytest.approx((2.0, 0.0, 0.0))
    # GPS lost: until the loss is confirmed the track still takes PX4's velocity.
    ap.gps_fix = 0
    await _fly(flight, clock, 0.3)
    assert flight.machine.gps_ok
    await _fly(flight, clock, 0.5)
    assert not flight.machine.gps_ok
    # Then PX4 dead-reckons and its horizontal velocity runs off; its vertical stays (the barometer aids it).
    ap.v_ned_m_s = (5.0, 3.0, -0.5)
    await _fly(flight, clock, 0.5)
    v = flight.pipeline.velocity.v_at(clock.now_s())
    assert v is not None
    # No drag model from a steady hover: the horizontal held at the last aided one, the vertical PX4's.
    assert flight.own_velocity.ego.model() is None
    assert v == pytest.approx((2.0, 0.0, -0.5))


def test_without_gps_the_velocity_is_the_drag_models() -> None:
    own = OwnVelocity()
    rng = np.random.default_rng(1)
    level = R_from_euler(0.0, 0.0, 0.0)
    # While aided: PX4's velocity passes through, and each sample with an attitude teaches the model.
    v = np.zeros(3)
    for k in range(400):
        t_s = k * 0.05
        pitch = 0.1 * np.sin(0.7 * t_s) + 0.01 * rng.standard_normal()
        R = R_from_euler(0.0, pitch, 0.0)
        v = v + 0.05 * (-9.81 * R[0, 2] / R[2, 2] * np.array([1.0, 0.0, 0.0]) - 0.4 * v)
        sample = own.update(t_s, (float(v[0]), float(v[1]), 0.0), R, aided=True)
        assert sample.learnt
        assert sample.v_ned_m_s == (float(v[0]), float(v[1]), 0.0)
    model = own.ego.model()
    assert model is not None
    assert model.drag_per_s == pytest.approx(0.4, abs=0.05)
    # Lost: PX4's horizontal velocity is not taken; the model's is, from the last aided one on.
    lost = own.update(20.0, (9.0, 9.0, -0.3), level, aided=False)
    assert not lost.learnt
    assert lost.v_ned_m_s is not None
    assert abs(float(lost.v_ned_m_s[0]) - float(v[0])) < 0.1
    assert float(lost.v_ned_m_s[2]) == pytest.approx(-0.3)
    # No attitude, nothing for the track.
    assert own.update(20.05, (9.0, 9.0, -0.3), None, aided=False).v_ned_m_s is None
