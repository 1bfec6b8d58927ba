"""How a flight ended, judged from the simulator's truth only (pure: samples in, verdict out).

Used by both evaluation harnesses; the service never sees any of it. Definitions:

* **crashed**: the follower hit the ground faster than ``crash_touchdown_m_s`` (vertical), tilted beyond
  ``crash_tilt_deg`` in the air, or came within ``collision_m`` of the leader (centre to centre).
* **on the ground**: height of the centre of gravity above its resting height below ``ground_band_m`` and
  slower than ``still_m_s``. A touchdown is the first sample on the ground after having been airborne; its
  vertical speed is the one reported (the land policy's bar is <= 1 m/s).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike

from companion.lab.evaluation.obstacles import Envelopes

#: The quad's centre of gravity rests this far above the ground (``sitl`` model, world NED z = -0.094 m).
REST_HEIGHT_M = 0.094


@dataclass(slots=True)
class TruthMonitor:
    """Watches the follower's true state; feed it every sample with :meth:`update`."""

    crash_touchdown_m_s: float = 2.0
    crash_tilt_deg: float = 60.0
    collision_m: float = 0.6
    #: The scene's structures (None: open ground only) and the follower's radius against them, m.
    obstacles: Envelopes | None = None
    body_radius_m: float = 0.3
    ground_band_m: float = 0.08
    still_m_s: float = 0.3
    airborne_m: float = 0.5
    crashed: bool = False
    crash_reason: str = ""
    crash_t_s: float | None = None
    airborne: bool = False
    on_ground: bool = True
    touchdowns: list[tuple[float, float]] = field(default_factory=list)
    max_height_m: float = 0.0
    min_separation_m: float = math.inf
    #: Closest the follower's centre came to a structure's envelope, m (inf without structures).
    min_obstacle_clearance_m: float = math.inf
    _descent_m_s: float = 0.0

    def update(
        self,
        t_s: float,
        p_ned_follower_m: ArrayLike,
        v_ned_follower_m_s: ArrayLike,
        q_ned_follower_wxyz: ArrayLike,
        p_ned_leader_m: ArrayLike | None,
    ) -> None:
        """One truth sample (world NED, m and m/s; attitude as a unit quaternion)."""
        p = np.asarray(p_ned_follower_m, dtype=np.float64)
        v = np.asarray(v_ned_follower_m_s, dtype=np.float64)
        height_m = -float(p[2]) - REST_HEIGHT_M
        self.max_height_m = max(self.max_height_m, height_m)
        speed_m_s = float(np.linalg.norm(v))
        if height_m > self.airborne_m:
            self.airborne = True
        contact = height_m < self.ground_band_m
        if self.airborne and contact and not self.on_ground:
            # First contact after flight: the vertical speed just before it is the touchdown speed.
            touchdown_m_s = max(float(v[2]), self._descent_m_s)
            self.touchdowns.append((t_s, touchdown_m_s))
            if touchdown_m_s > self.crash_touchdown_m_s:
                self._crash(t_s, f"hit the ground at {touchdown_m_s:.1f} m/s")
        self.on_ground = contact and (speed_m_s < self.still_m_s or self.on_ground)
        self._descent_m_s = float(v[2]) if not contact else 0.0
        _, x, y, _ = (float(c) for c in np.asarray(q_ned_follower_wxyz, dtype=np.float64))
        # Tilt: angle between body z and NED down, from the quaternion's R[2, 2].
        cos_tilt = 1.0 - 2.0 * (x * x + y * y)
        tilt_deg = math.degrees(math.acos(max(-1.0, min(1.0, cos_tilt))))
        if not contact and tilt_deg > self.crash_tilt_deg:
            self._crash(t_s, f"tilted {tilt_deg:.0f} deg in the air")
        if self.obstacles is not None and len(self.obstacles):
            clear_m, kind = self.obstacles.clearance(p)
            self.min_obstacle_clearance_m = min(self.min_obstacle_clearance_m, clear_m)
            if clear_m < self.body_radius_m:
                self._crash(t_s, f"hit a {kind} (centre {clear_m:.2f} m from its envelope)")
        if p_ned_leader_m is not None:
            sep = float(np.linalg.norm(np.asarray(p_ned_leader_m, dtype=np.float64) - p))
            self.min_separation_m = min(self.min_separation_m, sep)
            if sep < self.collision_m:
                self._crash(t_s, f"came within {sep:.2f} m of the leader")

    def _crash(self, t_s: float, why: str) -> None:
        if not self.crashed:
            self.crashed, self.crash_reason, self.crash_t_s = True, why, t_s

    @property
    def landed(self) -> bool:
        """Flew, and is now resting on the ground (without having crashed)."""
        return self.airborne and self.on_ground and not self.crashed

    @property
    def touchdown_m_s(self) -> float | None:
        """Vertical speed at the last touchdown, m/s (None if it never touched down after flying)."""
        return self.touchdowns[-1][1] if self.touchdowns else None
