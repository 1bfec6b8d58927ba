"""TEST-ONLY point-mass follower and circling leader, to exercise the formation law in closed loop.

Not the simulator and not a vision result: the law is fed the true relative state. It checks the law's
structure (signs, feed-forward, integrators, limits) quickly; the SITL tests check it against PX4 behaviour.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.kernel.flight import AttitudeSetpoint, VelocityBodySetpoint
from companion.kernel.frames import wrap_pi
from companion.mission.geometry import FollowerState
from companion.mission.safety import G_M_S2

PX4_YAW_P = 2.8


@dataclass
class Leader:
    """Flies a circle of ``radius_m`` at ``speed_m_s`` around the origin, counter-clockwise from above."""

    radius_m: float = 15.0
    speed_m_s: float = 3.0
    alt_m: float = 5.0

    def state(self, t_s: float) -> tuple[np.ndarray, np.ndarray]:
        w = self.speed_m_s / self.radius_m
        a = w * t_s
        p = np.array([self.radius_m * math.cos(a), self.radius_m * math.sin(a), -self.alt_m])
        v = np.array([-self.speed_m_s * math.sin(a), self.speed_m_s * math.cos(a), 0.0])
        return p, v


@dataclass
class PointMass:
    """A follower: velocity setpoints through a first-order lag, or attitude+thrust through simple physics."""

    p: np.ndarray
    v: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw_rad: float = 0.0
    roll_rad: float = 0.0
    pitch_rad: float = 0.0
    hover_thrust: float = 0.55
    drag_1_s: float = 0.15
    tau_v_s: float = 0.35
    tau_att_s: float = 0.12

    def follower(self, *, velocity_valid: bool = True) -> FollowerState:
        return FollowerState(
            yaw_rad=self.yaw_rad,
            v_ned_m_s=self.v.copy() if velocity_valid else None,
            v_down_m_s=float(self.v[2]),
            alt_rel_m=float(-self.p[2]),
            p_ned_m=self.p.copy() if velocity_valid else None,
            roll_rad=self.roll_rad,
            pitch_rad=self.pitch_rad,
        )

    def step_velocity(self, sp: VelocityBodySetpoint, dt_s: float) -> None:
        c, s = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        f, r, d = sp.v_body_m_s
        v_cmd = np.array([c * f - s * r, s * f + c * r, d])
        self.v += (v_cmd - self.v) * (dt_s / self.tau_v_s)
        self.p += self.v * dt_s
        self.yaw_rad = wrap_pi(self.yaw_rad + sp.yaw_rate_rad_s * dt_s)

    def step_attitude(self, sp: AttitudeSetpoint, dt_s: float) -> None:
        k = dt_s / self.tau_att_s
        self.roll_rad += (sp.roll_rad - self.roll_rad) * k
        self.pitch_rad += (sp.pitch_rad - self.pitch_rad) * k
        self.yaw_rad = wrap_pi(self.yaw_rad + PX4_YAW_P * wrap_pi(sp.yaw_rad - self.yaw_rad) * dt_s)
        thrust_acc = G_M_S2 * sp.thrust_norm / self.hover_thrust
        cr, sr = math.cos(self.roll_rad), math.sin(self.roll_rad)
        cp, sp_ = math.cos(self.pitch_rad), math.sin(self.pitch_rad)
        cy, sy = math.cos(self.yaw_rad), math.sin(self.yaw_rad)
        # Body z axis (down) in NED, thrust acts along -z_body.
        z_body = np.array([cr * sp_ * cy + sr * sy, cr * sp_ * sy - sr * cy, cr * cp])
        a = -thrust_acc * z_body + np.array([0.0, 0.0, G_M_S2]) - self.drag_1_s * self.v
        self.v += a * dt_s
        self.p += self.v * dt_s
