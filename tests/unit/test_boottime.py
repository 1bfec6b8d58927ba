"""The autopilot boot clock mapped onto ours (companion/vehicle/boottime.py)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.vehicle.boottime import BootClockMap


def test_samples_are_stamped_when_taken_through_a_latency_burst() -> None:
    m = BootClockMap()
    # The autopilot booted 100 s before our clock's zero; 5 ms of latency, then a 40 ms burst.
    for k in range(100):
        boot_ms = 100_000 + 20 * k
        arrival = k * 0.02 + (0.040 if 50 <= k < 70 else 0.005)
        stamp = m.stamp(boot_ms, arrival)
        assert stamp <= arrival
        assert stamp == pytest.approx(k * 0.02 + 0.005, abs=1e-3)


def test_follows_a_reboot_and_a_sender_without_boot_time() -> None:
    m = BootClockMap()
    m.stamp(500_000, 10.0)
    assert m.stamp(2_000, 11.0) == pytest.approx(11.0)  # rebooted: its clock restarted
    assert m.stamp(2_100, 11.12) == pytest.approx(11.1, abs=1e-3)
    assert m.stamp(0, 12.0) == 12.0


def test_timesync_takes_the_links_own_latency_out_of_every_stamp() -> None:
    """12 ms each way plus a spread: the fastest delivery alone leaves stamps 12 ms late, TIMESYNC not."""
    rng = np.random.default_rng(3)
    boot0_s = 100.0  # the autopilot's boot time at our clock's zero

    def delay_s() -> float:
        return 0.012 + abs(float(rng.normal(0.0, 0.010)))

    plain, synced = BootClockMap(), BootClockMap()
    errors_plain, errors_synced = [], []
    for k in range(500):
        t = k * 0.02  # when the autopilot sampled, on our clock
        if k % 25 == 0:  # a TIMESYNC exchange every 0.5 s
            sent = t
            answered_boot = sent + delay_s() + boot0_s
            assert synced.sync(answered_boot, sent, answered_boot - boot0_s + delay_s())
        arrival = t + delay_s()
        boot_ms = round((t + boot0_s) * 1000.0)
        errors_plain.append(plain.stamp(boot_ms, arrival) - t)
        errors_synced.append(synced.stamp(boot_ms, arrival) - t)
    assert synced.synced
    assert not plain.synced
    assert np.median(errors_plain[100:]) == pytest.approx(0.012, abs=0.002)
    assert abs(np.median(errors_synced[100:])) < 0.003
    assert synced.one_way_s == pytest.approx(0.012, abs=0.003)


def test_timesync_ignores_what_cannot_be_a_measure_and_restarts_on_reboot() -> None:
    m = BootClockMap()
    assert not m.sync(50.0, 10.0, 9.0)  # back before it left
    assert not m.sync(50.0, 10.0, 12.0)  # a round trip of 2 s: held up, or not ours
    assert not m.sync(0.0, 10.0, 10.01)
    assert math.isnan(m.one_way_s)
    assert m.sync(50.0, 10.0, 10.02)
    assert m.stamp(50_100, 10.2) == pytest.approx(10.11)  # boot 50.1 s on our clock: 10.01 + 0.1
    m.stamp(1_000, 11.0)  # rebooted: the old exchanges say nothing about the new clock
    assert not m.synced
