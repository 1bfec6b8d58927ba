"""The formation law: the paper's decoupled PID on the offset error, made to work on PX4 with and without GPS.

Geometry. The desired slot comes from ``FormationConfig.offset_cam_m``: the leader's position in a *level*
camera frame (x right, y down, z forward; the camera's mount tilt is not applied), i.e. ``forward = z``,
``right = x``, ``down = y`` in the follower's heading frame. Yaw keeps the leader at the slot's bearing
(centred in the image for the default slot), so the horizontal slot is the point on the current line of
sight at the slot's range: the translational error is radial (``e_r = range - slot_range``) plus vertical
(``e_z``), and the lateral error is the yaw loop's job. The two loops never fight over the same error.

Two outputs share that error:

* :meth:`FormationLaw.velocity` (GPS healthy): ``v = ff * v_leader + (kp e_r + kd de_r/dt + I_r) u_los``
  horizontally and ``ff * v_leader_z + kp_z e_z + I_z`` vertically, with ``v_leader = v_follower + v_rel``
  and the derivative taken from the tracker's filtered relative velocity (not a finite difference of noisy
  positions). PX4's velocity loop does the rest. Sent as a body-frame velocity with a yaw *rate*, so the
  leader's bearing rate is fed forward.
* :meth:`FormationLaw.attitude` (GPS lost): the same outer PI gives a desired *relative* velocity; an inner
  loop turns the relative-velocity error into an acceleration, hence a tilt, and a vertical-speed loop on the
  baro-aided vertical speed gives the thrust. Nothing here reads PX4's horizontal position or velocity,
  which are invalid without GPS.

Every output goes through :mod:`companion.mission.safety` last, in this order of precedence: the altitude
band (the ground is harder than the leader), the geofence, the separation barrier, then acceleration and
speed limits. An input or an output that is not finite (NaN, infinity) is never flown: the law forgets its
history and commands a hover instead (``non_finite`` counts it). The slot's geometry is
:mod:`companion.mission.geometry`; passing the depth guard's obstacle, :mod:`companion.mission.static_pass`.
"""

from __future__ import annotations

import math

import numpy as np

from companion.config import FormationConfig
from companion.kernel.flight import AttitudeSetpoint, Vec3T, VelocityBodySetpoint, VelocityNedSetpoint
from companion.kernel.frames import Vec3, heading_to_ned, ned_to_heading, wrap_pi
from companion.mission.formation_commands import (
    NO_ERROR,
    AttitudeCommand,
    VelocityCommand,
    all_finite,
    bounded_velocity,
    clamp_norm,
    integrate,
    low_passed_rate,
    ned_with_feedforward,
    slewed,
)
from companion.mission.geometry import (
    FollowerState,
    Slot,
    SlotError,
    accel_from_tilt,
    accel_lead,
    slot_error,
    tilt_from_accel,
    trail_velocity,
)
from companion.mission.join import JoinReference, joined
from companion.mission.plan_slot import NeighbourNow, SlotTarget, slot_velocity
from companion.mission.safety import (
    SafetyLimits,
    altitude_limit,
    clamp_horizontal_accel,
    clamp_speed,
    separation_limit_accel,
)
from companion.mission.thrust import ThrustController

#: A gap between two law updates longer than this restarts the integrators and the slew (s).
MAX_DT_S = 0.5
#: The first command after :meth:`FormationLaw.seed_velocity` slews from the seeded velocity over this
#: long (one control period at the default 20 Hz): without it the first command of FOLLOW jumped straight
#: to the full PID output, and the vehicle pitched past 40 deg and lost the leader from view (s).
FIRST_SLEW_DT_S = 0.05


class FormationLaw:
    """The PID formation law with its integrators, slew state and thrust controller.

    Call :meth:`reset` whenever the law stops being used (another state took over), so integrators never
    carry over a stale history.
    """

    #: Inner loop of the attitude law: relative-velocity error -> acceleration (1/s), like PX4's
    #: MPC_XY_VEL_P_ACC.
    KV_XY_1_S = 1.8
    #: Its integral, in the heading frame (1/s^2): the acceleration a steady turn needs is constant there.
    KI_V_XY_1_S2 = 0.6
    I_ACC_LIMIT_M_S2 = 3.0
    #: An absolute yaw setpoint makes PX4 turn at MC_YAW_P (2.8/s) times the error, so a setpoint this far
    #: ahead of the desired yaw in time turns at the desired rate (1 / MC_YAW_P, s).
    YAW_LEAD_S = 1.0 / 2.8

    def __init__(self, cfg: FormationConfig, limits: SafetyLimits, hover_thrust_norm: float = 0.5) -> None:
        self.cfg = cfg
        self.limits = limits
        self.slot = Slot.from_offset_cam(cfg.offset_cam_m)
        self.thrust = ThrustController(hover_thrust_norm)
        self._last_s: float | None = None
        self._i_range_m_s = 0.0
        self._i_down_m_s = 0.0
        self._i_acc_heading = np.zeros(2)
        self._v_prev: Vec3 | None = None
        self._v_leader_prev: Vec3 | None = None
        self._a_leader = np.zeros(3)
        #: The other followers relative to this one now (formations), set by the machine every step; the
        #: separation barrier holds against each.
        self.neighbours: list[NeighbourNow] = []
        self._v_slot_prev: Vec3 | None = None
        self._a_slot = np.zeros(3)
        #: Outputs replaced by a hover because they were not finite.
        self.non_finite = 0

    def reset(self) -> None:
        """Forget integrators and slew history (the hover-thrust estimate is a vehicle property: kept)."""
        self._last_s = None
        self._i_range_m_s = 0.0
        self._i_down_m_s = 0.0
        self._i_acc_heading = np.zeros(2)
        self._v_prev = None
        self._v_leader_prev = None
        self._a_leader = np.zeros(3)
        self._v_slot_prev = None
        self._a_slot = np.zeros(3)

    def _leader_accel(self, v_leader: Vec3 | None, dt: float, a_track: Vec3T | Vec3 | None = None) -> Vec3:
        """The leader's acceleration, bounded by the law's acceleration cap.

        The tracker's estimate ``a_track`` where it has one (``tracker.leader_accel_filter``), else the
        low-passed derivative of the leader's estimated velocity.
        """
        limit = self.cfg.max_accel_m_s2
        if a_track is not None:
            self._a_leader = clamp_norm(np.array(a_track, dtype=np.float64), limit)
            self._v_leader_prev = None if v_leader is None else np.array(v_leader, dtype=np.float64)
            return self._a_leader
        if v_leader is None:
            self._v_leader_prev = None
            self._a_leader = np.zeros(3)
            return self._a_leader
        if self._v_leader_prev is not None and dt > 0.0:
            self._a_leader = low_passed_rate(
                self._a_leader,
                v_leader,
                self._v_leader_prev,
                dt,
                tau_s=self.cfg.leader_accel_tau_s,
                limit=limit,
            )
        self._v_leader_prev = np.array(v_leader, dtype=np.float64)
        return self._a_leader

    @property
    def leader_accel_ned_m_s2(self) -> Vec3:
        """The law's current estimate of the leader's acceleration (NED, m/s^2; zero when unknown)."""
        return self._a_leader

    def seed_velocity(self, v_ned_m_s: Vec3 | None) -> None:
        """Start the acceleration slew from the vehicle's current velocity, not from zero."""
        self._v_prev = None if v_ned_m_s is None else np.array(v_ned_m_s, dtype=np.float64)

    def _dt(self, now_s: float) -> float:
        last, self._last_s = self._last_s, now_s
        if last is None or not 0.0 < now_s - last <= MAX_DT_S:
            self._i_range_m_s = 0.0
            self._i_down_m_s = 0.0
            self._i_acc_heading = np.zeros(2)
            return 0.0
        return now_s - last

    def _yaw_rate(self, err: SlotError, yaw_rad: float) -> float:
        max_rate = math.radians(self.cfg.max_yaw_rate_deg_s)
        rate = self.cfg.kp_yaw * wrap_pi(err.yaw_des_rad - yaw_rad) + err.bearing_rate_rad_s
        return float(np.clip(rate, -max_rate, max_rate))

    def velocity(
        self,
        p_ned_rel_m: Vec3,
        v_ned_rel_m_s: Vec3,
        follower: FollowerState,
        now_s: float,
        *,
        a_leader_ned_m_s2: Vec3T | Vec3 | None = None,
        obstacle_ned_m: Vec3 | None = None,
        slew_m_s2: float | None = None,
        coasting: bool = False,
        slot_target: SlotTarget | None = None,
        v_leader_ned_m_s: Vec3 | None = None,
        kp_range_1_s: float | None = None,
        join: JoinReference | None = None,
    ) -> VelocityCommand:
        """The GPS-healthy law: a body velocity and yaw rate that hold the slot (see module doc).

        ``a_leader_ned_m_s2``: the tracker's estimate of the leader's acceleration (NED, m/s^2), if it
        makes one; otherwise the law differentiates the leader's velocity. ``obstacle_ned_m``: the depth
        guard's nearest thing ahead (relative NED, m), held off like the leader but taken as static.
        ``slew_m_s2``: how fast the command may change (default ``command_slew_m_s2``). ``coasting``: the
        track has no detection now (the lead is dropped unless ``accel_lead_while_coasting``).
        ``slot_target``: a formation plan's slot turned with the leader; the error across the line of sight
        to it is flown out too, and the slot's own motion fed forward. ``v_leader_ned_m_s``: the leader's
        own velocity where it shares one (GPS on both ends: steadier than the camera's at the range of an
        outer slot, and unbroken while the detector misses it); default: ours plus the estimate's relative.
        ``kp_range_1_s``: the range gain (default ``kp_xy``). ``join``: the planned approach's reference
        (:mod:`companion.mission.join`): the error is flown to it, its motion fed forward.
        """
        if not all_finite(
            p_ned_rel_m,
            v_ned_rel_m_s,
            follower.yaw_rad,
            follower.v_ned_m_s,
            follower.p_ned_m,
            a_leader_ned_m_s2,
            obstacle_ned_m,
            slew_m_s2,
            slot_target,
            v_leader_ned_m_s,
            self.neighbours,
        ):
            self._non_finite()
            return VelocityCommand(self.hover_velocity(), (0.0, 0.0, 0.0), 0.0, NO_ERROR)
        dt = self._dt(now_s)
        cfg, lim = self.cfg, self.limits
        err = slot_error(self.slot, p_ned_rel_m, v_ned_rel_m_s, follower.yaw_rad)
        err, ff_join = (err, None) if join is None else joined(err, join, self.cfg.leader_accel_ff_s)
        v_rel = np.asarray(v_ned_rel_m_s, dtype=np.float64)
        v_leader: Vec3 | None
        if v_leader_ned_m_s is not None:
            v_leader = np.asarray(v_leader_ned_m_s, dtype=np.float64)
        elif follower.v_ned_m_s is not None:
            v_leader = np.asarray(follower.v_ned_m_s) + v_rel
        else:
            v_leader = None
        a_leader = self._leader_accel(v_leader, dt, a_leader_ned_m_s2)
        if coasting and not cfg.accel_lead_while_coasting:
            a_leader = np.zeros(3)
        if v_leader is None:
            ff = np.zeros(3)
        else:
            ff = cfg.leader_velocity_ff * v_leader
            ff[:2] += accel_lead(a_leader[:2], err, cfg)
            ff[2] += cfg.leader_accel_ff_z_s * a_leader[2]

        kp = cfg.kp_xy if kp_range_1_s is None else kp_range_1_s
        v_range = kp * err.e_range_m + cfg.kd_xy * err.e_range_rate_m_s + self._i_range_m_s
        v_down = cfg.kp_z * err.e_down_m + self._i_down_m_s
        raw = ff + v_range * err.u_los + np.array([0.0, 0.0, v_down])
        if ff_join is not None:
            raw += ff_join
        if slot_target is not None:
            raw += slot_velocity(
                np.asarray(p_ned_rel_m, dtype=np.float64), err.u_los, slot_target, cfg.kp_slot_1_s
            )
            raw[:2] += cfg.slot_accel_ff_s * self._slot_accel(slot_target, dt)[:2]
        else:
            self._v_slot_prev = None
            if v_leader is not None and join is None:
                raw += trail_velocity(err, err.e_range_m + self.slot.range_h_m, v_leader, cfg)

        v = clamp_speed(raw, lim)
        if self._v_prev is not None:
            step_s = dt if dt > 0.0 else FIRST_SLEW_DT_S
            slew_h = cfg.command_slew_m_s2 if slew_m_s2 is None else slew_m_s2
            v = slewed(v, self._v_prev, step_s, slew_h, cfg.command_slew_m_s2)
        p = np.asarray(p_ned_rel_m, dtype=np.float64)
        v = bounded_velocity(v, p, v_leader, follower, self.limits, self.neighbours, obstacle_ned_m)
        # Separation wins over max speed: a leader rushing at us may push the command past it.
        self._v_prev = v

        # Anti-windup: hold an integral while the output is cut in the direction it would push.
        cut_h = float(np.dot(raw - v, err.u_los))
        cut_z = float(raw[2] - v[2])
        self._i_range_m_s = integrate(
            self._i_range_m_s, cfg.ki_xy * err.e_range_m, dt, cfg.i_limit_xy_m_s, cut_h * err.e_range_m > 1e-3
        )
        self._i_down_m_s = integrate(
            self._i_down_m_s, cfg.ki_z * err.e_down_m, dt, cfg.i_limit_z_m_s, cut_z * err.e_down_m > 1e-3
        )

        yaw_rate = self._yaw_rate(err, follower.yaw_rad)
        v_body = ned_to_heading(v, follower.yaw_rad)
        if not (np.all(np.isfinite(v_body)) and math.isfinite(yaw_rate)):
            self._non_finite()
            v = v_body = np.zeros(3)
            yaw_rate = 0.0
        sp: VelocityBodySetpoint | VelocityNedSetpoint
        if cfg.acceleration_feedforward:
            sp = ned_with_feedforward(v, a_leader, follower, yaw_rate * self.YAW_LEAD_S, cfg.max_accel_m_s2)
        else:
            sp = VelocityBodySetpoint(
                v_body_m_s=(float(v_body[0]), float(v_body[1]), float(v_body[2])), yaw_rate_rad_s=yaw_rate
            )
        return VelocityCommand(sp, (float(v[0]), float(v[1]), float(v[2])), yaw_rate, err)

    def _non_finite(self) -> None:
        """A NaN or infinity reached an output: drop every history it may have poisoned."""
        self.non_finite += 1
        self.reset()

    def _finite_attitude(self, sp: AttitudeSetpoint, yaw_rad: float) -> AttitudeSetpoint:
        """``sp``, or level at the hover thrust when any of it is not finite."""
        if all(math.isfinite(x) for x in (sp.roll_rad, sp.pitch_rad, sp.yaw_rad, sp.thrust_norm)):
            return sp
        return self._level(yaw_rad)

    def _level(self, yaw_rad: float) -> AttitudeSetpoint:
        """Level at the hover thrust (a non-finite input or output): forget the histories it touched."""
        self._non_finite()
        hover = self.thrust.hover_thrust_norm
        if not math.isfinite(hover):
            self.thrust.hover_thrust_norm = hover = 0.5
        return AttitudeSetpoint(
            roll_rad=0.0,
            pitch_rad=0.0,
            yaw_rad=yaw_rad if math.isfinite(yaw_rad) else 0.0,
            thrust_norm=float(np.clip(hover, 0.0, 1.0)),
        )

    def _slot_accel(self, target: SlotTarget, dt: float) -> Vec3:
        """The slot's own acceleration as the follower sees it (low-passed derivative), m/s^2.

        Fed forward as a velocity lead, as the leader's is: PX4's velocity loop lags a turning slot as it
        lags an accelerating leader.
        """
        v = -np.asarray(target.v_ned_rel_m_s, dtype=np.float64)
        if self._v_slot_prev is not None and dt > 0.0:
            cfg = self.cfg
            self._a_slot = low_passed_rate(
                self._a_slot, v, self._v_slot_prev, dt, tau_s=cfg.leader_accel_tau_s, limit=cfg.max_accel_m_s2
            )
        self._v_slot_prev = v
        return self._a_slot

    def attitude(
        self,
        p_ned_rel_m: Vec3,
        v_ned_rel_m_s: Vec3,
        follower: FollowerState,
        now_s: float,
        *,
        slot_target: SlotTarget | None = None,
    ) -> AttitudeCommand:
        """The GPS-lost law: attitude and thrust from the relative estimate and the baro (see module doc)."""
        if not all_finite(p_ned_rel_m, v_ned_rel_m_s, follower, slot_target, self.neighbours):
            return AttitudeCommand(self._level(follower.yaw_rad), (0.0, 0.0, 0.0), 0.0, None)
        dt = self._dt(now_s)
        cfg, lim = self.cfg, self.limits
        p = np.asarray(p_ned_rel_m, dtype=np.float64)
        v_rel = np.asarray(v_ned_rel_m_s, dtype=np.float64)
        err = slot_error(self.slot, p, v_rel, follower.yaw_rad)

        # Outer loop: the relative velocity we want (radial only; tangential relative motion is unwanted).
        v_rel_des = -(cfg.kp_xy_attitude * err.e_range_m + self._i_range_m_s) * err.u_los
        if slot_target is not None:
            # The follower's velocity for the slot is minus the relative velocity it needs.
            v_rel_des = v_rel_des - slot_velocity(p, err.u_los, slot_target, cfg.kp_slot_1_s)
        dv = v_rel - v_rel_des
        dv[2] = 0.0
        dv_h = ned_to_heading(dv, follower.yaw_rad)
        if dt == 0.0:  # start from the tilt flown now (from level, 2 m/s on SIH's drag fell 0.6 m behind)
            a_now = np.asarray(accel_from_tilt(follower.roll_rad, follower.pitch_rad))
            self._i_acc_heading = clamp_norm(a_now, self.I_ACC_LIMIT_M_S2)
        a_h = self.KV_XY_1_S * dv_h[:2] + self._i_acc_heading
        a = heading_to_ned(np.array([a_h[0], a_h[1], 0.0]), follower.yaw_rad)
        a_max = min(cfg.max_accel_m_s2, lim.max_horizontal_accel_m_s2)
        raw_a = a.copy()
        h = math.hypot(a[0], a[1])
        if h > a_max:
            a[:2] *= a_max / h
        a = separation_limit_accel(a, p, v_rel, lim)
        for n in self.neighbours:
            a = separation_limit_accel(a, n.p_ned_rel_m, n.v_ned_rel_m_s, lim)
        a = clamp_horizontal_accel(a, lim)
        saturated = float(np.linalg.norm(raw_a - a)) > 1e-3

        # Vertical: follow the leader's height with the baro-aided vertical speed.
        v_leader_down = follower.v_down_m_s + float(v_rel[2])
        v_down_des = cfg.leader_velocity_ff * v_leader_down + cfg.kp_z * err.e_down_m + self._i_down_m_s
        v_down_des = float(np.clip(v_down_des, -lim.max_vertical_speed_m_s, lim.max_vertical_speed_m_s))
        v_down_des = altitude_limit(v_down_des, follower.alt_rel_m, lim)

        if dt > 0.0:
            if not saturated:
                self._i_acc_heading = np.clip(
                    self._i_acc_heading + self.KI_V_XY_1_S2 * dv_h[:2] * dt,
                    -self.I_ACC_LIMIT_M_S2,
                    self.I_ACC_LIMIT_M_S2,
                )
            self._i_range_m_s = integrate(
                self._i_range_m_s, cfg.ki_xy * err.e_range_m, dt, cfg.i_limit_xy_m_s, saturated
            )
            self._i_down_m_s = integrate(
                self._i_down_m_s, cfg.ki_z * err.e_down_m, dt, cfg.i_limit_z_m_s, False
            )

        roll, pitch = tilt_from_accel(a, follower.yaw_rad)
        thrust = self.thrust.thrust(v_down_des, follower.v_down_m_s, roll, pitch, dt)
        yaw_sp = self._attitude_yaw(err, follower.yaw_rad)
        sp = AttitudeSetpoint(roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw_sp, thrust_norm=thrust)
        sp = self._finite_attitude(sp, follower.yaw_rad)
        return AttitudeCommand(sp, (float(a[0]), float(a[1]), float(a[2])), v_down_des, err)

    def _attitude_yaw(self, err: SlotError, yaw_rad: float) -> float:
        """Absolute yaw setpoint: the desired yaw plus a lead, never more than a bounded step away."""
        target = err.yaw_des_rad + err.bearing_rate_rad_s * self.YAW_LEAD_S
        step_max = math.radians(self.cfg.max_yaw_rate_deg_s) / max(self.cfg.kp_yaw, 1e-3)
        step = float(np.clip(wrap_pi(target - yaw_rad), -step_max, step_max))
        return wrap_pi(yaw_rad + step)

    def hover_attitude(
        self,
        follower: FollowerState,
        v_down_des_m_s: float,
        now_s: float,
        *,
        yaw_rate_rad_s: float = 0.0,
        p_ned_rel_m: Vec3 | None = None,
        v_ned_rel_m_s: Vec3 | None = None,
    ) -> AttitudeCommand:
        """Level-ish attitude at a commanded vertical speed, for hovering, scanning and landing without GPS.

        Brakes on PX4's velocity estimate while it is still valid (``follower.v_ned_m_s`` not None),
        otherwise stays level. Keeps the separation barrier when a relative estimate is given.
        """
        if not all_finite(
            follower, v_down_des_m_s, yaw_rate_rad_s, p_ned_rel_m, v_ned_rel_m_s, self.neighbours
        ):
            return AttitudeCommand(self._level(follower.yaw_rad), (0.0, 0.0, 0.0), 0.0, None)
        dt = self._dt(now_s)
        lim = self.limits
        a = np.zeros(3)
        if follower.v_ned_m_s is not None:
            v = np.asarray(follower.v_ned_m_s, dtype=np.float64)
            a[:2] = -self.KV_XY_1_S * v[:2]
        if p_ned_rel_m is not None and v_ned_rel_m_s is not None:
            a = separation_limit_accel(a, np.asarray(p_ned_rel_m), np.asarray(v_ned_rel_m_s), lim)
        for n in self.neighbours:
            a = separation_limit_accel(a, n.p_ned_rel_m, n.v_ned_rel_m_s, lim)
        a_max = min(self.cfg.max_accel_m_s2, lim.max_horizontal_accel_m_s2) * 0.5
        h = math.hypot(a[0], a[1])
        if h > a_max:
            a[:2] *= a_max / h
        roll, pitch = tilt_from_accel(a, follower.yaw_rad)
        thrust = self.thrust.thrust(v_down_des_m_s, follower.v_down_m_s, roll, pitch, dt)
        yaw_sp = wrap_pi(follower.yaw_rad + yaw_rate_rad_s * self.YAW_LEAD_S)
        sp = AttitudeSetpoint(roll_rad=roll, pitch_rad=pitch, yaw_rad=yaw_sp, thrust_norm=thrust)
        sp = self._finite_attitude(sp, follower.yaw_rad)
        return AttitudeCommand(sp, (float(a[0]), float(a[1]), float(a[2])), v_down_des_m_s, None)

    def coast_velocity(
        self,
        v_leader_ned_m_s: Vec3,
        p_ned_rel_m: Vec3,
        follower: FollowerState,
        obstacle_ned_m: Vec3 | None = None,
        v_station_ned_m_s: Vec3T = (0.0, 0.0, 0.0),
    ) -> VelocityBodySetpoint:
        """Coast with the leader unseen (GPS healthy): its last velocity, level, no closing on its guess.

        The camera is kept on the leader's dead-reckoned bearing. The dead-reckoned leader flies straight
        on while a real one may turn: closing on it brought a follower from 4.4 m to 1.7 m of a circling
        leader in 1.5 s (network circle runs). The separation barrier still applies against the
        dead-reckoned position. ``v_station_ned_m_s``: added to hold a station (NED, m/s; horizontal).
        """
        if not all_finite(
            v_station_ned_m_s,
            v_leader_ned_m_s,
            p_ned_rel_m,
            follower.yaw_rad,
            follower.v_ned_m_s,
            follower.p_ned_m,
            obstacle_ned_m,
            self.neighbours,
        ):
            self._non_finite()
            return self.hover_velocity()
        lim = self.limits
        p = np.asarray(p_ned_rel_m, dtype=np.float64)
        v_leader = np.asarray(v_leader_ned_m_s, dtype=np.float64)
        level = clamp_speed(
            np.array([v_leader[0] + v_station_ned_m_s[0], v_leader[1] + v_station_ned_m_s[1], 0.0]), lim
        )
        v = bounded_velocity(level, p, v_leader, follower, lim, self.neighbours, obstacle_ned_m)
        v_rel = v_leader - (np.zeros(3) if follower.v_ned_m_s is None else np.asarray(follower.v_ned_m_s))
        yaw_rate = self._yaw_rate(slot_error(self.slot, p, v_rel, follower.yaw_rad), follower.yaw_rad)
        v_body = ned_to_heading(v, follower.yaw_rad)
        if not (np.all(np.isfinite(v_body)) and math.isfinite(yaw_rate)):
            self._non_finite()
            return self.hover_velocity()
        return VelocityBodySetpoint(
            v_body_m_s=(float(v_body[0]), float(v_body[1]), float(v_body[2])), yaw_rate_rad_s=yaw_rate
        )

    def hover_velocity(self, v_down_m_s: float = 0.0, yaw_rate_rad_s: float = 0.0) -> VelocityBodySetpoint:
        """Stop in place (GPS healthy): zero horizontal velocity, a vertical speed and a yaw rate."""
        if not (math.isfinite(v_down_m_s) and math.isfinite(yaw_rate_rad_s)):
            self.non_finite += 1
            v_down_m_s = yaw_rate_rad_s = 0.0
        return VelocityBodySetpoint(v_body_m_s=(0.0, 0.0, v_down_m_s), yaw_rate_rad_s=yaw_rate_rad_s)
