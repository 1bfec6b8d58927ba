"""A model of PX4's EKF2 as clients see it (pure: time in, seeded randomness; the receiver: sitl.physics.gps).

What this reproduces is EKF2's *observable* behaviour, not its maths:

* With GNSS: position and velocity follow GPS through a complementary filter, so the estimate carries
  GPS's slowly wandering error (Gauss-Markov bias) but little of its white noise.
* Prediction integrates the true velocity change (what an IMU measures) plus an accelerometer bias
  error, so once aiding stops the estimate dead-reckons and drifts, growing quadratically.
* PX4's timeline after aiding stops (``ekf2/EKF/ekf_helper.cpp``, ``aid_sources/gnss/gps_control.cpp``):
  after 1 s the EKF counts as inertial dead-reckoning; after ``EKF2_NOAID_TOUT`` (5 s) horizontal
  position and velocity become invalid; after 7 s (``reset_timeout_max``) GNSS fusion stops with the
  STATUSTEXT "GNSS data fusion stopped". A GNSS fix that disagrees with the estimate (stuck or wrong
  receiver, jumps) fails the innovation gate, raises GPS_GLITCH, and after 7 s of rejection the EKF
  resets to it, as PX4 does.
* External vision (VISION_POSITION_ESTIMATE / ODOMETRY in the vehicle's local NED frame) is fused as
  another horizontal aiding source, so it keeps position valid with its own accuracy.
* Height comes from the barometer (always valid) with its offset to GNSS height learnt while GNSS is
  fused, so altitude stays valid and smooth after GPS loss.

Attitude and body rates are not estimated: the autopilot uses the true ones (EKF2's attitude error is
a fraction of a degree, below anything this simulator is used to measure).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Final

import numpy as np

from sitl.physics.geo import LocalProjection
from sitl.physics.gps import GpsSample, NormalDraws

# EKF2 timeline constants (s), from ekf2/EKF/common.h.
NO_AID_DEADRECKON_S = 1.0  # no_aid_timeout_max
RESET_TIMEOUT_S = 7.0  # reset_timeout_max
GPS_CHECK_PASS_S = 3.5  # PX4 SITL (SIH) passed its GPS checks and set home 4.2-4.3 s after boot
GPS_REGAIN_PASS_S = 1.0  # checks already passed once: short wait
GPS_GATE_SIGMA = 5.0  # EKF2_GPS_P_GATE / EKF2_GPS_V_GATE
GPS_POS_NOISE_M = 0.5  # EKF2_GPS_P_NOISE
GPS_VEL_NOISE_M_S = 0.3  # EKF2_GPS_V_NOISE
EV_GATE_SIGMA = 5.0  # EKF2_EVP_GATE
EV_DEFAULT_NOISE_M = 0.1  # EKF2_EVP_NOISE
EV_TIMEOUT_S = 0.5


@dataclass(slots=True)
class VisionSample:
    """An external-vision position (vehicle-local NED, m) with its standard deviation."""

    t_s: float
    n_m: float
    e_m: float
    d_m: float
    std_h_m: float
    vel_ned_m_s: tuple[float, float, float] | None = None


@dataclass(frozen=True, slots=True)
class EstimatorEvents:
    """Things that happened during one update (for STATUSTEXT and logs)."""

    texts: tuple[tuple[int, str], ...] = ()


_NO_EVENTS: Final = EstimatorEvents()


class Estimator:
    """EKF2's outputs for one vehicle in its local NED frame (origin: its EKF origin / home).

    Call :meth:`update` at the outer-loop rate (50 Hz) with the true kinematics (from which the "IMU"
    is derived), the new GPS fix if any, and the latest vision sample if any. Read the estimate
    from the attributes afterwards.
    """

    def __init__(
        self, origin: LocalProjection, rng: np.random.Generator, noaid_timeout_s: float = 5.0
    ) -> None:
        self.origin = origin
        self.noaid_timeout_s = noaid_timeout_s
        # Accelerometer bias error (what EKF2 has not estimated), m/s^2: drawn once, then a random walk.
        self._acc_bias = [float(x) for x in rng.normal(0.0, 0.03, 3)]
        self._acc_bias[2] *= 0.3
        self._prev_v_true: tuple[float, float, float] | None = None
        self.n_m = self.e_m = self.d_m = 0.0
        self.vn_m_s = self.ve_m_s = self.vd_m_s = 0.0
        # Baro: true height error = slow drift; offset to GNSS height learnt while fusing GNSS.
        self._baro_bias_m = float(rng.normal(0.0, 0.05))
        self._normals = NormalDraws(rng)  # after the draws above: from here on it owns rng
        self._texts: list[tuple[int, str]] = []
        self._baro_offset_m = 0.0
        self._baro_offset_avg_m: float | None = None
        # Aiding bookkeeping (sim time, s); -inf = never.
        self.t_last_h_aid_s = -math.inf
        self.t_last_gnss_fused_s = -math.inf
        self._t_gps_good_since_s: float | None = None
        self._t_gps_rejected_since_s: float | None = None
        self.gps_checks_passed = False
        self.gnss_fusing = False
        self.gps_glitch = False
        self.origin_valid = False
        self.ev_fusing = False
        self._t_last_ev_s = -math.inf
        self._eph_at_aid_m = 10.0
        self.eph_m = 10.0
        self.epv_m = 0.5
        self.evh_m_s = 1.0
        self.evv_m_s = 0.3
        self.t_s = 0.0
        self.reset_counter = 0

    # --- validity (EKF2's own flags) -------------------------------------------------------------
    def time_since_aid_s(self) -> float:
        return self.t_s - self.t_last_h_aid_s

    @property
    def xy_valid(self) -> bool:
        """``vehicle_local_position.xy_valid`` (and ``v_xy_valid``): aided within EKF2_NOAID_TOUT."""
        return self.time_since_aid_s() < self.noaid_timeout_s

    @property
    def dead_reckoning(self) -> bool:
        return self.origin_valid and self.time_since_aid_s() > NO_AID_DEADRECKON_S

    @property
    def global_valid(self) -> bool:
        return self.origin_valid and self.xy_valid

    @property
    def h_aiding(self) -> bool:
        return self.time_since_aid_s() <= NO_AID_DEADRECKON_S

    # --- update ----------------------------------------------------------------------------------
    def update(
        self,
        t_s: float,
        dt_s: float,
        *,
        p_local_true_m: tuple[float, float, float],
        v_true_m_s: tuple[float, float, float],
        gps: GpsSample | None,
        vision: VisionSample | None,
        a_imu_ned_m_s2: tuple[float, float, float] | None = None,
    ) -> EstimatorEvents:
        self.t_s = t_s
        # Prediction: the true velocity change, or while dead-reckoning ``a_imu_ned_m_s2`` (specific force in
        # NED plus g: what EKF2 integrates, blind to drag), plus the uncorrected accelerometer bias.
        if self._prev_v_true is None:
            dvn = dve = dvd = 0.0
            # Start at the truth (EKF2 aligns on the ground before anyone looks).
            self.n_m, self.e_m, self.d_m = p_local_true_m
        else:
            pv = self._prev_v_true
            dvn, dve, dvd = v_true_m_s[0] - pv[0], v_true_m_s[1] - pv[1], v_true_m_s[2] - pv[2]
        b = self._acc_bias
        rw = 0.004 * math.sqrt(dt_s)
        r = self._normals.take(5)
        b[0] += rw * r[0]
        b[1] += rw * r[1]
        b[2] += 0.3 * rw * r[2]
        if a_imu_ned_m_s2 is not None and self._prev_v_true is not None:
            dvn, dve, dvd = (a * dt_s for a in a_imu_ned_m_s2)
        self._prev_v_true = v_true_m_s
        self.vn_m_s += dvn + b[0] * dt_s
        self.ve_m_s += dve + b[1] * dt_s
        self.vd_m_s += dvd + b[2] * dt_s
        self.n_m += self.vn_m_s * dt_s
        self.e_m += self.ve_m_s * dt_s
        self.d_m += self.vd_m_s * dt_s

        if not self.origin_valid and t_s - self.t_last_h_aid_s > NO_AID_DEADRECKON_S:
            # Before any aiding EKF2 runs in constant-position mode: the vehicle sits where it woke up.
            self.n_m, self.e_m = p_local_true_m[0], p_local_true_m[1]
            self.vn_m_s, self.ve_m_s = v_true_m_s[0], v_true_m_s[1]

        # Baro height (always): true height + slow drift + noise, minus the learnt GNSS offset.
        self._baro_bias_m += 0.002 * math.sqrt(dt_s) * r[3]
        baro_d = p_local_true_m[2] + self._baro_bias_m + 0.05 * r[4]
        baro_est_d = baro_d - self._baro_offset_m
        innov_d = baro_est_d - self.d_m
        self.d_m += 0.08 * innov_d
        self.vd_m_s += 0.6 * innov_d * dt_s

        if gps is not None:
            self._fuse_gps(t_s, gps, baro_d)
        elif self.gnss_fusing and t_s - self.t_last_gnss_fused_s > RESET_TIMEOUT_S:
            self._stop_gnss()
        if vision is not None and vision.t_s > self._t_last_ev_s:
            self._fuse_vision(vision)
        self.ev_fusing = t_s - self._t_last_ev_s < EV_TIMEOUT_S + NO_AID_DEADRECKON_S

        # Accuracy: small while aided, growing as the dead-reckoning error would.
        tau = t_s - self.t_last_h_aid_s
        if tau <= NO_AID_DEADRECKON_S:
            self.eph_m = self._eph_at_aid_m
            self.evh_m_s = 0.1
        else:
            self.eph_m = math.sqrt(self._eph_at_aid_m**2 + (0.1 * tau) ** 2 + (0.5 * 0.05 * tau * tau) ** 2)
            self.evh_m_s = math.sqrt(0.01 + (0.05 * tau) ** 2)
        if not self._texts:
            return _NO_EVENTS
        ev = EstimatorEvents(tuple(self._texts))
        self._texts.clear()
        return ev

    def _fuse_gps(self, t_s: float, gps: GpsSample, baro_d_m: float) -> None:
        if gps.fix_type < 3 or gps.satellites < 6 or gps.eph_m > 3.0:
            self._t_gps_good_since_s = None
            return
        if self._t_gps_good_since_s is None:
            self._t_gps_good_since_s = t_s
        n, e, d = self.origin.to_ned(gps.lat_deg, gps.lon_deg, gps.alt_m)
        if not self.gnss_fusing:
            # While the checks run, average the baro-to-GNSS height offset (time constant ~3 s), so
            # that starting fusion does not step the height by one sample's noise.
            off = baro_d_m - d
            avg = self._baro_offset_avg_m
            self._baro_offset_avg_m = off if avg is None else avg + 0.03 * (off - avg)
            wait_s = GPS_REGAIN_PASS_S if self.gps_checks_passed else GPS_CHECK_PASS_S
            if t_s - self._t_gps_good_since_s < wait_s:
                return
            self.gps_checks_passed = True
            self.gnss_fusing = True
            self.origin_valid = True
            self._t_gps_rejected_since_s = None
            # Starting (or restarting) fusion resets the horizontal state to the receiver.
            self._reset_to_gps(n, e, gps)
            if self.t_last_gnss_fused_s == -math.inf:
                # First fusion: anchor the baro height to the averaged GNSS height. On a regain the
                # offset learnt before the loss is kept (the height estimate must not jump).
                avg = self._baro_offset_avg_m
                self._baro_offset_m = avg if avg is not None else baro_d_m - d
            self.t_last_gnss_fused_s = t_s
            self.t_last_h_aid_s = t_s
            self._eph_at_aid_m = 0.3
            return
        # Innovation gate (EKF2_GPS_P_GATE / V_GATE, in standard deviations).
        in_n, in_e = n - self.n_m, e - self.e_m
        in_vn, in_ve = gps.vn_m_s - self.vn_m_s, gps.ve_m_s - self.ve_m_s
        var_p = GPS_POS_NOISE_M**2 + self.eph_m**2
        var_v = GPS_VEL_NOISE_M_S**2 + self.evh_m_s**2
        pos_ratio = (in_n * in_n + in_e * in_e) / (GPS_GATE_SIGMA**2 * var_p)
        vel_ratio = (in_vn * in_vn + in_ve * in_ve) / (GPS_GATE_SIGMA**2 * var_v)
        if pos_ratio > 1.0 or vel_ratio > 1.0:
            self.gps_glitch = True
            if self._t_gps_rejected_since_s is None:
                self._t_gps_rejected_since_s = t_s
            if t_s - self._t_gps_rejected_since_s > RESET_TIMEOUT_S and not self.h_aiding:
                # No other aiding: EKF2 gives up on its own estimate and resets to the receiver.
                self._reset_to_gps(n, e, gps)
                self._t_gps_rejected_since_s = None
                self.t_last_gnss_fused_s = t_s
                self.t_last_h_aid_s = t_s
            elif t_s - self.t_last_gnss_fused_s > RESET_TIMEOUT_S and self.gnss_fusing:
                self._stop_gnss()
            return
        self.gps_glitch = False
        self._t_gps_rejected_since_s = None
        self.n_m += 0.1 * in_n
        self.e_m += 0.1 * in_e
        self.vn_m_s += 0.2 * in_vn + 0.05 * in_n
        self.ve_m_s += 0.2 * in_ve + 0.05 * in_e
        self.vd_m_s += 0.1 * (gps.vd_m_s - self.vd_m_s)
        # GNSS height slowly re-anchors the baro offset (EKF2_HGT_REF = GNSS).
        self._baro_offset_m += 0.01 * ((baro_d_m - d) - self._baro_offset_m)
        self.t_last_gnss_fused_s = t_s
        self.t_last_h_aid_s = t_s
        self._eph_at_aid_m = 0.3

    def _reset_to_gps(self, n: float, e: float, gps: GpsSample) -> None:
        self.n_m, self.e_m = n, e
        self.vn_m_s, self.ve_m_s = gps.vn_m_s, gps.ve_m_s
        self.reset_counter = (self.reset_counter + 1) % 256

    def _stop_gnss(self) -> None:
        self.gnss_fusing = False
        self.gps_glitch = False
        self._t_gps_good_since_s = None
        self._texts.append((4, "GNSS data fusion stopped"))  # MAV_SEVERITY_WARNING

    def _fuse_vision(self, v: VisionSample) -> None:
        std = v.std_h_m if math.isfinite(v.std_h_m) and v.std_h_m > 0 else EV_DEFAULT_NOISE_M
        std = max(0.01, std)
        in_n, in_e = v.n_m - self.n_m, v.e_m - self.e_m
        dt_since = v.t_s - self._t_last_ev_s
        self._t_last_ev_s = v.t_s
        aided = self.h_aiding
        var = std * std + (self.eph_m**2 if aided else 0.0)
        if aided and (in_n * in_n + in_e * in_e) > EV_GATE_SIGMA**2 * var:
            return  # rejected by the innovation gate
        if not aided:
            # First vision after a gap: EKF2 resets horizontal position to the new aiding source.
            self.n_m, self.e_m = v.n_m, v.e_m
            self.reset_counter = (self.reset_counter + 1) % 256
        else:
            k = min(0.5, max(0.02, 0.2 * (0.1 / std) ** 2))
            self.n_m += k * in_n
            self.e_m += k * in_e
            if 0.0 < dt_since < 1.0:
                self.vn_m_s += 0.3 * k * in_n / max(dt_since, 0.02)
                self.ve_m_s += 0.3 * k * in_e / max(dt_since, 0.02)
        if v.vel_ned_m_s is not None:
            self.vn_m_s += 0.3 * (v.vel_ned_m_s[0] - self.vn_m_s)
            self.ve_m_s += 0.3 * (v.vel_ned_m_s[1] - self.ve_m_s)
        self.t_last_h_aid_s = v.t_s
        self.origin_valid = self.origin_valid or self.gps_checks_passed
        self._eph_at_aid_m = max(0.05, std)
