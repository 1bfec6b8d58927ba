"""PX4's heading estimate against the true one: a bias drawn per flight plus a slow wander (pure, seeded)."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True, slots=True)
class HeadingErrorModel:
    """How far PX4's heading estimate is from the true heading: a bias per flight plus a slow wander.

    Measured on PX4 SITL (SIH quadrotor with its magnetometer, hovering 60 s): estimate minus truth ranged
    from 0 to -10 deg (mean -6 deg, wandering over tens of seconds); in formation flights 4-9 deg. Roll and
    pitch stayed within about 1 deg of the truth. ``[world] heading_*`` in config/sitl.toml turn it on.
    """

    bias_sigma_deg: float = 4.0
    wander_sigma_deg: float = 3.0
    wander_tau_s: float = 15.0


class HeadingError:
    """PX4's heading estimate minus the true heading, rad (seeded; :meth:`update` at the outer-loop rate)."""

    def __init__(self, rng: np.random.Generator, model: HeadingErrorModel = HeadingErrorModel()) -> None:
        self._rng = rng
        self.model = model
        self._bias_rad = math.radians(model.bias_sigma_deg) * float(rng.standard_normal())
        self._wander_rad = math.radians(model.wander_sigma_deg) * float(rng.standard_normal())
        self.rad = self._bias_rad + self._wander_rad

    def update(self, dt_s: float) -> float:
        """Advance by ``dt_s`` (first-order Gauss-Markov wander); the error now, rad."""
        m = self.model
        a = math.exp(-dt_s / m.wander_tau_s)
        sigma = math.radians(m.wander_sigma_deg) * math.sqrt(1.0 - a * a)
        self._wander_rad = a * self._wander_rad + sigma * float(self._rng.standard_normal())
        self.rad = self._bias_rad + self._wander_rad
        return self.rad
