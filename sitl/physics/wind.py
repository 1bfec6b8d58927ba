"""Wind: a steady mean, seeded discrete gusts and light turbulence (pure, sim time in).

Gusts are MIL-F-8785C "1 - cosine" shapes: each rises and falls smoothly over its duration, peaks at
an amplitude drawn up to ``gust_max_m_s``, and blows within +-30 deg of the mean direction. They
arrive as a Poisson process with mean spacing ``gust_interval_s``; overlapping gusts are capped at
``gust_max_m_s`` together, so the wind never exceeds mean + gust_max (plus turbulence). Turbulence
is a first-order Gauss-Markov process per axis. The field is uniform in space (vehicles metres
apart feel the same air), which is what matters for a formation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class WindParams:
    """Wind settings; ``from_deg`` is meteorological (where the wind comes from, 0 = north)."""

    mean_speed_m_s: float = 0.0
    from_deg: float = 0.0
    gust_max_m_s: float = 0.0
    gust_interval_s: float = 15.0
    gust_duration_min_s: float = 2.0
    gust_duration_max_s: float = 5.0
    turbulence_m_s: float = 0.0
    turbulence_tau_s: float = 2.0


@dataclass(frozen=True, slots=True)
class _Gust:
    start_s: float
    duration_s: float
    vn_m_s: float
    ve_m_s: float


class WindModel:
    """Air velocity in NED (where the air moves towards), m/s, at any sim time (call in order)."""

    def __init__(self, params: WindParams, rng: np.random.Generator) -> None:
        self.params = params
        self._rng = rng
        to_rad = math.radians(params.from_deg + 180.0)
        self._mean = (params.mean_speed_m_s * math.cos(to_rad), params.mean_speed_m_s * math.sin(to_rad))
        self._gusts: list[_Gust] = []
        self._next_gust_s = self._draw_gap() if params.gust_max_m_s > 0 else math.inf
        self._turb = [0.0, 0.0, 0.0]
        self._t_s = 0.0

    def _draw_gap(self) -> float:
        return float(self._rng.exponential(self.params.gust_interval_s))

    def _spawn(self, t_s: float) -> None:
        p = self.params
        # Peak amplitude: mostly moderate, sometimes near the maximum (a few per scenario reach it).
        amp = p.gust_max_m_s * float(self._rng.uniform(0.4, 1.0))
        base = math.radians(p.from_deg + 180.0) + math.radians(float(self._rng.uniform(-30.0, 30.0)))
        dur = float(self._rng.uniform(p.gust_duration_min_s, p.gust_duration_max_s))
        self._gusts.append(_Gust(t_s, dur, amp * math.cos(base), amp * math.sin(base)))

    def sample(self, t_s: float) -> tuple[float, float, float]:
        """Wind at ``t_s`` (NED, m/s)."""
        p = self.params
        dt = max(0.0, t_s - self._t_s)
        self._t_s = t_s
        while t_s >= self._next_gust_s:
            self._spawn(self._next_gust_s)
            self._next_gust_s += self._draw_gap()
        gn = ge = 0.0
        alive = []
        for g in self._gusts:
            x = (t_s - g.start_s) / g.duration_s
            if x < 1.0:
                alive.append(g)
                shape = 0.5 * (1.0 - math.cos(2.0 * math.pi * x))
                gn += shape * g.vn_m_s
                ge += shape * g.ve_m_s
        self._gusts = alive
        # Overlapping gusts must not add up past the configured peak.
        g_abs = math.hypot(gn, ge)
        if g_abs > p.gust_max_m_s > 0:
            gn, ge = gn * p.gust_max_m_s / g_abs, ge * p.gust_max_m_s / g_abs
        vn, ve = self._mean[0] + gn, self._mean[1] + ge
        vd = 0.0
        if p.turbulence_m_s > 0 and dt > 0:
            a = math.exp(-dt / p.turbulence_tau_s)
            s = p.turbulence_m_s * math.sqrt(1.0 - a * a)
            r = self._rng.standard_normal(3).tolist()
            self._turb = [
                a * self._turb[0] + s * r[0],
                a * self._turb[1] + s * r[1],
                a * self._turb[2] + 0.3 * s * r[2],
            ]
            vn += self._turb[0]
            ve += self._turb[1]
            vd = self._turb[2]
        return vn, ve, vd
