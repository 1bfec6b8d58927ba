"""ONBOARD_COMPUTER_STATUS (MAVLink message 390) from the machine's readings; pure.

MAVLink marks unused array entries with the type's maximum (UINT8_MAX for loads, INT8_MAX for
temperatures) and ``cpu_combined``/``gpu_combined`` hold the last 10 samples, newest first.
"""

from __future__ import annotations

from collections import deque

from companion.service.ports import OnboardComputerStatus
from companion.service.sysinfo import SystemReading

UINT8_MAX = 255
INT8_MAX = 127
INT16_MAX = 32767
UINT32_MAX = 4294967295


def _pct(x: float | None) -> int:
    return UINT8_MAX if x is None else max(0, min(100, round(x)))


def _temp(x: float | None) -> int:
    return INT8_MAX if x is None else max(-128, min(126, round(x)))


def _pad(values: list[int], n: int, fill: int) -> list[int]:
    return (values + [fill] * n)[:n]


class OnboardStatusBuilder:
    """Keeps the 10-sample CPU/GPU history the message carries."""

    def __init__(self) -> None:
        self._cpu: deque[int] = deque(maxlen=10)
        self._gpu: deque[int] = deque(maxlen=10)

    def build(self, reading: SystemReading, uptime_s: float, time_unix_s: float) -> OnboardComputerStatus:
        """The message fields for one reading."""
        self._cpu.appendleft(_pct(reading.cpu_percent))
        self._gpu.appendleft(_pct(reading.gpu_percent))
        temps = reading.temperatures_c
        board = next((v for k, v in temps.items() if "cpu" in k.lower()), None)
        if board is None and temps:
            board = max(temps.values())
        cores = [_pct(c) for c in reading.cpu_core_percent]
        fields: dict[str, int | list[int]] = {
            "time_usec": int(time_unix_s * 1e6),
            "uptime": min(UINT32_MAX, int(uptime_s * 1000)),
            "type": 0,  # the primary mission computer
            "cpu_cores": _pad(cores, 8, UINT8_MAX),
            "cpu_combined": _pad(list(self._cpu), 10, UINT8_MAX),
            "gpu_cores": _pad(
                [_pct(reading.gpu_percent)] if reading.gpu_percent is not None else [], 4, UINT8_MAX
            ),
            "gpu_combined": _pad(list(self._gpu) if reading.gpu_percent is not None else [], 10, UINT8_MAX),
            "temperature_board": _temp(board),
            "temperature_core": _pad([_temp(v) for v in list(temps.values())[:8]], 8, INT8_MAX),
            "fan_speed": [INT16_MAX] * 4,
            "ram_usage": 0 if reading.mem_used_mib is None else round(reading.mem_used_mib),
            "ram_total": 0 if reading.mem_total_mib is None else round(reading.mem_total_mib),
            "storage_type": [0] * 4,
            "storage_usage": [0] * 4,
            "storage_total": [0] * 4,
            "link_type": [0] * 6,
            "link_tx_rate": [0] * 6,
            "link_rx_rate": [0] * 6,
            "link_tx_max": [0] * 6,
            "link_rx_max": [0] * 6,
        }
        return OnboardComputerStatus(fields)
