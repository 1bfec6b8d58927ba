"""How busy the host was while a real-path run flew, and whether it starved the run.

A real-path run (the simulator or PX4 SITL, the service and its detector on one machine) keeps its rates only
while the host has cores to spare: PX4 runs in real time, the service's control loop at 20 Hz. Other work on
the machine shows up as late control ticks, old telemetry and a slower camera, and the formation pays for
it (a loaded two-core host turned a 0.35 m run into 1.9 m). :class:`HostLoad` reads ``/proc/stat`` around a
run; :func:`starved` says whether the run's own figures show it was held back.
"""

from __future__ import annotations

import contextlib
import os
import time
from collections.abc import Callable, Mapping
from typing import Any

#: Other processes took more than this share of the machine's cores: the run was not alone.
OTHERS_MAX_FRAC = 0.15
#: The control loop ticks every 50 ms; its interval's p99 past this means the service did not get a core
#: often enough, ms (one gap of ~0.5 s is the service's own: it waits for PX4 to take offboard mode).
TICK_P99_MAX_MS = 100.0
#: The attitude's age at the control tick, p95, past this, ms (20-30 ms on an idle host).
TELEMETRY_AGE_P95_MAX_MS = 60.0


def _cpu_jiffies() -> tuple[float, float] | None:
    """(busy, total) CPU time of the whole machine so far, s; None where /proc/stat is not readable."""
    try:
        with open("/proc/stat", encoding="ascii") as f:
            fields = f.readline().split()
    except OSError:
        return None
    if not fields or fields[0] != "cpu":
        return None
    values = [float(x) for x in fields[1:]]
    idle = values[3] + (values[4] if len(values) > 4 else 0.0)  # idle + iowait
    hz = float(os.sysconf("SC_CLK_TCK"))
    return (sum(values) - idle) / hz, sum(values) / hz


class HostLoad:
    """The machine's CPU use between :meth:`start` and :meth:`stop` (``/proc/stat``; nothing elsewhere).

    ``read_cpu`` and ``clock`` are the machine's by default: (busy, total) CPU seconds so far, and a
    monotonic clock, s.
    """

    def __init__(
        self,
        read_cpu: Callable[[], tuple[float, float] | None] = _cpu_jiffies,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self._read_cpu, self._clock = read_cpu, clock
        self._t0 = 0.0
        self._cpu0: tuple[float, float] | None = None

    def start(self) -> None:
        self._t0 = self._clock()
        self._cpu0 = self._read_cpu()

    def stop(self, own_cpu_s: float) -> dict[str, Any]:
        """The machine's figures since :meth:`start`; ``own_cpu_s``: what the run itself used, CPU s."""
        wall_s = self._clock() - self._t0
        cores = os.cpu_count() or 1
        out: dict[str, Any] = {"cores": cores, "wall_s": round(wall_s, 1), "own_cpu_s": round(own_cpu_s, 1)}
        cpu1 = self._read_cpu()
        if self._cpu0 is not None and cpu1 is not None and wall_s > 0.0:
            busy_s = cpu1[0] - self._cpu0[0]
            capacity_s = wall_s * cores
            out["machine_busy_frac"] = round(min(busy_s / capacity_s, 1.0), 3)
            out["others_cpu_frac"] = round(min(max(busy_s - own_cpu_s, 0.0) / capacity_s, 1.0), 3)
        with contextlib.suppress(OSError):
            out["loadavg_1m"] = round(os.getloadavg()[0], 2)
        return out


def starved(host: Mapping[str, Any], report: Mapping[str, Any]) -> list[str]:
    """Why the host held this run back (empty: it did not), from the host's load and the run's own timing."""
    why = []
    others = host.get("others_cpu_frac")
    if others is not None and others > OTHERS_MAX_FRAC:
        why.append(f"other work took {others:.0%} of the machine")
    ticks = ((report.get("deviation_split") or {}).get("run") or {}).get("ticks") or {}
    gap = ticks.get("interval_p99_ms")
    if gap is not None and gap > TICK_P99_MAX_MS:
        why.append(f"control ticks came up to {gap:.0f} ms apart (p99)")
    age = ((report.get("control_tick_ages_ms") or {}).get("telemetry_age_ms") or {}).get("p95")
    if age is not None and age > TELEMETRY_AGE_P95_MAX_MS:
        why.append(f"the attitude was {age:.0f} ms old at the tick (p95)")
    return why
