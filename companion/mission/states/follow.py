"""FOLLOW and FOLLOW_VISION: the formation law flown on the leader estimate, brought to the control instant.

FOLLOW flies velocity setpoints while GPS is healthy. FOLLOW_VISION flies attitude and thrust without GPS,
or velocity again once PX4 has taken the external position fix built from the leader's shared position
(``gps_loss_policy = "vision_external_position"``). A stale estimate goes to HOVER, a lost one to
REACQUIRE (:mod:`companion.mission.states.recovery`).
"""

from __future__ import annotations

import math

import numpy as np

from companion.estimation.leader import LeaderEstimate, TrackStatus
from companion.kernel.flight import ExternalPosition, VehicleState
from companion.kernel.frames import Vec3
from companion.mission.join import JoinPlanner
from companion.mission.plan_slot import SlotTarget, SlotTurner
from companion.mission.shared_motion import SharedRelativeFix, shared_rel_now
from companion.mission.states.context import MissionContext
from companion.mission.states.request import (
    PhaseStep,
    TransitionRequest,
    enter_follow,
    go,
    gps_lost,
    hover,
    moving,
    reacquire,
)
from companion.mission.types import MissionInputs, MissionState, Reason, VisionMode

#: PX4 must report a valid estimate this long before velocity setpoints ride on an external fix, s.
EXTERNAL_PROBATION_S = 1.0
#: A shared leader position older than this is not used, s.
SHARED_STALE_S = 1.0
#: The camera has missed the leader this long before FOLLOW flies on its shares instead, s: the track's
#: coast is sound over a frame or two.
SHARE_FIX_AFTER_S = 0.1
#: PX4's reset counter on the external fix: the fix is never reset in flight.
EXTERNAL_RESET_COUNTER = 0


class FollowPhase:
    """The handlers of FOLLOW and FOLLOW_VISION."""

    def __init__(self, ctx: MissionContext) -> None:
        self.c = ctx
        #: The age of the track flown on at the last tick, s: a younger one is another track.
        self._track_age_s = math.inf
        f = ctx.cfg.formation
        #: The planned approach into the slot, armed on every entry into FOLLOW (planned on its first tick).
        self.join = JoinPlanner(f.join_speed_m_s, f.join_accel_m_s2, f.join_min_error_m)
        #: A formation plan's slot, turned with the leader's shared heading (None: a lone follower).
        slot = f.slot_leader_m
        self.slot_turner = SlotTurner(slot) if slot is not None else None
        #: The shares held to the camera, flown while it misses the leader (``coast_on_shared_position``).
        self.shared_fix = (
            SharedRelativeFix(f.shared_offset_tau_s)
            if f.lead_on_shared_motion and f.coast_on_shared_position
            else None
        )
        #: This tick FOLLOW flew on the shares while the camera missed the leader (the machine clears it).
        self.coasted_on_share = False
        #: How FOLLOW_VISION flies (set on entry, changed as PX4 takes or drops the external fix).
        self.vision_mode: VisionMode | None = None
        #: FOLLOW_VISION's probation of the external fix: since when it is sent and PX4 has called its
        #: position valid, s, and whether it gave up on PX4 taking it.
        self._ext_since: float | None = None
        self._ext_valid_since: float | None = None
        self._ext_gave_up = False

    def start_vision_on_attitude(self) -> None:
        """Entering FOLLOW_VISION: attitude first, the external fix on probation afresh."""
        self.vision_mode = VisionMode.ATTITUDE
        self._reset_external()

    def forget_share_fix(self) -> None:
        """GPS lost: the GPS that comes back may put both ends elsewhere."""
        if self.shared_fix is not None:
            self.shared_fix.reset()

    def _reset_external(self) -> None:
        self._ext_valid_since = None
        self._ext_since = None
        self._ext_gave_up = False

    def _slot_target(self, inp: MissionInputs) -> SlotTarget | None:
        """The plan's slot now (None without a plan or a fresh shared heading of the leader)."""
        if self.slot_turner is None:
            return None
        return self.slot_turner.update(inp.leader_shared, self.c.now_s)

    def _leader_or_transition(self, inp: MissionInputs) -> LeaderEstimate | TransitionRequest:
        """The estimate to fly on, or the request to go to HOVER (stale) or REACQUIRE (lost)."""
        est = inp.leader
        if est is None or not self.c.fresh(est):
            return hover("never" if est is None else f"{self.c.now_s - est.stamp_s:.2f} s old")
        if not est.usable:
            return reacquire("far-field track dropped" if est.far_field else est.status.value)
        return est

    def follow(self, inp: MissionInputs) -> PhaseStep:
        veh = inp.vehicle
        if not self.c.gps.ok:
            return moving(gps_lost())
        est = self._leader_or_transition(inp)
        if isinstance(est, TransitionRequest):
            return moving(est)
        self._on_new_track(est)
        p_rel, v_rel = self.relative_now(est, veh)
        p_rel, v_rel = self._through_misses(inp, est, p_rel, v_rel)
        f = self.c.cfg.formation
        motion = self.c.leader_motion
        steady = self._steady(est)
        slew_fast = steady or (motion is not None and self.c.link.clean(self.c.now_s))
        cmd = self.c.law.velocity(
            p_rel,
            v_rel,
            self.c.follower(veh, velocity_valid=True, airframe=inp.airframe),
            self.c.now_s,
            a_leader_ned_m_s2=est.a_ned_leader_m_s2 if motion is None else motion.a_ned_m_s2,
            obstacle_ned_m=self.c.obstacle_now(inp),
            slew_m_s2=f.command_slew_steady_m_s2 if slew_fast else f.command_slew_m_s2,
            kp_range_1_s=f.kp_xy_steady if steady else f.kp_xy,
            # The shared motion does not stop when the camera misses the leader.
            coasting=est.status == TrackStatus.COASTING and motion is None,
            slot_target=self._slot_target(inp),
            v_leader_ned_m_s=self._shared_leader_velocity(inp) if motion is None else motion.v_ned_m_s,
            join=self.join.reference(self.c.law.slot, p_rel, veh.yaw_rad, self.c.now_s),
        )
        return PhaseStep(cmd.setpoint, None, cmd.error.error_ned_m)

    def _on_new_track(self, est: LeaderEstimate) -> None:
        """Start the law and the join afresh when the tracker moved to another track (a challenger won).

        What the law remembers (the leader's velocity for its acceleration, the integrators) and the join
        planned on entry belong to the track they were built on. On PX4 a false track held through the
        take-off (an object 10 m off) was planned for; when the real leader won 0.6 s into FOLLOW, the
        join's reference still asked for the old track's range and height, and the follower was commanded
        4 m/s backwards from its slot (2.3 m off).
        """
        age_s = est.track_age_s
        if age_s < self._track_age_s and math.isfinite(self._track_age_s):
            self.c.law.reset()
            self.join.arm()
        self._track_age_s = age_s

    def _through_misses(
        self, inp: MissionInputs, est: LeaderEstimate, p_rel: Vec3, v_rel: Vec3
    ) -> tuple[Vec3, Vec3]:
        """The relative position and velocity to fly on (NED, m, m/s, at the setpoint's instant).

        The camera's while it sees the leader; once the camera has missed it for ``SHARE_FIX_AFTER_S``, the
        camera's last relative position carried on at the shares' relative velocity (after a longer gap, the
        shares' position with its offset from the camera: ``SharedRelativeFix``).
        """
        fix, motion, sh = self.shared_fix, self.c.leader_motion, inp.leader_shared
        if fix is None or motion is None or sh is None:
            return p_rel, v_rel
        veh = inp.vehicle
        v_rel_shared = motion.v_ned_m_s - np.asarray(veh.v_ned_m_s)
        rel_shared = shared_rel_now(sh, motion, veh, self.c.now_s) + v_rel_shared * veh.link_delay_or_zero_s
        if est.status == TrackStatus.CONFIRMED:
            fix.observe(p_rel, rel_shared, self.c.now_s)
            return p_rel, v_rel
        if est.stamp_s - est.last_measurement_s < SHARE_FIX_AFTER_S:
            return p_rel, v_rel
        p_fix = fix.fix(rel_shared, v_rel_shared, self.c.now_s)
        if p_fix is None:
            return p_rel, v_rel
        self.coasted_on_share = True
        return p_fix, v_rel_shared

    def _shared_leader_velocity(self, inp: MissionInputs) -> Vec3 | None:
        """Formations: the leader's own shared velocity while fresh (None: the law uses the estimate's)."""
        sh = inp.leader_shared
        if self.slot_turner is None or sh is None or sh.v_ned_m_s is None:
            return None
        if not 0.0 <= self.c.ages.age_s(sh.stamp_s, self.c.now_s) <= SHARED_STALE_S:
            return None
        return np.asarray(sh.v_ned_m_s, dtype=np.float64)

    def _steady(self, est: LeaderEstimate) -> bool:
        """Whether the leader is seen steadily on a clean link: the faster slew and range gain are flown."""
        f = self.c.cfg.formation
        seen = est.status == TrackStatus.CONFIRMED and est.recent_hit_ratio >= f.steady_hit_ratio
        return seen and self.c.link.clean(self.c.now_s)

    def relative_now(self, est: LeaderEstimate, veh: VehicleState) -> tuple[Vec3, Vec3]:
        """The estimate brought from its frame's capture instant to when the setpoint made now acts.

        That is now plus the link's measured one-way delay (TIMESYNC; none while unmeasured), see
        :mod:`companion.mission.ego`.
        """
        if not self.c.cfg.formation.latency_compensation:
            return np.array(est.p_ned_rel_m), np.array(est.v_ned_rel_m_s)
        a_leader = (
            self.c.law.leader_accel_ned_m_s2
            if est.a_ned_leader_m_s2 is None
            else np.array(est.a_ned_leader_m_s2)
        )
        rel = self.c.ego.predict(
            est.stamp_s,
            np.array(est.p_ned_rel_m),
            np.array(est.v_ned_rel_m_s),
            self.c.now_s,
            a_leader=a_leader,
            ahead_s=veh.link_delay_or_zero_s,
        )
        return rel.p_ned_rel_m, rel.v_ned_rel_m_s

    def _external_fix(self, inp: MissionInputs) -> ExternalPosition | None:
        """The follower's position for PX4: the leader's shared position minus the seen relative vector."""
        est, shared = inp.leader, inp.leader_shared
        if est is None or shared is None or self.c.ages.age_s(shared.stamp_s, self.c.now_s) > SHARED_STALE_S:
            return None
        p = np.array(shared.p_ned_m) - np.array(est.p_ned_rel_m)
        if shared.v_ned_m_s is not None:
            # The leader where it was when the frame was taken, not when it shared its position.
            dt_s = min(max(est.stamp_s - shared.stamp_s, -SHARED_STALE_S), SHARED_STALE_S)
            p += np.asarray(shared.v_ned_m_s) * dt_s
        var = np.array(shared.variance_m2) + np.array(est.var_ned_rel_m2)
        veh = inp.vehicle
        return ExternalPosition(
            stamp_s=est.stamp_s,
            p_ned_m=(float(p[0]), float(p[1]), float(p[2])),
            variance_m2=(float(var[0]), float(var[1]), float(var[2])),
            yaw_rad=veh.yaw_rad,
            roll_rad=veh.roll_rad,
            pitch_rad=veh.pitch_rad,
            reset_counter=EXTERNAL_RESET_COUNTER,
        )

    def follow_vision(self, inp: MissionInputs) -> PhaseStep:
        veh = inp.vehicle
        if self.c.gps.ok:
            return moving(enter_follow(Reason.GPS_RESTORED))
        if not self.c.link.attitude_available(veh, self.c.now_s):
            return moving(
                go(MissionState.CONTROLLED_LANDING, Reason.NO_VISION_FALLBACK, "no attitude or altitude")
            )
        est = self._leader_or_transition(inp)
        if isinstance(est, TransitionRequest):
            return moving(est)
        self._on_new_track(est)
        p_rel, v_rel = self.relative_now(est, veh)
        ext = self._external_fix(inp) if self.c.m.gps_loss_policy == "vision_external_position" else None
        ext, request = self._vision_mode_now(ext, veh)
        if self.vision_mode == VisionMode.EXTERNAL_POSITION:
            vcmd = self.c.law.velocity(
                p_rel,
                v_rel,
                self.c.follower(veh, velocity_valid=True, airframe=inp.airframe),
                self.c.now_s,
                a_leader_ned_m_s2=est.a_ned_leader_m_s2,
                obstacle_ned_m=self.c.obstacle_now(inp),
            )
            return PhaseStep(vcmd.setpoint, ext, vcmd.error.error_ned_m, request)
        acmd = self.c.law.attitude(
            p_rel,
            v_rel,
            self.c.follower(veh, velocity_valid=False),
            self.c.now_s,
            slot_target=self._slot_target(inp),
        )
        err = acmd.error.error_ned_m if acmd.error is not None else None
        return PhaseStep(acmd.setpoint, ext, err, request)

    def _vision_mode_now(
        self, ext: ExternalPosition | None, veh: VehicleState
    ) -> tuple[ExternalPosition | None, TransitionRequest | None]:
        """FOLLOW_VISION's mode this tick, the external fix to send, and the mode change to log.

        Velocity on the external fix while PX4 holds it valid, back to attitude when it goes; on attitude,
        the fix is sent while PX4 digests it and flown once it has been valid ``EXTERNAL_PROBATION_S``;
        not taken within ``external_position_accept_s``, it is no longer sent (said once).
        """
        now_s = self.c.now_s
        if self.vision_mode == VisionMode.EXTERNAL_POSITION:
            if ext is not None and veh.position_valid is True:
                return ext, None
            why = "shared leader position stale" if ext is None else "PX4 rejected the external fix"
            self.vision_mode = VisionMode.ATTITUDE
            self._reset_external()
            self.c.law.reset()
            return ext, go(MissionState.FOLLOW_VISION, Reason.VISION_MODE_CHANGED, f"attitude: {why}")
        if ext is None or self._ext_gave_up:
            return None, None
        if self._ext_since is None:
            self._ext_since = now_s
        if veh.position_valid is True:
            if self._ext_valid_since is None:
                self._ext_valid_since = now_s
            if now_s - self._ext_valid_since < EXTERNAL_PROBATION_S:
                return ext, None
            self.vision_mode = VisionMode.EXTERNAL_POSITION
            self.c.law.reset()
            self.c.law.seed_velocity(np.array(veh.v_ned_m_s))
            return ext, go(
                MissionState.FOLLOW_VISION, Reason.VISION_MODE_CHANGED, "external position accepted"
            )
        self._ext_valid_since = None
        if now_s - self._ext_since <= self.c.m.external_position_accept_s:
            return ext, None
        # PX4 does not take the fix: stop sending it and stay on attitude (said once).
        self._ext_gave_up = True
        why = f"attitude: external position not accepted in {self.c.m.external_position_accept_s:g} s"
        return None, go(MissionState.FOLLOW_VISION, Reason.VISION_MODE_CHANGED, why)
