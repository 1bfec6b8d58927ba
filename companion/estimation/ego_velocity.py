"""The follower's own velocity without GPS: a drag model learnt while GPS is good, flown on attitude after.

Why: the tracker subtracts the follower's own velocity changes from the leader's relative motion
(ego-motion). With GPS, PX4's velocity is good. Without it, PX4 dead-reckons on its accelerometers, which
cannot feel aerodynamic drag: in PX4 SITL its velocity ran off by 1-2 m/s within 2-4 s of the loss, and
taken as the follower's manoeuvres it threw the track off the leader. Left out, the track lags every
manoeuvre of the follower's own.

The model, horizontal NED per unit mass, in level flight (thrust balances gravity)::

    dv/dt = tilt(R) - k v + c        tilt(R) = -g (R[0, 2], R[1, 2]) / R[2, 2]

``tilt`` is the acceleration the thrust gives at the attitude ``R_ned_body``, ``k`` a linear drag (1/s) and
``c`` the push of a steady wind (``k`` times the wind). PX4's heading estimate is off the truth by ``e``
(``yaw_est - yaw_true``): the attitude turns ``tilt`` by ``e`` against GPS's north, so the fit carries
``e`` too, linearised (a few degrees). While GPS is good, :meth:`EgoVelocityObserver.learn` fits
``(k, c_n, c_e, e)`` by least squares with exponential forgetting to GPS velocity differences; after the
loss, :meth:`EgoVelocityObserver.step` integrates the model from the last GPS velocity on the attitude
alone, in GPS's frame (the tilt turned back by the fitted heading error), so the velocity the tracker gets
goes on smoothly from PX4's last aided one. Pure: times come in, nothing is read from a clock.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from companion.kernel.frames import Mat3, Vec3

Velocity = Vec3 | tuple[float, float, float]

G_M_S2 = 9.80665
#: GPS velocity differences are taken over at least this long, s (shorter ones are mostly noise).
SAMPLE_DT_S = 0.2
#: Longer gaps between velocity samples are not differenced (a telemetry gap, not an acceleration), s.
MAX_SAMPLE_DT_S = 1.0
#: The fit forgets with this time constant, s: wind and mass drift slowly.
FORGET_TAU_S = 60.0
#: The model is used once it has seen this many differences and this much speed change (m/s).
MIN_SAMPLES = 40
MIN_SPEED_SPAN_M_S = 1.0
#: Prior on (k, c_n, c_e, e): a weak pull towards (0.3 1/s, no wind, no heading error), in the
#: information form (1 / sigma^2, times a small weight: it only keeps the fit defined before data come).
_PRIOR_MEAN = np.array([0.3, 0.0, 0.0, 0.0])
_PRIOR_INFO = np.diag([1.0 / 0.5**2, 1.0 / 1.0**2, 1.0 / 1.0**2, 1.0 / 0.1**2]) * 0.1
#: Accepted fits: drag between these (1/s), heading error within this (rad).
DRAG_RANGE_PER_S = (0.0, 3.0)
MAX_HEADING_ERROR_RAD = math.radians(30.0)
#: The fitted heading error is applied only when its one sigma is within this, rad.
MAX_HEADING_SIGMA_RAD = math.radians(1.5)
#: ...and only when it is at least this large, rad. Against an exact heading (the project's simulator with
#: its error off) the fit wandered up to 2.1 deg at a stated sigma of 0.65 deg (its residuals are
#: correlated over seconds, so the stated sigma is low), and a correction taken then turned every bearing
#: by 2 deg for the rest of the flight.
MIN_HEADING_ERROR_RAD = math.radians(3.0)
#: After this long without GPS the model's velocity is no longer offered, s (its error has grown).
MAX_COAST_S = 120.0


def thrust_accel_h(R_ned_body: Mat3) -> tuple[float, float]:
    """Horizontal acceleration from thrust at attitude ``R_ned_body`` in level flight, NED m/s^2."""
    r22 = max(float(R_ned_body[2, 2]), 0.2)  # tilted beyond ~78 deg: no level flight to speak of
    return -G_M_S2 * float(R_ned_body[0, 2]) / r22, -G_M_S2 * float(R_ned_body[1, 2]) / r22


@dataclass(frozen=True, slots=True)
class EgoModel:
    """A fitted model: drag (1/s), wind push (NED m/s^2, north and east), heading error (rad)."""

    drag_per_s: float
    push_ne_m_s2: tuple[float, float]
    heading_error_rad: float
    samples: int
    #: One sigma of the heading error's fit, rad (from the residuals and how much tilt the flight had).
    heading_sigma_rad: float = math.inf

    @property
    def heading_trusted(self) -> bool:
        """Whether the heading error is known well enough, and large enough, to correct the bearings with.

        Significant too (three sigma, and at least :data:`MIN_HEADING_ERROR_RAD`): against an exact
        heading the fit wandered within about 1 deg of zero at a stated sigma of 0.6-0.9 deg, now and then
        to 2 deg, and correcting by that would only add error.
        """
        sigma = self.heading_sigma_rad
        e = abs(self.heading_error_rad)
        return sigma <= MAX_HEADING_SIGMA_RAD and e >= max(3.0 * sigma, MIN_HEADING_ERROR_RAD)


class EgoVelocityObserver:
    """Learns the follower's drag while GPS is good; estimates its horizontal velocity without GPS."""

    def __init__(self) -> None:
        self._info = _PRIOR_INFO.copy()
        self._vec = _PRIOR_INFO @ _PRIOR_MEAN
        self._yy = 0.0  # the decayed sum of squared targets, and of rows (for the residuals)
        self._rows = 0.0
        self._samples = 0
        self._v_min = math.inf
        self._v_max = -math.inf
        self._last: tuple[float, float, float, tuple[float, float]] | None = None  # t, vn, ve, tilt
        self._tilt_sum = np.zeros(2)
        self._tilt_n = 0
        self._model: EgoModel | None = None
        self._coast: tuple[float, np.ndarray] | None = None  # t_s, v (attitude frame, horizontal)
        self._coast_since_s = 0.0
        self._vd_m_s = 0.0

    # -- while GPS is good ---------------------------------------------------------------------------
    def learn(self, t_s: float, v_ned_m_s: Velocity, R_ned_body: Mat3) -> None:
        """One GPS-aided velocity sample (NED m/s, GPS's north) with the attitude at the same time."""
        self._coast = None
        tilt = thrust_accel_h(R_ned_body)
        vn, ve = float(v_ned_m_s[0]), float(v_ned_m_s[1])
        self._vd_m_s = float(v_ned_m_s[2])
        if not (math.isfinite(vn) and math.isfinite(ve) and all(math.isfinite(x) for x in tilt)):
            return
        self._tilt_sum += tilt
        self._tilt_n += 1
        last = self._last
        if last is None:
            self._last = (t_s, vn, ve, tilt)
            self._tilt_sum[:] = 0.0
            self._tilt_n = 0
            return
        dt = t_s - last[0]
        if dt < SAMPLE_DT_S:
            return
        tilt_mean = self._tilt_sum / self._tilt_n
        self._tilt_sum[:] = 0.0
        self._tilt_n = 0
        self._last = (t_s, vn, ve, tilt)
        if dt > MAX_SAMPLE_DT_S:
            return
        accel = ((vn - last[1]) / dt, (ve - last[2]) / dt)
        self._add(dt, accel, (0.5 * (vn + last[1]), 0.5 * (ve + last[2])), tilt_mean)
        speed = math.hypot(vn, ve)
        self._v_min = min(self._v_min, speed)
        self._v_max = max(self._v_max, speed)

    def _add(
        self, dt: float, accel: tuple[float, float], v_mid: tuple[float, float], tilt: np.ndarray
    ) -> None:
        (an, ae), (vn, ve) = accel, v_mid
        tn, te = float(tilt[0]), float(tilt[1])
        # y = a - tilt = -k v + c - e J tilt, J tilt = (-te, tn): rows over theta = (k, c_n, c_e, e).
        rows = np.array([[-vn, 1.0, 0.0, te], [-ve, 0.0, 1.0, -tn]])
        y = np.array([an - tn, ae - te])
        decay = math.exp(-dt / FORGET_TAU_S)
        self._info = decay * self._info + (1.0 - decay) * _PRIOR_INFO + rows.T @ rows
        self._vec = decay * self._vec + (1.0 - decay) * (_PRIOR_INFO @ _PRIOR_MEAN) + rows.T @ y
        self._yy = decay * self._yy + float(y @ y)
        self._rows = decay * self._rows + 2.0
        self._samples += 1
        self._model = None

    def model(self) -> EgoModel | None:
        """The fit, once it has seen enough and is plausible; else None."""
        if self._model is not None:
            return self._model
        if self._samples < MIN_SAMPLES or self._v_max - self._v_min < MIN_SPEED_SPAN_M_S:
            return None
        theta = np.linalg.solve(self._info, self._vec)
        k, cn, ce, e = (float(x) for x in theta)
        if not (DRAG_RANGE_PER_S[0] <= k <= DRAG_RANGE_PER_S[1]) or abs(e) > MAX_HEADING_ERROR_RAD:
            return None
        # Residual variance of the least squares (prior terms left out: they are small by design).
        rss = max(self._yy - float(theta @ self._vec), 0.0)
        var_y = rss / max(self._rows - theta.size, 1.0)
        sigma_e = math.sqrt(var_y * float(np.linalg.inv(self._info)[3, 3]))
        self._model = EgoModel(k, (cn, ce), e, self._samples, sigma_e)
        return self._model

    # -- after the loss ------------------------------------------------------------------------------
    def step(
        self, t_s: float, R_ned_body: Mat3, v_start_ned_m_s: Velocity, vd_m_s: float | None = None
    ) -> Vec3 | None:
        """The follower's velocity at ``t_s`` without GPS, GPS's frame (NED m/s); None without a model.

        ``v_start_ned_m_s``: the last GPS-aided velocity, where the first step after the loss starts from.
        ``vd_m_s``: the autopilot's vertical velocity, which the barometer keeps aided without GPS (its
        height stays valid); None or not finite holds the last GPS-aided one.
        """
        m = self.model()
        if m is None:
            return None
        if self._coast is None:
            v0 = np.asarray(v_start_ned_m_s, dtype=np.float64)
            self._coast = (t_s, v0[:2].copy())
            self._coast_since_s = t_s
        t0, v = self._coast
        if t_s - self._coast_since_s > MAX_COAST_S:
            return None
        dt = min(max(t_s - t0, 0.0), MAX_SAMPLE_DT_S)
        tilt = _turn(np.array([*thrust_accel_h(R_ned_body), 0.0]), -m.heading_error_rad)[:2]
        accel = tilt - m.drag_per_s * v + np.asarray(m.push_ne_m_s2)
        v = v + accel * dt
        self._coast = (t_s, v)
        if vd_m_s is not None and math.isfinite(vd_m_s):
            self._vd_m_s = vd_m_s
        return np.array([v[0], v[1], self._vd_m_s])


def _turn(v: np.ndarray, angle_rad: float) -> np.ndarray:
    """``v`` turned about NED down by ``angle_rad`` (north towards east)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    out = v.copy()
    out[0] = c * v[0] - s * v[1]
    out[1] = s * v[0] + c * v[1]
    return out
