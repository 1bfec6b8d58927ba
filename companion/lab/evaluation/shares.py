"""What the vehicles of a formation share over MQTT, as it reaches each follower: sampled, delayed, local.

Every vehicle publishes its own estimate (position, velocity, heading) while its GPS is good, ``rate_hz``
times a second; it arrives ``latency_s`` later. Each follower sees positions in its own local NED frame
(the publisher's local estimate moved by the offset between both EKF origins, as the service does with
geodetic positions).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field

from companion.kernel.flight import Vec3T


@dataclass(frozen=True, slots=True)
class Share:
    """One vehicle's estimate in the shared world frame (NED from the simulator's home) at ``t_s``."""

    name: str
    t_s: float
    p_world_ned_m: Vec3T
    v_ned_m_s: Vec3T
    yaw_rad: float
    yaw_rate_rad_s: float


@dataclass(slots=True)
class ShareBus:
    """Shares in flight: published when due, delivered after the latency."""

    rate_hz: float = 10.0
    latency_s: float = 0.1
    _pending: deque[tuple[float, Share]] = field(default_factory=deque)
    _next_s: float = 0.0

    def due(self, t_s: float) -> bool:
        return t_s + 1e-9 >= self._next_s

    def publish(self, t_s: float, shares: list[Share]) -> None:
        """The estimates of every vehicle whose GPS is good at ``t_s`` (call when :meth:`due`)."""
        self._next_s = t_s + 1.0 / self.rate_hz
        for s in shares:
            self._pending.append((t_s + self.latency_s, s))

    def arrived(self, t_s: float) -> list[Share]:
        out = []
        while self._pending and self._pending[0][0] <= t_s + 1e-9:
            out.append(self._pending.popleft()[1])
        return out
