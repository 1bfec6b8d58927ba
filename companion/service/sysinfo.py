"""Readings of the companion computer itself: load, CPU use, memory, temperatures, GPU load (Jetson).

Everything is read from ``/proc`` and ``/sys`` under a root that tests can point elsewhere. Files that do
not exist on a board (no thermal zones in a container, no GPU load outside a Jetson) give None, never
an error.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

#: Where Jetson boards expose GPU load in 1/1000 (L4T 35/36 uses the first; older ones the second).
_JETSON_GPU_LOAD = ("sys/devices/platform/gpu.0/load", "sys/devices/gpu.0/load")


@dataclass(frozen=True, slots=True)
class CpuTimes:
    """Cumulative jiffies from one ``/proc/stat`` line."""

    busy: int
    total: int


@dataclass(frozen=True, slots=True)
class SystemReading:
    """One sample of the machine's state."""

    load_1m: float | None
    #: Whole-machine CPU use since the previous sample, %, and per core.
    cpu_percent: float | None
    cpu_core_percent: tuple[float, ...]
    mem_used_mib: float | None
    mem_total_mib: float | None
    #: Thermal zone type (e.g. ``cpu-thermal``, ``GPU-therm``) -> degrees C.
    temperatures_c: dict[str, float] = field(default_factory=dict)
    gpu_percent: float | None = None

    def to_json(self) -> dict[str, object]:
        return {
            "load_1m": self.load_1m,
            "cpu_percent": _r(self.cpu_percent),
            "cpu_core_percent": [round(c, 1) for c in self.cpu_core_percent],
            "mem_used_mib": _r(self.mem_used_mib),
            "mem_total_mib": _r(self.mem_total_mib),
            "temperatures_c": {k: round(v, 1) for k, v in self.temperatures_c.items()},
            "gpu_percent": _r(self.gpu_percent),
        }


def _r(x: float | None) -> float | None:
    return None if x is None else round(x, 1)


def parse_proc_stat(text: str) -> tuple[CpuTimes | None, list[CpuTimes]]:
    """The aggregate ``cpu`` line and the per-core ``cpuN`` lines of ``/proc/stat``."""
    total: CpuTimes | None = None
    cores: list[CpuTimes] = []
    for line in text.splitlines():
        if not line.startswith("cpu"):
            continue
        name, *fields = line.split()
        values = [int(v) for v in fields[:8]]  # user nice system idle iowait irq softirq steal
        if len(values) < 4:
            continue
        idle = values[3] + (values[4] if len(values) > 4 else 0)
        times = CpuTimes(busy=sum(values) - idle, total=sum(values))
        if name == "cpu":
            total = times
        else:
            cores.append(times)
    return total, cores


def cpu_percent(prev: CpuTimes, now: CpuTimes) -> float | None:
    """CPU use between two samples, %; None when no time passed."""
    d_total = now.total - prev.total
    if d_total <= 0:
        return None
    return 100.0 * max(0, now.busy - prev.busy) / d_total


def parse_meminfo(text: str) -> tuple[float | None, float | None]:
    """(used, total) MiB from ``/proc/meminfo``; used = total - available."""
    kib: dict[str, int] = {}
    for line in text.splitlines():
        key, _, rest = line.partition(":")
        parts = rest.split()
        if parts and parts[0].isdigit():
            kib[key] = int(parts[0])
    total = kib.get("MemTotal")
    avail = kib.get("MemAvailable")
    if total is None:
        return None, None
    used = None if avail is None else (total - avail) / 1024.0
    return used, total / 1024.0


class SystemMonitor:
    """Samples the machine; CPU percentages are over the interval since the previous :meth:`read`."""

    def __init__(self, root: Path = Path("/")) -> None:
        self._root = root
        self._prev_total: CpuTimes | None = None
        self._prev_cores: list[CpuTimes] = []

    def read(self) -> SystemReading:
        """One sample (a few small file reads; cheap enough for the event loop at 1 Hz)."""
        load = self._read("proc/loadavg")
        load_1m = float(load.split()[0]) if load else None
        cpu_total = None
        cores_pct: list[float] = []
        stat = self._read("proc/stat")
        if stat:
            total, cores = parse_proc_stat(stat)
            if total is not None and self._prev_total is not None:
                cpu_total = cpu_percent(self._prev_total, total)
            if len(cores) == len(self._prev_cores):
                for prev, now in zip(self._prev_cores, cores, strict=True):
                    pct = cpu_percent(prev, now)
                    cores_pct.append(0.0 if pct is None else pct)
            self._prev_total, self._prev_cores = total, cores
        mem = self._read("proc/meminfo")
        used, total_mib = parse_meminfo(mem) if mem else (None, None)
        return SystemReading(
            load_1m=load_1m,
            cpu_percent=cpu_total,
            cpu_core_percent=tuple(cores_pct),
            mem_used_mib=used,
            mem_total_mib=total_mib,
            temperatures_c=self._temperatures(),
            gpu_percent=self._gpu_percent(),
        )

    def _temperatures(self) -> dict[str, float]:
        out: dict[str, float] = {}
        base = self._root / "sys/class/thermal"
        if not base.is_dir():
            return out
        for zone in sorted(base.glob("thermal_zone*")):
            raw = _read_file(zone / "temp")
            if raw is None or not raw.strip().lstrip("-").isdigit():
                continue
            name = (_read_file(zone / "type") or zone.name).strip() or zone.name
            milli_c = int(raw.strip())
            if milli_c <= -40000:  # Jetson reports -256 C for zones that are switched off
                continue
            out[name if name not in out else f"{name}.{zone.name}"] = milli_c / 1000.0
        return out

    def _gpu_percent(self) -> float | None:
        for rel in _JETSON_GPU_LOAD:
            raw = self._read(rel)
            if raw and raw.strip().isdigit():
                return int(raw.strip()) / 10.0
        return None

    def _read(self, rel: str) -> str | None:
        return _read_file(self._root / rel)


def _read_file(path: Path) -> str | None:
    try:
        return path.read_text()
    except OSError:
        return None
