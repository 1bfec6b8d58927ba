"""PX4 Commander's decisions, pure.

Arming, the user's intended mode, mode requirements, failsafe fallbacks, estimate validity with
probation, and auto-disarm.

Sources (PX4 v1.15, ``src/modules/commander``):

* ``UserModeIntention.cpp``: while disarmed any mode change is accepted; while armed the mode must
  be able to run (AUTO.LAND is always forced).
* ``ModeUtil/mode_requirements.cpp`` and ``failsafe/framework.cpp::modeCanRun``: what each mode
  needs (Hold and RTL: global + local position; Takeoff: local position; Land: relaxed local position;
  Descend: attitude; Offboard: the offboard signal).
* ``failsafe/failsafe.cpp::checkModeFallback``: an intended mode that cannot run, or an offboard signal
  that is lost, selects an action (COM_OBL_RC_ACT; its manual-control options fall to NAV_RCL_ACT
  because plain SITL has no manual control); ``framework.cpp`` then walks Hold -> RTL -> Land ->
  Descend -> Terminate until a mode can run. These fallbacks clear when the condition clears.
* ``HealthAndArmingChecks/checks/estimatorCheck.cpp``: position invalid when the EKF flag is false or
  eph >= COM_POS_FS_EPH (x2.5 hysteresis while valid); invalidation is immediate, recovery needs 1 s.
* ``Commander.cpp``: auto-disarm COM_DISARM_LAND after landing, COM_DISARM_PRFLT if never airborne.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import Enum

from sitl.autopilot.modes import MANUAL_MODES, NavState

PROBATION_S = 1.0


@dataclass(frozen=True, slots=True)
class Flags:
    """What the mode requirements look at, already through probation and accuracy checks."""

    attitude_valid: bool = True
    local_position_valid: bool = False
    local_position_relaxed_valid: bool = False
    local_velocity_valid: bool = False
    global_position_valid: bool = False
    local_altitude_valid: bool = True
    home_valid: bool = False
    offboard_signal: bool = False
    manual_control: bool = False
    mission_valid: bool = False


def mode_can_run(nav: NavState, f: Flags) -> bool:
    """PX4 ``modeCanRun`` for the modes this simulator knows."""
    if nav is NavState.AUTO_LOITER:
        return f.global_position_valid and f.local_position_valid and f.local_altitude_valid
    if nav is NavState.AUTO_TAKEOFF:
        return f.local_position_valid and f.local_altitude_valid
    if nav is NavState.AUTO_LAND:
        return f.local_position_relaxed_valid and f.local_altitude_valid
    if nav is NavState.AUTO_RTL:
        return f.global_position_valid and f.local_position_valid and f.home_valid and f.local_altitude_valid
    if nav is NavState.OFFBOARD:
        return f.offboard_signal and f.attitude_valid
    if nav is NavState.DESCEND:
        return f.attitude_valid
    if nav is NavState.TERMINATION:
        return True
    if nav is NavState.AUTO_MISSION:
        return f.mission_valid and f.global_position_valid and f.local_position_valid
    if nav in MANUAL_MODES:
        return f.manual_control
    return False


class Action(Enum):
    """Failsafe actions, in the order ``framework.cpp`` falls back through them."""

    NONE = 0
    HOLD = 1
    RTL = 2
    LAND = 3
    DESCEND = 4
    TERMINATE = 5
    DISARM = 6


_ACTION_MODE = {
    Action.HOLD: NavState.AUTO_LOITER,
    Action.RTL: NavState.AUTO_RTL,
    Action.LAND: NavState.AUTO_LAND,
    Action.DESCEND: NavState.DESCEND,
    Action.TERMINATE: NavState.TERMINATION,
}


def rc_loss_action(nav_rcl_act: int) -> Action:
    """NAV_RCL_ACT: 1 Hold, 2 Return, 3 Land, 5 Terminate, 6 Disarm (0 'disabled' holds)."""
    return {1: Action.HOLD, 2: Action.RTL, 3: Action.LAND, 5: Action.TERMINATE, 6: Action.DISARM}.get(
        nav_rcl_act, Action.HOLD
    )


def offboard_loss_action(com_obl_rc_act: int, nav_rcl_act: int) -> Action:
    """The offboard-loss action for COM_OBL_RC_ACT.

    0 Position, 1 Altitude, 2 Stabilized (all need manual control, so without it NAV_RCL_ACT decides),
    3 Return, 4 Land, 5 Hold, 6 Terminate, 7 Disarm.
    """
    if com_obl_rc_act in (0, 1, 2):
        return rc_loss_action(nav_rcl_act)
    return {3: Action.RTL, 4: Action.LAND, 5: Action.HOLD, 6: Action.TERMINATE, 7: Action.DISARM}.get(
        com_obl_rc_act, Action.RTL
    )


def resolve_failsafe(intended: NavState, f: Flags, com_obl_rc_act: int, nav_rcl_act: int) -> Action:
    """The failsafe action for an armed vehicle whose user wants ``intended`` (NONE: fly it)."""
    action = Action.NONE
    if intended is NavState.OFFBOARD and not f.offboard_signal:
        action = offboard_loss_action(com_obl_rc_act, nav_rcl_act)
    elif not mode_can_run(intended, f):
        action = Action.RTL
    if action is Action.NONE or action is Action.DISARM:
        return action
    # framework.cpp: fall through Hold -> RTL -> Land -> Descend -> Terminate until one can run.
    order = (Action.HOLD, Action.RTL, Action.LAND, Action.DESCEND, Action.TERMINATE)
    for candidate in order[order.index(action) :]:
        if mode_can_run(_ACTION_MODE[candidate], f):
            return candidate
    return Action.TERMINATE


def action_nav_state(action: Action) -> NavState | None:
    """The navigation state a failsafe action flies in (None for NONE and DISARM)."""
    return _ACTION_MODE.get(action)


class Probation:
    """A validity flag that drops at once and comes back only after ``PROBATION_S`` of being good."""

    __slots__ = ("_good_since_s", "valid")

    def __init__(self) -> None:
        self.valid = False
        self._good_since_s: float | None = None

    def update(self, t_s: float, good: bool) -> bool:
        if not good:
            self.valid = False
            self._good_since_s = None
        elif not self.valid:
            if self._good_since_s is None:
                self._good_since_s = t_s
            if t_s - self._good_since_s >= PROBATION_S:
                self.valid = True
        return self.valid


class ValidityChecks:
    """estimatorCheck.cpp: EKF flags + accuracy limits + probation -> the commander's flags."""

    def __init__(self) -> None:
        self.local_pos = Probation()
        self.local_pos_relaxed = Probation()
        self.local_vel = Probation()
        self.global_pos = Probation()

    def update(
        self,
        t_s: float,
        *,
        ekf_xy_valid: bool,
        ekf_global_valid: bool,
        eph_m: float,
        evh_m_s: float,
        com_pos_fs_eph_m: float,
        com_vel_fs_evh_m_s: float,
    ) -> tuple[bool, bool, bool, bool]:
        """(local position, relaxed local position, local velocity, global position) validity."""
        eph_lim = com_pos_fs_eph_m * (2.5 if self.local_pos.valid else 1.0)
        evh_lim = com_vel_fs_evh_m_s * (2.5 if self.local_vel.valid else 1.0)
        lp = self.local_pos.update(t_s, ekf_xy_valid and eph_m < eph_lim)
        lr = self.local_pos_relaxed.update(t_s, ekf_xy_valid)
        lv = self.local_vel.update(t_s, ekf_xy_valid and evh_m_s < evh_lim)
        gp_lim = com_pos_fs_eph_m * (2.5 if self.global_pos.valid else 1.0)
        gp = self.global_pos.update(t_s, ekf_global_valid and eph_m < gp_lim)
        return lp, lr, lv, gp


class DisarmTimer:
    """Auto-disarm: COM_DISARM_LAND after landing, COM_DISARM_PRFLT when armed but never flown."""

    __slots__ = ("_landed_since_s", "flown")

    def __init__(self) -> None:
        self._landed_since_s: float | None = None
        self.flown = False

    def reset(self) -> None:
        self._landed_since_s = None
        self.flown = False

    def update(
        self, t_s: float, armed: bool, landed: bool, disarm_land_s: float, disarm_prflt_s: float
    ) -> bool:
        """True when the vehicle should disarm now."""
        if not armed:
            self.reset()
            return False
        if not landed:
            self.flown = True
            self._landed_since_s = None
            return False
        if self._landed_since_s is None:
            self._landed_since_s = t_s
        limit_s = disarm_land_s if self.flown else disarm_prflt_s
        if limit_s <= 0 or not math.isfinite(limit_s):
            return False
        return t_s - self._landed_since_s >= limit_s
