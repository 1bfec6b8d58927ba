"""REACQUIRE and HOVER: the leader lost or its estimate stale, in the air.

REACQUIRE coasts on the leader's last velocity (GPS healthy; a leader lost hovering: the follower holds
where it was; the leader's own velocity while fresh shares carry one), then scans in yaw toward where it
was last seen (or looks where the leader's fresh shares put it), and takes the leader again on a steady
track, or sooner on a confirmed one where the leader was lost; HOVER holds on the vehicle's own telemetry
while perception stalls. Both abort after their timeouts (``reacquire_coast_s + reacquire_scan_s``,
``stall_hover_s``).
"""

from __future__ import annotations

import math

import numpy as np

from companion.estimation.leader import TrackStatus
from companion.kernel.flight import Setpoint, Vec3T, VehicleState
from companion.kernel.frames import Vec3, wrap_pi
from companion.mission.formation_commands import clamp_norm
from companion.mission.shared_motion import shared_rel_now
from companion.mission.states.context import MissionContext
from companion.mission.states.request import PhaseStep, abort, enter_follow, go, moving, reacquire
from companion.mission.types import MissionInputs, MissionState, Reason

#: Altitude-hold gain of the attitude hover (1/s).
ALT_HOLD_KP_1_S = 0.8
#: Station keeping while coasting on a leader lost hovering: gain (1/s) and speed cap (m/s).
STATION_KP_1_S = 1.0
STATION_MAX_M_S = 0.5
#: A confirmed track this close to the dead-reckoned leader while coasting is the leader again, without
#: waiting for ``reacquire_min_track_s`` (m): a hovering leader found again after a short miss was left
#: to start off while the follower waited out the age. Tight: false boxes beside a leader lost against a
#: tree crown sat 0.9 m from where it was lost.
FOUND_WHERE_LOST_M = 0.5
#: A leader lost at a slower horizontal speed than this is taken as hovering (m/s): a hovering leader's
#: estimated velocity is 0.1-0.2 m/s of noise, a flying one's the 2-3 m/s it flies.
HOVERING_LEADER_M_S = 0.5


class RecoveryPhase:
    """The handlers of REACQUIRE and HOVER."""

    def __init__(self, ctx: MissionContext) -> None:
        self.c = ctx
        #: REACQUIRE and HOVER fly attitude setpoints (decided on entry: no GPS, or vision on attitude).
        self.attitude_kind = False
        #: Where the lost leader dead-reckons from, and at what velocity (local NED, m and m/s): the coast.
        self.leader_lost_p_ned_m: Vec3 | None = None
        self.leader_lost_v_ned_m_s: Vec3 | None = None
        #: Where the follower was when it lost a hovering leader: REACQUIRE's coast holds it (local NED, m).
        self.hold_p_ned_m: Vec3 | None = None
        #: The yaw scan's direction: toward the side the leader was last seen on (+1 right, -1 left).
        self.scan_sign = 1.0
        #: The height the attitude hover holds (above home, m; NaN: taken on the first tick).
        self.alt_hold_m = math.nan

    def remember_loss(self, inp: MissionInputs, *, attitude: bool) -> None:
        """Leader lost, entering REACQUIRE: where it was going (coast) and which way to scan.

        ``attitude``: the flight on entry uses attitude setpoints (no GPS, or vision on attitude).
        """
        veh = inp.vehicle
        self.attitude_kind = attitude
        # A track dropped as far-field was never the leader: search from here, without coasting toward it.
        far = inp.leader is not None and inp.leader.far_field
        last = None if far else self.c.last_leader
        if last is not None:
            p_rel, v_rel = np.array(last.p_ned_rel_m), np.array(last.v_ned_rel_m_s)
            age = max(0.0, self.c.now_s - last.stamp_s)
            motion = self.c.leader_motion
            v_leader = np.array(veh.v_ned_m_s) + v_rel if motion is None else motion.v_ned_m_s.copy()
            if motion is None and math.hypot(v_leader[0], v_leader[1]) < HOVERING_LEADER_M_S:
                # Its estimated velocity is noise: coasting on it flew the follower away from its slot.
                v_leader = np.zeros(3)
                self.hold_p_ned_m = np.array(veh.p_ned_m)
            else:
                self.hold_p_ned_m = None
            # p_rel is from the estimate's stamp: the leader moved by its velocity since, we by ours.
            p_rel_now = p_rel + (v_leader - np.array(veh.v_ned_m_s)) * age
            self.leader_lost_p_ned_m = np.array(veh.p_ned_m) + p_rel_now
            self.leader_lost_v_ned_m_s = v_leader
            bearing = math.atan2(p_rel[1], p_rel[0])
            self.scan_sign = 1.0 if wrap_pi(bearing - veh.yaw_rad) >= 0.0 else -1.0
        else:
            self.leader_lost_p_ned_m = None
            self.leader_lost_v_ned_m_s = None
            self.hold_p_ned_m = None
            self.scan_sign = 1.0
        self.alt_hold_m = veh.alt_rel_m

    def remember_hover(self, inp: MissionInputs, *, attitude: bool) -> None:
        """The estimate went stale, entering HOVER: hover on the vehicle's own telemetry."""
        self.attitude_kind = attitude
        self.alt_hold_m = inp.vehicle.alt_rel_m

    def reacquire(self, inp: MissionInputs) -> PhaseStep:
        veh = inp.vehicle
        if self.c.tracked(inp, confirmed_only=True) and (
            self.c.track.steady(inp.leader) or self._found_where_lost(inp)
        ):
            return moving(enter_follow(Reason.LEADER_REACQUIRED))
        if not self.attitude_kind and not self.c.gps.ok:
            return moving(go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "while re-acquiring"))
        t = self.c.t_in_state()
        if t > self.c.m.reacquire_coast_s + self.c.m.reacquire_scan_s:
            return moving(abort(Reason.REACQUIRE_TIMEOUT))
        scanning = t > self.c.m.reacquire_coast_s
        scan_rate = self.scan_sign * math.radians(self.c.m.scan_yaw_rate_deg_s) if scanning else 0.0
        candidate = self.c.track.candidate_rel(inp.leader, self.c.now_s)
        shared = self._shared_leader_rel(inp)
        if candidate is not None and scanning:
            # Look at what the tracker has found, not yet steady, so it stays in view while it proves
            # itself; never fly toward it (a phantom must not pull the follower).
            scan_rate = self._look_rate(candidate, veh.yaw_rad)
        elif shared is not None and scanning:
            # The leader says where it is: look there instead of sweeping the horizon.
            scan_rate = self._look_rate(shared, veh.yaw_rad)
        if self.attitude_kind:
            fol = self.c.follower(veh, velocity_valid=False)
            v_down = self._alt_hold_v_down(veh)
            return PhaseStep(
                self.c.law.hover_attitude(fol, v_down, self.c.now_s, yaw_rate_rad_s=scan_rate).setpoint
            )
        if not scanning and self.leader_lost_p_ned_m is not None and self.leader_lost_v_ned_m_s is not None:
            return PhaseStep(self._coast(inp, t, candidate))
        return PhaseStep(self.c.law.hover_velocity(yaw_rate_rad_s=scan_rate))

    def _coast(self, inp: MissionInputs, t: float, candidate: Vec3 | None) -> Setpoint:
        """Coast: the leader's last velocity, looking where it dead-reckons to (GPS is healthy).

        Without closing on that guess (see FormationLaw.coast_velocity); looking at a candidate instead
        when there is one, which the separation barrier then also holds off.
        """
        lost_p, lost_v = self.leader_lost_p_ned_m, self.leader_lost_v_ned_m_s
        if lost_p is None or lost_v is None:  # pragma: no cover - the caller checked
            return self.c.law.hover_velocity()
        veh = inp.vehicle
        p_leader = lost_p + lost_v * t
        motion = self.c.leader_motion
        if motion is not None:
            # The leader's own velocity as it shares it: the dead reckoning goes on from here at it.
            lost_v = motion.v_ned_m_s.copy()
            self.leader_lost_v_ned_m_s = lost_v
            self.leader_lost_p_ned_m = p_leader - motion.v_ned_m_s * t
            self.hold_p_ned_m = None
        p_rel = p_leader - np.array(veh.p_ned_m) if candidate is None else candidate
        return self.c.law.coast_velocity(
            lost_v,
            p_rel,
            self.c.follower(veh, velocity_valid=True),
            self.c.obstacle_now(inp),
            v_station_ned_m_s=self._station_velocity(veh),
        )

    def _station_velocity(self, veh: VehicleState) -> Vec3T:
        """Back to where the follower lost a hovering leader (NED, m/s, horizontal); zero otherwise."""
        if self.hold_p_ned_m is None:
            return (0.0, 0.0, 0.0)
        e = self.hold_p_ned_m - np.array(veh.p_ned_m)
        v = clamp_norm(STATION_KP_1_S * np.array([e[0], e[1], 0.0]), STATION_MAX_M_S)
        return (float(v[0]), float(v[1]), 0.0)

    def _shared_leader_rel(self, inp: MissionInputs) -> Vec3 | None:
        """Where the leader's fresh shares put it now, relative to the follower (NED, m; GPS healthy)."""
        sh, motion = inp.leader_shared, self.c.leader_motion
        if sh is None or motion is None or not self.c.gps.ok:
            return None
        return shared_rel_now(sh, motion, inp.vehicle, self.c.now_s)

    def _found_where_lost(self, inp: MissionInputs) -> bool:
        """Whether the track is where the lost leader dead-reckons to (coasting, GPS healthy)."""
        lost_p, lost_v, est = self.leader_lost_p_ned_m, self.leader_lost_v_ned_m_s, inp.leader
        t = self.c.t_in_state()
        if lost_p is None or lost_v is None or est is None or self.attitude_kind or not self.c.gps.ok:
            return False
        if t > self.c.m.reacquire_coast_s:
            return False
        p_found = np.array(inp.vehicle.p_ned_m) + np.array(est.p_ned_rel_m)
        return float(np.linalg.norm(p_found - (lost_p + lost_v * t))) < FOUND_WHERE_LOST_M

    def _look_rate(self, p_rel_ned_m: Vec3, yaw_rad: float) -> float:
        """A yaw rate that turns the camera onto a relative position, bounded by the scan rate, rad/s."""
        bearing = math.atan2(p_rel_ned_m[1], p_rel_ned_m[0])
        max_rate = math.radians(self.c.m.scan_yaw_rate_deg_s)
        return float(np.clip(self.c.cfg.formation.kp_yaw * wrap_pi(bearing - yaw_rad), -max_rate, max_rate))

    def _alt_hold_v_down(self, veh: VehicleState) -> float:
        if not math.isfinite(self.alt_hold_m):
            self.alt_hold_m = veh.alt_rel_m
        v = ALT_HOLD_KP_1_S * (veh.alt_rel_m - self.alt_hold_m)
        lim = self.c.limits.max_vertical_speed_m_s
        return float(np.clip(v, -lim, lim))

    def hover(self, inp: MissionInputs) -> PhaseStep:
        veh = inp.vehicle
        est = inp.leader
        if self.c.fresh(est) and est is not None:
            if est.usable:
                return moving(enter_follow(Reason.PERCEPTION_RESUMED))
            if est.status == TrackStatus.LOST:
                return moving(reacquire("after stall"))
        if not self.attitude_kind and not self.c.gps.ok:
            return moving(go(MissionState.CONTROLLED_LANDING, Reason.GPS_LOST, "while hovering"))
        if self.c.t_in_state() > self.c.m.stall_hover_s:
            return moving(abort(Reason.STALL_TIMEOUT))
        if self.attitude_kind:
            fol = self.c.follower(veh, velocity_valid=False)
            return PhaseStep(
                self.c.law.hover_attitude(fol, self._alt_hold_v_down(veh), self.c.now_s).setpoint
            )
        return PhaseStep(self.c.law.hover_velocity())
