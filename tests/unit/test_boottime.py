"""The autopilot boot clock mapped onto ours (companion/vehicle/boottime.py)."""

from __future__ import annotations

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
