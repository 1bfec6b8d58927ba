"""Pure pieces of the service machinery: mailbox, backoff, supervise, health board, latency, outbox."""

from __future__ import annotations

import asyncio
import random

import pytest
from hypothesis import given
from hypothesis import strategies as st

from companion.estimation.leader import LeaderEstimate, TrackStatus
from companion.kernel import compat
from companion.kernel.clock import ManualClock
from companion.kernel.flight import VehicleState
from companion.mission.types import MissionInputs, MissionState, StepOutput
from companion.service.health import HealthBoard
from companion.service.latency import LatencyStats, TickAges
from companion.service.mailbox import Latest, MailboxClosedError
from companion.service.supervise import Backoff, supervise
from companion.telemetry.outbox import Outbox, Outgoing


async def test_latest_drops_stale_values_and_counts_them() -> None:
    box: Latest[int] = Latest()
    for i in range(5):
        box.put(i)
    assert await box.take() == 4
    assert box.dropped == 4
    box.put(5)
    assert await box.take() == 5
    assert box.dropped == 4


async def test_latest_take_waits_and_close_wakes() -> None:
    box: Latest[str] = Latest()

    async def later() -> None:
        await asyncio.sleep(0.01)
        box.put("frame")
        await asyncio.sleep(0.01)
        box.close()

    async with compat.TaskGroup() as tg:
        tg.create_task(later())
        assert await box.take() == "frame"
        with pytest.raises(MailboxClosedError):
            await box.take()


async def test_latest_observers_see_newer_values() -> None:
    box: Latest[int] = Latest()
    box.put(1)
    seq, v = await box.wait_newer(0)
    assert (seq, v) == (1, 1)
    with pytest.raises(TimeoutError):
        async with compat.timeout(0.02):
            await box.wait_newer(seq)
    assert box.peek() == 1


@given(st.integers(0, 40), st.floats(0.01, 5), st.floats(1, 100))
def test_backoff_stays_within_bounds_and_grows(attempts: int, initial_s: float, max_s: float) -> None:
    max_s = max(max_s, initial_s)
    b = Backoff(initial_s, max_s, random.Random(attempts))
    for n in range(attempts):
        cap = min(max_s, initial_s * 2**n)
        d = b.next_delay_s()
        assert cap / 2 <= d <= cap
    b.reset()
    assert b.next_delay_s() <= initial_s


async def test_supervise_restarts_with_backoff_and_reports() -> None:
    clock = ManualClock()
    health = HealthBoard(clock)
    health.register("mqtt", critical=False)
    delays: list[float] = []
    runs = 0

    async def flaky() -> None:
        nonlocal runs
        runs += 1
        if runs < 4:
            raise ConnectionError(f"broker gone {runs}")

    async def fake_sleep(d: float) -> None:
        delays.append(d)

    await supervise("mqtt", flaky, health, clock, Backoff(1.0, 8.0, random.Random(0)), sleep=fake_sleep)
    assert runs == 4
    assert len(delays) == 3
    assert 0.5 <= delays[0] <= 1.0
    assert 1.0 <= delays[1] <= 2.0
    assert 2.0 <= delays[2] <= 4.0
    c = health.component("mqtt")
    assert c.failures == 3
    assert c.restarts == 3
    assert "broker gone 3" in c.detail


async def test_supervise_never_swallows_cancellation() -> None:
    clock = ManualClock()
    health = HealthBoard(clock)
    health.register("x", critical=False)

    async def forever() -> None:
        await asyncio.sleep(3600)

    task = asyncio.create_task(supervise("x", forever, health, clock, Backoff(1, 2, random.Random())))
    await asyncio.sleep(0)
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await task
    assert health.component("x").failures == 0


def test_health_board_staleness() -> None:
    clock = ManualClock()
    hb = HealthBoard(clock)
    hb.register("mission", critical=True, stale_after_s=2.0)
    hb.register("mqtt", critical=False)
    assert not hb.critical_alive()
    hb.beat("mission", detail="FOLLOW")
    hb.beat("mqtt", ok=False, detail="disconnected")
    assert hb.critical_alive()
    assert not hb.all_ok()
    clock.advance(2.5)
    m = hb.component("mission")
    assert not m.alive
    assert not m.ok
    assert "no beat for 2.5 s" in m.detail
    assert not hb.critical_alive()
    with pytest.raises(KeyError, match="not registered"):
        hb.beat("nope")


def test_latency_percentiles_over_window() -> None:
    lat = LatencyStats(window=100)
    for i in range(1000):
        lat.record("detect", float(i % 100))
    s = lat.summary()["detect"]
    assert s["count"] == 1000
    assert s["p50_ms"] == pytest.approx(49.5)
    assert s["p95_ms"] == pytest.approx(94.05)
    assert s["p99_ms"] == pytest.approx(98.01)
    assert s["max_ms"] == 99.0


def test_tick_ages_record_what_the_tick_flies_on() -> None:
    """Attitude and leader-estimate ages per control tick; an unusable or stale input is not a latency."""
    lat = LatencyStats()
    clock = ManualClock(100.0)
    ages = TickAges(lat, clock)

    def est(stamp_s: float, status: TrackStatus) -> LeaderEstimate:
        return LeaderEstimate(stamp_s, status, (5.0, 0.0, 0.0), (0.0, 0.0, 0.0), stamp_s)

    out = StepOutput(MissionState.FOLLOW)
    for leader in (
        est(99.92, TrackStatus.CONFIRMED),
        est(99.9, TrackStatus.LOST),
        est(50.0, TrackStatus.CONFIRMED),
    ):
        veh = VehicleState(attitude_stamp_s=99.99, link_rtt_s=0.006, link_rtt_stamp_s=99.5)
        ages.on_step(MissionInputs(veh, leader=leader), out)
    s = lat.summary()
    assert s["mavlink_rtt"]["count"] == 1  # one exchange, however many ticks saw it
    assert s["mavlink_rtt"]["p50_ms"] == pytest.approx(6.0)
    assert s["telemetry_age"]["count"] == 3
    assert s["telemetry_age"]["p50_ms"] == pytest.approx(10.0)
    assert s["camera_age"]["count"] == 1
    assert s["camera_age"]["p50_ms"] == pytest.approx(80.0)


def test_outbox_drops_oldest_and_ack_is_safe() -> None:
    box = Outbox(2)
    items = [Outgoing("t", bytes([i]), 1, False) for i in range(3)]
    box.push(items[0])
    head = box.peek()
    box.push(items[1])
    box.push(items[2])  # items[0] dropped while it was being "published"
    assert box.dropped == 1
    assert len(box) == 2
    assert head is not None
    box.ack(head)  # must not remove items[1]
    assert box.peek() is items[1]


def test_stamp_mapper_keeps_relative_timing_and_follows_slips() -> None:
    from companion.service.stamps import StampMapper

    m = StampMapper(window_s=1.0)
    # sim clock = service clock - 100 s; transport delay 5 ms + jitter up to 20 ms
    jitter = [0.0, 0.02, 0.01, 0.0, 0.015]
    mapped = [m.map(t, t + 100.0 + 0.005 + j) for t, j in zip([0.0, 0.1, 0.2, 0.3, 0.4], jitter, strict=True)]
    assert mapped[3] == pytest.approx(100.305)
    assert mapped[4] == pytest.approx(100.405)  # jitter removed, relative timing exact
    assert all(
        a <= 100.0 + t + 0.005 + j + 1e-9
        for a, t, j in zip(mapped, [0, 0.1, 0.2, 0.3, 0.4], jitter, strict=True)
    )
    # the simulator slips 0.5 s behind: after the window the new offset is adopted
    for i in range(30):
        t = 0.5 + 0.1 * i
        last = m.map(t, t + 100.5 + 0.005)
    assert last == pytest.approx(0.5 + 2.9 + 100.505)


def test_describe_flattens_task_group_errors() -> None:
    from companion.service.supervise import describe

    eg = compat.ExceptionGroup(
        "unhandled errors in a TaskGroup",
        [ValueError("bad frame"), compat.ExceptionGroup("x", [KeyError("k")])],
    )
    assert describe(eg) == "ValueError: bad frame; KeyError: 'k'"
