"""The tracker's motion models and filter arithmetic; pure.

Two models on the relative state in NED axes: constant velocity (``n`` = 6: p, v) for the track and its
challengers, and a Singer acceleration (``n`` = 9: p, v, a) for the opt-in leader-acceleration filter
(``tracker.leader_accel_filter``). Plus the follower's ego-motion shift and the Mahalanobis distance the
gate uses.
"""

from __future__ import annotations

import math

import numpy as np
from filterpy.kalman import KalmanFilter
from numpy.typing import NDArray

from companion.config import TrackerConfig
from companion.estimation.estimate import Mat6
from companion.kernel.frames import Mat3, Vec3

_EYE3 = np.eye(3)


def mahalanobis2(y: Vec3, S: Mat3) -> float:
    """``y^T S^-1 y`` for a symmetric positive-definite 3x3 ``S`` (closed form: no LAPACK call per box)."""
    a, b, c = float(S[0, 0]), float(S[0, 1]), float(S[0, 2])
    d, e, f = float(S[1, 1]), float(S[1, 2]), float(S[2, 2])
    # Adjugate of the symmetric matrix [[a b c] [b d e] [c e f]].
    A, B, C = d * f - e * e, c * e - b * f, b * e - c * d
    D, E, F = a * f - c * c, b * c - a * e, a * d - b * b
    det = a * A + b * B + c * C
    if det <= 0.0:
        return math.inf
    y0, y1, y2 = float(y[0]), float(y[1]), float(y[2])
    quad = A * y0 * y0 + D * y1 * y1 + F * y2 * y2 + 2.0 * (B * y0 * y1 + C * y0 * y2 + E * y1 * y2)
    return quad / det


def height_deweighted(R_ned_m2: Mat3, y_down_m: float, s_down_m2: float, dof: float) -> Mat3:
    """``R`` with its height (down) variance scaled by ``(dof + z^2) / (dof + 1)`` beyond one sigma.

    ``z^2 = y_down^2 / s_down``: the height innovation against its predicted variance. A Student-t's
    weighting of that one axis: a box whose height is several sigma off moves the track's height (and
    its vertical rate) a fraction of what a Gaussian update would, and an ordinary one as before. The
    row and column are scaled by the same factor's square root, so ``R`` stays positive definite.
    ``dof`` 0 returns ``R`` as it is.
    """
    if dof <= 0.0 or s_down_m2 <= 0.0:
        return R_ned_m2
    z2 = y_down_m * y_down_m / s_down_m2
    if z2 <= 1.0:
        return R_ned_m2
    k = math.sqrt((dof + z2) / (dof + 1.0))
    out: Mat3 = R_ned_m2.copy()
    out[2, :] *= k
    out[:, 2] *= k
    return out


def new_filter(cfg: TrackerConfig, p_ned_m: Vec3, R_ned_m2: Mat3, n: int) -> KalmanFilter:
    """A filter of ``n`` states (6: p, v; 9: p, v, a) started at a measurement, at rest."""
    kf = KalmanFilter(dim_x=n, dim_z=3)
    kf.x = np.concatenate([p_ned_m, np.zeros(n - 3)]).reshape(n, 1)
    P = np.zeros((n, n))
    P[:3, :3] = R_ned_m2
    P[3:6, 3:6] = _EYE3 * cfg.init_velocity_std_m_s**2
    if n == 9:
        P[6:, 6:] = _EYE3 * cfg.init_accel_std_m_s2**2
    kf.P = P
    kf.H = np.hstack([_EYE3, np.zeros((3, n - 3))])
    return kf


def ego_shift(
    dt: float, v_follower: Vec3 | None, v_follower_before: Vec3 | None, n: int
) -> NDArray[np.float64]:
    """The state change the follower's own velocity change causes over ``dt`` (linear in between).

    ``v_follower_before``: the follower's velocity at the filter's current time. The acceleration state
    (``n`` = 9) is the leader's own and is not shifted.
    """
    shift = np.zeros(n)
    if v_follower is not None and v_follower_before is not None:
        dv = np.asarray(v_follower, dtype=np.float64) - v_follower_before
        shift[:3] = -0.5 * dt * dv
        shift[3:6] = -dv
    return shift


def transition(cfg: TrackerConfig, dt: float, n: int) -> NDArray[np.float64]:
    """State transition over ``dt`` s: constant velocity (``n`` = 6), or a Singer acceleration (9).

    Singer: the leader's acceleration decays towards zero with ``accel_tau_s`` between measurements,
    so a filter without measurements does not extrapolate a manoeuvre for seconds.
    """
    if n == 6:
        return np.kron(np.array([[1.0, dt], [0.0, 1.0]]), _EYE3)
    tau = cfg.accel_tau_s
    e = math.exp(-dt / tau)
    per_axis = np.array(
        [[1.0, dt, tau * tau * (dt / tau - 1.0 + e)], [0.0, 1.0, tau * (1.0 - e)], [0.0, 0.0, e]]
    )
    return np.kron(per_axis, _EYE3)


def process_noise(cfg: TrackerConfig, dt: float, p_ned_m: Vec3, n: int, *, size_ranged: bool) -> Mat6:
    """Process noise over ``dt`` s, per axis.

    Constant velocity (``n`` = 6): discrete white-noise acceleration,
    ``[[dt^4/4, dt^3/2], [dt^3/2, dt^2]] * q`` with ``q = process_accel_std_m_s2^2``. Singer (9):
    white-noise jerk, ``jerk_std_m_s3^2`` times
    ``[[dt^5/20, dt^4/8, dt^3/6], [dt^4/8, dt^3/3, dt^2/2], [dt^3/6, dt^2/2, dt]]``.

    While the track is ranged by box size (``size_ranged``: beyond the stereo range), the noise along the
    line of sight ``p_ned_m`` is scaled by ``(size_range_accel_std_m_s2 / process_accel_std_m_s2)^2``:
    range then comes from ~10 % per-frame measurements and only a smoother radial motion model averages
    enough of them; across the line of sight the bearing stays precise.

    Constant velocity only: with ``process_accel_std_z_m_s2`` set, the height's noise is scaled by
    ``(process_accel_std_z_m_s2 / process_accel_std_m_s2)^2``. The follower's own climbs are taken out
    as ego-motion, so the relative height moves only when the leader's does; a noisy vertical rate fed
    forward otherwise pumps the follower's height.
    """
    if n == 6:
        T = (cfg.process_accel_std_m_s2**2 * dt * dt) * np.array([[dt * dt / 4.0, dt / 2.0], [dt / 2.0, 1.0]])
    else:
        d2, d3 = dt * dt, dt * dt * dt
        T = (cfg.jerk_std_m_s3**2) * np.array(
            [
                [d3 * d2 / 20.0, d2 * d2 / 8.0, d3 / 6.0],
                [d2 * d2 / 8.0, d3 / 3.0, d2 / 2.0],
                [d3 / 6.0, d2 / 2.0, dt],
            ]
        )
    r2 = p_ned_m @ p_ned_m
    if not size_ranged or r2 <= 0.0:
        shape = _EYE3
    else:
        # Spatial shape I - (1 - k) u u^T with k = (q_los / q)^2: the radial variance scaled down.
        k = (cfg.size_range_accel_std_m_s2 / cfg.process_accel_std_m_s2) ** 2
        shape = _EYE3 - ((1.0 - k) / r2) * np.outer(p_ned_m, p_ned_m)
    if n == 6 and cfg.process_accel_std_z_m_s2 is not None:
        # Height scaled apart (D shape D keeps it positive semi-definite).
        d = np.array([1.0, 1.0, cfg.process_accel_std_z_m_s2 / cfg.process_accel_std_m_s2])
        shape = shape * np.outer(d, d)
    Q: Mat6 = np.kron(T, shape).astype(np.float64)
    return Q
