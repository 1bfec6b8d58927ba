"""Collective thrust for the attitude law (GPS lost): vertical speed in, normalised thrust out."""

from __future__ import annotations

import math

import numpy as np

from companion.mission.safety import G_M_S2


class ThrustController:
    """Vertical speed -> normalised collective thrust, with an adaptive hover-thrust estimate.

    ``thrust = hover * (1 + a_up / g) / (cos roll cos pitch)`` with ``a_up = kv (v_down - v_down_des)``.
    The hover estimate integrates the vertical-speed error, so a wrong initial guess (PX4's MPC_THR_HOVER,
    or the config default) is learned within seconds instead of leaving a steady climb or sink.
    """

    KV_1_S = 3.0
    K_HOVER = 0.15
    MIN_THRUST = 0.05
    MAX_THRUST = 0.95

    def __init__(self, hover_thrust_norm: float) -> None:
        self.hover_thrust_norm = hover_thrust_norm

    def thrust(
        self, v_down_des_m_s: float, v_down_m_s: float, roll_rad: float, pitch_rad: float, dt_s: float
    ) -> float:
        err = v_down_m_s - v_down_des_m_s
        a_up = self.KV_1_S * err
        self.hover_thrust_norm = float(np.clip(self.hover_thrust_norm + self.K_HOVER * err * dt_s, 0.1, 0.9))
        cos_tilt = max(0.5, math.cos(roll_rad) * math.cos(pitch_rad))
        t = self.hover_thrust_norm * (1.0 + a_up / G_M_S2) / cos_tilt
        return float(np.clip(t, self.MIN_THRUST, self.MAX_THRUST))
