"""A PX4-like autopilot for one simulated vehicle, driven at the message level.

The autopilot is the only thing a MAVLink client talks to. It is transport-free: the UDP server
(:mod:`sitl.serve`) and the lockstep harness (:mod:`sitl.world`) both feed it pymavlink message
objects through :meth:`Autopilot.handle_message` and collect what it sends from its links'
``outbox``, so tests and evaluation run exactly the code that answers on the wire.

Loops (PX4's, at the rates PX4 SITL runs them):

* every physics tick (200 Hz, PX4's IMU_INTEG_RATE): :meth:`inner_update` - attitude and rate
  control and the mixer;
* 50 Hz: :meth:`outer_update` - sensors (GPS 10 Hz), the estimator, the commander (arming, modes,
  failsafes, auto-disarm), the navigator or offboard setpoint, the position controller;
* streams: :meth:`service_links` sends each link's default streams at PX4's rates, but only for
  links that are active - no message is built when nobody listens.

Links: index 0 is the API link (PX4 "onboard" mode, the one MAVSDK uses on 14540+i), index 1 the
GCS link ("normal" mode, QGroundControl on 14550). Command ACKs and parameter replies go back on the
link the request came from; STATUSTEXT, HEARTBEAT and parameter changes go to every active link.
"""

from __future__ import annotations

import logging
import math
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from sitl import telemetry
from sitl.attitude import Quat, attitude_from_thrust, quat_from_euler, wrap_pi
from sitl.commander import (
    Action,
    DisarmTimer,
    Flags,
    ValidityChecks,
    action_nav_state,
    mode_can_run,
    resolve_failsafe,
)
from sitl.control import NAN, PositionController, PositionLimits, TrajectorySetpoint
from sitl.dynamics import QUAD, QuadDynamics, QuadModel
from sitl.estimator import Estimator, GpsFailure, GpsSample, GpsSensor, VisionSample
from sitl.geo import LocalProjection
from sitl.inner_loop import AttitudeGains, InnerLoop
from sitl.modes import NavState, nav_state_from_mode
from sitl.navigator import Navigator, NavLimits, RtlPhase
from sitl.offboard import (
    OffboardSetpoint,
    SetpointKind,
    parse_attitude_target,
    parse_global_int,
    parse_local_ned,
)
from sitl.params import PARAM_TYPE_INT32, ParamStore, decode_value, encode_value

log = logging.getLogger(__name__)

LINK_API: Final = 0
LINK_GCS: Final = 1

# MAV_RESULT
ACCEPTED, TEMPORARILY_REJECTED, DENIED, UNSUPPORTED, FAILED = 0, 1, 2, 3, 4
# MAV_SEVERITY
SEV_EMERGENCY, SEV_ALERT, SEV_CRITICAL, SEV_ERROR, SEV_WARNING, SEV_NOTICE, SEV_INFO = 0, 1, 2, 3, 4, 5, 6
# MAV_LANDED_STATE
LANDED_ON_GROUND, LANDED_IN_AIR, LANDED_TAKEOFF, LANDED_LANDING = 1, 2, 3, 4
# MAV_STATE
STATE_UNINIT, STATE_STANDBY, STATE_ACTIVE, STATE_CRITICAL = 0, 3, 4, 5

FORCE_MAGIC: Final = 21196
INJECT_UNIT_GPS: Final = 4
_INJECT_TYPES = {0: None, 1: GpsFailure.OFF, 2: GpsFailure.STUCK, 4: GpsFailure.WRONG}
_MOTORS_OFF = (0.0, 0.0, 0.0, 0.0)
#: Armed on the ground, PX4 spins the motors at idle.
_MOTORS_IDLE = (0.03, 0.03, 0.03, 0.03)
_STATUSTEXT_REPEAT_S = 1.0
#: Frames PX4 accepts external-vision poses in: LOCAL_NED 1, LOCAL_FRD 20, and the deprecated
#: MOCAP_NED 14 / VISION_NED 16 that older clients still send (gone from pymavlink's common).
_EV_FRAMES = frozenset({1, 20, 14, 16})


@dataclass(slots=True)
class Home:
    """The home position: geodetic and in the vehicle's local NED frame."""

    lat_deg: float
    lon_deg: float
    alt_m: float
    n_m: float
    e_m: float
    d_m: float


@dataclass(slots=True)
class Battery:
    """A 4S LiPo that drains with thrust (no failsafe: flights here are short)."""

    capacity_mah: float = 5000.0
    consumed_mah: float = 0.0
    voltage_mv: int = 16800
    current_ca: int = 0
    remaining_pct: int = 100

    def update(self, dt_s: float, thrust: float) -> None:
        current_a = 0.5 + 40.0 * thrust * thrust
        self.consumed_mah += current_a * dt_s / 3.6
        frac = max(0.0, 1.0 - self.consumed_mah / self.capacity_mah)
        self.remaining_pct = round(100 * frac)
        self.voltage_mv = int(4 * (3500 + 700 * frac) - current_a * 8)
        self.current_ca = int(current_a * 100)


@dataclass(frozen=True, slots=True)
class AutopilotStatus:
    """What a MAVLink client could know about the vehicle (for in-process pilots and harnesses).

    Everything here is also on the wire (HEARTBEAT, SYS_STATUS, EXTENDED_SYS_STATE,
    LOCAL_POSITION_NED, HOME_POSITION); position and velocity are the *estimate*.
    """

    t_s: float
    armed: bool
    nav_state: NavState
    landed: bool
    global_position_ok: bool
    local_position_ok: bool
    home_set: bool
    p_ned_m: tuple[float, float, float]
    v_ned_m_s: tuple[float, float, float]
    yaw_rad: float


class LinkOutput:
    """One MAVLink link's outgoing side: stream intervals (s) and the outbox of message objects."""

    __slots__ = ("_defaults", "_gps_sent_t_s", "active", "intervals_s", "next_due_s", "outbox")

    def __init__(self, rates_hz: dict[int, float]) -> None:
        self._defaults = {mid: _interval(hz) for mid, hz in rates_hz.items()}
        self.intervals_s: dict[int, float] = dict(self._defaults)
        self.next_due_s: dict[int, float] = dict.fromkeys(self.intervals_s, 0.0)
        self.outbox: list[mavlink.MAVLink_message] = []
        self.active = False
        self._gps_sent_t_s = -1.0

    def set_interval(self, msg_id: int, interval_us: float) -> bool:
        """SET_MESSAGE_INTERVAL semantics: -1 off, 0 default, > 0 interval in microseconds."""
        if msg_id not in telemetry.BUILDERS or msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return False
        if interval_us < 0:
            self.intervals_s.pop(msg_id, None)
            return True
        if interval_us == 0:
            if msg_id in self._defaults:
                self.intervals_s[msg_id] = self._defaults[msg_id]
            else:
                self.intervals_s.pop(msg_id, None)
        else:
            self.intervals_s[msg_id] = max(interval_us * 1e-6, 1e-3)
        self.next_due_s[msg_id] = 0.0
        return True


def _interval(rate_hz: float) -> float:
    return telemetry.ON_UPDATE if math.isinf(rate_hz) else 1.0 / rate_hz


def _text(value: Any) -> str:
    """A MAVLink char[] field as clean text (pymavlink may hand bytes or a str with NULs)."""
    if isinstance(value, bytes | bytearray):
        value = value.decode("ascii", errors="replace")
    return str(value).split("\x00", 1)[0]


def _fin(value: Any) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        return NAN
    return v if math.isfinite(v) else NAN


class Autopilot:
    """One vehicle's PX4: estimator, commander, navigator, controllers and MAVLink endpoints.

    Args:
        name: Vehicle name (logs).
        sysid: MAVLink system id (PX4 SITL: instance + 1).
        dyn: The vehicle's dynamics; the autopilot reads its attitude and rates (a perfect AHRS) and
            its kinematics only through the sensor models.
        world: Projection of the shared world frame.
        spawn_ned_m: The vehicle's spawn point in the world frame: its EKF origin and first home.
        rng: Seeded generator for the estimator's errors.
        gps: The GNSS receiver model (owns its own generator and scripted faults).
        speed_factor: Sim/wall speed; COM_OF_LOSS_T is multiplied by it, as PX4 SITL does with
            PX4_SIM_SPEED_FACTOR, so wall-clock setpoint streams keep working at any speed.
        epoch_unix_s: Unix time at sim time 0 (SYSTEM_TIME).
        params: Parameter overrides (name -> value).
        model: Airframe constants for the control allocation.
    """

    def __init__(
        self,
        *,
        name: str,
        sysid: int,
        dyn: QuadDynamics,
        world: LocalProjection,
        spawn_ned_m: tuple[float, float, float],
        rng: np.random.Generator,
        gps: GpsSensor,
        speed_factor: float = 1.0,
        epoch_unix_s: float = 1_767_225_600.0,
        params: dict[str, float] | None = None,
        model: QuadModel = QUAD,
    ) -> None:
        self.name = name
        self.sysid = sysid
        self.dyn = dyn
        self.gps = gps
        self.speed_factor = speed_factor
        self.epoch_unix_s = epoch_unix_s
        self._spawn_n, self._spawn_e = spawn_ned_m[0], spawn_ned_m[1]
        lat, lon, alt = world.to_geodetic(spawn_ned_m[0], spawn_ned_m[1], 0.0)
        self.origin = LocalProjection(lat, lon, alt)
        self.params = ParamStore({"MAV_SYS_ID": float(sysid), **(params or {})})
        #: The store's live value dict (a plain dict lookup: these are read many times a tick).
        self._pv = self.params.values
        self._params_version = -1
        self.est = Estimator(self.origin, rng)
        self.validity = ValidityChecks()
        self.disarm_timer = DisarmTimer()
        self.navigator = Navigator()
        self.pos_ctrl = PositionController(PositionLimits())
        self.inner = InnerLoop(model, AttitudeGains())
        self.model = model
        self.links = [LinkOutput(telemetry.ONBOARD_RATES_HZ), LinkOutput(telemetry.NORMAL_RATES_HZ)]
        self.battery = Battery()
        self._battery_dt_s = 0.0
        self.counters: Counter[str] = Counter()
        # Commander state.
        self.t_s = 0.0
        self.armed = False
        self.user_mode = NavState.AUTO_LOITER  # PX4 boots in Hold
        self.nav_state = NavState.AUTO_LOITER
        self.failsafe_action = Action.NONE
        self.flags = Flags()
        self._flags_key: tuple[bool, ...] = ()
        self.home: Home | None = None
        self.gps_last: GpsSample | None = None
        self.landed = True
        self._ground_contact_since_s: float | None = None
        self._takeoff_ref_d_m = 0.0
        self._takeoff_target_d_m = NAN
        self._hold_target: tuple[float, float, float] | None = None
        # Setpoints.
        self.offboard_sp: OffboardSetpoint | None = None
        self._vision: VisionSample | None = None
        self._yaw_hold_rad = dyn.yaw_rad
        self._traj: TrajectorySetpoint | None = None
        # Inner-loop inputs (read every physics tick).
        self.q_sp: Quat = (1.0, 0.0, 0.0, 0.0)
        self.thrust_sp = 0.0
        self.yawspeed_ff_rad_s = NAN
        self._rates_sp: tuple[float, float, float] | None = None
        self._motors: tuple[float, float, float, float] | None = _MOTORS_OFF
        self._integrate = False
        self._statustext_sent: dict[str, float] = {}
        self._handlers: dict[str, Callable[[Any, int | None, int, int], None]] = {
            "COMMAND_LONG": self._on_command_long,
            "COMMAND_INT": self._on_command_int,
            "SET_POSITION_TARGET_LOCAL_NED": self._on_set_position_target_local_ned,
            "SET_POSITION_TARGET_GLOBAL_INT": self._on_set_position_target_global_int,
            "SET_ATTITUDE_TARGET": self._on_set_attitude_target,
            "PARAM_REQUEST_LIST": self._on_param_request_list,
            "PARAM_REQUEST_READ": self._on_param_request_read,
            "PARAM_SET": self._on_param_set,
            "VISION_POSITION_ESTIMATE": self._on_vision_position_estimate,
            "ODOMETRY": self._on_odometry,
            "TIMESYNC": self._on_timesync,
            "PING": self._on_ping,
            "MISSION_REQUEST_LIST": self._on_mission_request_list,
            "MISSION_COUNT": self._on_mission_count,
            "HEARTBEAT": self._on_heartbeat,
        }
        self._apply_params()

    # ------------------------------------------------------------------ time
    def time_boot_ms(self) -> int:
        return int(self.t_s * 1000.0) & 0xFFFFFFFF

    def unix_time_us(self) -> int:
        return int((self.epoch_unix_s + self.t_s) * 1e6)

    # ------------------------------------------------------------------ physics-rate loop
    def inner_update(self, dt_s: float) -> tuple[float, float, float, float]:
        """Attitude -> rates -> motors for this physics tick (motor commands 0..1, PX4 order)."""
        fixed = self._motors
        if fixed is not None:
            return fixed
        d = self.dyn
        rates = self._rates_sp
        if rates is None:
            return self.inner.update(
                d.roll_rad, d.pitch_rad, d.yaw_rad, d.p_rad_s, d.q_rad_s, d.r_rad_s,
                self.q_sp, self.yawspeed_ff_rad_s, self.thrust_sp, dt_s, self._integrate,
            )  # fmt: skip
        rp, rq, rr = rates
        return self.inner.rates_to_motors(
            rp, rq, rr, self.thrust_sp, d.p_rad_s, d.q_rad_s, d.r_rad_s, dt_s, self._integrate
        )

    # ------------------------------------------------------------------ 50 Hz loop
    def outer_update(self, t_s: float, dt_s: float) -> None:
        """Sensors, estimator, commander, navigator and position control at sim time ``t_s``."""
        self.t_s = t_s
        if self._params_version != self.params.version:
            self._apply_params()
        n, e, d, vn, ve, vd = self.dyn.kinematics()
        gps = self.gps.sample(t_s, (n, e, d), (vn, ve, vd))
        if gps is not None:
            self.gps_last = gps
        vision = self._vision if int(self._pv["EKF2_EV_CTRL"]) & 1 else None
        events = self.est.update(
            t_s,
            dt_s,
            p_local_true_m=(n - self._spawn_n, e - self._spawn_e, d),
            v_true_m_s=(vn, ve, vd),
            gps=gps,
            vision=vision,
        )
        for severity, text in events.texts:
            self.statustext(severity, text)
        self._update_home()
        self._update_flags()
        self._update_land_detector()
        self._update_mode()
        self._control(dt_s)
        if self.disarm_timer.update(
            t_s, self.armed, self.landed, self._pv["COM_DISARM_LAND"], self._pv["COM_DISARM_PRFLT"]
        ):
            self._disarm(
                "Disarmed by landing" if self.disarm_timer.flown else "Disarmed by auto preflight disarming"
            )
        self._battery_dt_s += dt_s
        if self._battery_dt_s >= 0.1:
            self.battery.update(self._battery_dt_s, self.thrust_sp if self.armed else 0.0)
            self._battery_dt_s = 0.0

    def _apply_params(self) -> None:
        p = self.params
        self._params_version = p.version
        self.pos_ctrl.limits = PositionLimits(
            pos_p_xy=p["MPC_XY_P"],
            pos_p_z=p["MPC_Z_P"],
            vel_p_xy=p["MPC_XY_VEL_P_ACC"],
            vel_i_xy=p["MPC_XY_VEL_I_ACC"],
            vel_d_xy=p["MPC_XY_VEL_D_ACC"],
            vel_p_z=p["MPC_Z_VEL_P_ACC"],
            vel_i_z=p["MPC_Z_VEL_I_ACC"],
            vel_d_z=p["MPC_Z_VEL_D_ACC"],
            vel_max_xy_m_s=p["MPC_XY_VEL_MAX"],
            vel_max_up_m_s=p["MPC_Z_VEL_MAX_UP"],
            vel_max_down_m_s=p["MPC_Z_VEL_MAX_DN"],
            tilt_max_rad=math.radians(p["MPC_TILTMAX_AIR"]),
            thr_min=p["MPC_THR_MIN"],
            thr_max=p["MPC_THR_MAX"],
            hover_thrust=p["MPC_THR_HOVER"],
        )
        self.inner.gains = AttitudeGains(
            roll_p=p["MC_ROLL_P"],
            pitch_p=p["MC_PITCH_P"],
            yaw_p=p["MC_YAW_P"],
            yaw_weight=p["MC_YAW_WEIGHT"],
            roll_rate_max=math.radians(p["MC_ROLLRATE_MAX"]),
            pitch_rate_max=math.radians(p["MC_PITCHRATE_MAX"]),
            yaw_rate_max=math.radians(p["MC_YAWRATE_MAX"]),
        )
        self.navigator.limits = NavLimits(
            cruise_m_s=min(p["MPC_XY_CRUISE"], p["MPC_XY_VEL_MAX"]),
            acc_hor_m_s2=p["MPC_ACC_HOR"],
            up_m_s=p["MPC_Z_V_AUTO_UP"],
            down_m_s=p["MPC_Z_V_AUTO_DN"],
            acc_up_m_s2=p["MPC_ACC_UP_MAX"],
            acc_down_m_s2=p["MPC_ACC_DOWN_MAX"],
            takeoff_speed_m_s=p["MPC_TKO_SPEED"],
            land_speed_m_s=p["MPC_LAND_SPEED"],
            land_alt1_m=p["MPC_LAND_ALT1"],
            land_alt2_m=p["MPC_LAND_ALT2"],
            alt_acceptance_m=p["NAV_MC_ALT_RAD"],
            rtl_return_alt_m=p["RTL_RETURN_ALT"],
            rtl_descend_alt_m=p["RTL_DESCEND_ALT"],
            rtl_land_delay_s=p["RTL_LAND_DELAY"],
            yaw_rate_max_rad_s=math.radians(p["MPC_YAWRAUTO_MAX"]),
        )
        self.est.noaid_timeout_s = p["EKF2_NOAID_TOUT"] * 1e-6

    # ------------------------------------------------------------------ estimate helpers
    def position_ned(self) -> tuple[float, float, float]:
        e = self.est
        return (e.n_m, e.e_m, e.d_m)

    def velocity_ned(self) -> tuple[float, float, float]:
        e = self.est
        return (e.vn_m_s, e.ve_m_s, e.vd_m_s)

    def attitude_q(self) -> Quat:
        d = self.dyn
        return quat_from_euler(d.roll_rad, d.pitch_rad, d.yaw_rad)

    def status(self) -> AutopilotStatus:
        present, _, health = self.sensor_bits()
        gps_ok = bool(present & health & telemetry.SENSOR_GPS)
        vis_ok = bool(present & health & telemetry.SENSOR_VISION_POSITION)
        return AutopilotStatus(
            t_s=self.t_s,
            armed=self.armed,
            nav_state=self.nav_state,
            landed=self.landed,
            global_position_ok=gps_ok,
            local_position_ok=gps_ok or vis_ok,
            home_set=self.home is not None,
            p_ned_m=self.position_ned(),
            v_ned_m_s=self.velocity_ned(),
            yaw_rad=self.dyn.yaw_rad,
        )

    # ------------------------------------------------------------------ commander
    def _update_home(self) -> None:
        if self.home is None and not self.armed and self.flags.global_position_valid:
            self._set_home_here()

    def _set_home_here(self) -> None:
        n, e, d = self.position_ned()
        lat, lon, alt = self.origin.to_geodetic(n, e, d)
        self.home = Home(lat, lon, alt, n, e, d)
        self._broadcast(telemetry.home_position(self))

    def _update_flags(self) -> None:
        p = self.params
        lp, lr, lv, gp = self.validity.update(
            self.t_s,
            ekf_xy_valid=self.est.xy_valid,
            ekf_global_valid=self.est.global_valid,
            eph_m=self.est.eph_m,
            evh_m_s=self.est.evh_m_s,
            com_pos_fs_eph_m=p["COM_POS_FS_EPH"],
            com_vel_fs_evh_m_s=p["COM_VEL_FS_EVH"],
        )
        key = (lp, lr, lv, gp, self.home is not None, self._offboard_available(lp, lv))
        if key != self._flags_key:  # Flags is immutable; rebuild only when something changed
            self._flags_key = key
            self.flags = Flags(
                attitude_valid=True,
                local_position_valid=lp,
                local_position_relaxed_valid=lr,
                local_velocity_valid=lv,
                global_position_valid=gp,
                local_altitude_valid=True,
                home_valid=key[4],
                offboard_signal=key[5],
            )

    def _offboard_available(self, local_pos_valid: bool, local_vel_valid: bool) -> bool:
        sp = self.offboard_sp
        if sp is None:
            return False
        if self.t_s - sp.t_s >= self._pv["COM_OF_LOSS_T"] * self.speed_factor:
            return False
        if sp.position and not local_pos_valid:
            return False
        return not (sp.velocity and not local_vel_valid)

    def armable(self) -> bool:
        return mode_can_run(self.user_mode, self.flags)

    def system_status(self) -> int:
        if self.armed:
            return STATE_CRITICAL if self.failsafe_action is not Action.NONE else STATE_ACTIVE
        return STATE_STANDBY if self.armable() else STATE_UNINIT

    def _update_mode(self) -> None:
        if not self.armed:
            self.failsafe_action = Action.NONE
            nav = self.user_mode
        else:
            if (
                self.nav_state is NavState.AUTO_TAKEOFF
                and self.user_mode is NavState.AUTO_TAKEOFF
                and self.navigator.takeoff_done
            ):
                # COM_TAKEOFF_ACT = 0: hold at the takeoff point once the altitude is reached.
                self._hold_target = self.navigator.target
                self.user_mode = NavState.AUTO_LOITER
            p = self.params
            action = resolve_failsafe(
                self.user_mode, self.flags, int(p["COM_OBL_RC_ACT"]), int(p["NAV_RCL_ACT"])
            )
            if action is Action.DISARM:
                self._disarm("Failsafe: disarming")
                return
            if action is not self.failsafe_action:
                if action is not Action.NONE:
                    target = action_nav_state(action)
                    name = target.ui_name if target is not None else action.name.title()
                    self.statustext(SEV_CRITICAL, f"Failsafe activated: switching to {name}")
                elif self.failsafe_action is not Action.NONE:
                    self.statustext(SEV_INFO, "Failsafe cleared")
            self.failsafe_action = action
            nav = action_nav_state(action) or self.user_mode
        if nav is not self.nav_state:
            self._enter(nav)

    def _enter(self, nav: NavState) -> None:
        self.nav_state = nav
        pos, vel = self.position_ned(), self.velocity_ned()
        yaw = self.dyn.yaw_rad
        self._yaw_hold_rad = yaw
        hold_target, self._hold_target = self._hold_target, None
        if nav.is_auto:
            self.navigator.enter(
                nav, self.t_s, pos, vel, yaw, takeoff_d_m=self._takeoff_target_d_m, hold_target=hold_target
            )

    def _set_user_mode(self, nav: NavState) -> None:
        self.user_mode = nav
        if nav is NavState.AUTO_TAKEOFF and not math.isfinite(self._takeoff_target_d_m):
            self._takeoff_target_d_m = self._takeoff_d_from_alt(NAN)
        # Re-enter even if the nav state stays (e.g. a second takeoff command) so targets refresh.
        self._update_mode()
        if self.nav_state is nav:
            self._enter(nav)

    def _takeoff_d_from_alt(self, alt_amsl_m: float) -> float:
        home_d = self.home.d_m if self.home is not None else 0.0
        if math.isfinite(alt_amsl_m):
            target_d = self.origin.alt0_m - alt_amsl_m
        else:
            target_d = home_d - self._pv["MIS_TAKEOFF_ALT"]
        # Never take off downwards: PX4 holds when already above the takeoff altitude.
        return min(target_d, self.est.d_m)

    def _arm(self, forced: bool) -> tuple[int, str | None]:
        if self.armed:
            return ACCEPTED, None
        del forced  # PX4 runs the checks on external arm requests even when forced
        if not self.armable():
            return TEMPORARILY_REJECTED, "Arming denied: Resolve system health failures first"
        self.armed = True
        self.landed = True
        self._takeoff_ref_d_m = self.est.d_m
        self.disarm_timer.reset()
        self.pos_ctrl.reset()
        self.inner.reset_integrators()
        if self.flags.global_position_valid:
            self._set_home_here()  # PX4 updates home on arming
        self._enter(self.nav_state)
        self.statustext(SEV_INFO, "Armed by external command")
        return ACCEPTED, None

    def _disarm(self, text: str | None) -> None:
        was_failsafe = self.failsafe_action is not Action.NONE
        self.armed = False
        self._motors = _MOTORS_OFF
        self.thrust_sp = 0.0
        self.landed = True
        self._takeoff_target_d_m = NAN
        if was_failsafe:
            self.user_mode = NavState.AUTO_LAND if self.nav_state is NavState.DESCEND else self.nav_state
        self.failsafe_action = Action.NONE
        if self.nav_state is not self.user_mode:
            self._enter(self.user_mode)
        self.disarm_timer.reset()
        if text:
            self.statustext(SEV_INFO, text)

    # ------------------------------------------------------------------ land detector
    def _descent_commanded(self) -> bool:
        nav = self.nav_state
        if nav in (NavState.AUTO_LAND, NavState.DESCEND):
            return True
        if nav is NavState.AUTO_RTL and self.navigator.rtl_phase is RtlPhase.LAND:
            return True
        sp = self._traj
        if sp is not None:
            if not math.isnan(sp.vz) and sp.vz > 0.05:
                return True
            return bool(not math.isnan(sp.z) and sp.z > self.est.d_m + 0.3)
        # Attitude/rate offboard: low thrust is the only hint, as for PX4's land detector.
        return self.thrust_sp < 0.6 * self._pv["MPC_THR_HOVER"]

    def _update_land_detector(self) -> None:
        if not self.armed:
            self.landed = True
            self._ground_contact_since_s = None
            return
        e = self.est
        if self.landed:
            if self._motors is None and (self._takeoff_ref_d_m - e.d_m > 0.3 or e.vd_m_s < -0.5):
                self.landed = False
                self._ground_contact_since_s = None
            return
        slow = abs(e.vd_m_s) < 0.25 and math.hypot(e.vn_m_s, e.ve_m_s) < 1.5
        low_thrust = self.thrust_sp < 0.9 * self._pv["MPC_THR_HOVER"]
        if slow and low_thrust and self._descent_commanded():
            if self._ground_contact_since_s is None:
                self._ground_contact_since_s = self.t_s
            elif self.t_s - self._ground_contact_since_s >= 1.0:  # LNDMC_TRIG_TIME
                self.landed = True
                self._takeoff_ref_d_m = e.d_m
        else:
            self._ground_contact_since_s = None

    def landed_state(self) -> int:
        if self.landed:
            return LANDED_ON_GROUND
        if self.nav_state is NavState.AUTO_TAKEOFF:
            return LANDED_TAKEOFF
        if self.nav_state is NavState.AUTO_LAND or (
            self.nav_state is NavState.AUTO_RTL and self.navigator.rtl_phase is RtlPhase.LAND
        ):
            return LANDED_LANDING
        return LANDED_IN_AIR

    # ------------------------------------------------------------------ control
    def _control(self, dt_s: float) -> None:
        if not self.armed or self.nav_state is NavState.TERMINATION:
            self._motors = _MOTORS_OFF
            self.thrust_sp = 0.0
            self._traj = None
            return
        nav = self.nav_state
        self._rates_sp = None
        self.yawspeed_ff_rad_s = NAN
        traj: TrajectorySetpoint | None = None
        if nav is NavState.OFFBOARD and self.offboard_sp is not None:
            sp = self.offboard_sp
            if sp.kind is SetpointKind.TRAJECTORY:
                traj = sp.trajectory
                if not sp.valid:
                    # PX4: invalid position-control input -> hold level and stop vertically.
                    traj = TrajectorySetpoint().set(acc=(0.0, 0.0, NAN), vel=(NAN, NAN, 0.0))
            else:
                self._traj = None
                self._attitude_setpoint(sp, dt_s)
                return
        elif nav.is_auto:
            home = self.home
            home_ned = (home.n_m, home.e_m, home.d_m) if home is not None else (0.0, 0.0, 0.0)
            traj = self.navigator.update(self.t_s, dt_s, self.position_ned(), home_ned)
        else:
            traj = TrajectorySetpoint().set(acc=(0.0, 0.0, NAN), vel=(NAN, NAN, self._pv["MPC_LAND_SPEED"]))
        self._traj = traj
        if self.landed and not self._climb_demanded(traj):
            self._idle_on_ground()
            return
        if self._motors is not None:
            # Leaving the ground: start the position controller from a clean state.
            self.pos_ctrl.reset()
            self.inner.reset_integrators()
            self._motors = None
        thr = self.pos_ctrl.update(traj, self.position_ned(), self.velocity_ned(), dt_s)
        if not math.isnan(traj.yaw):
            self._yaw_hold_rad = traj.yaw
        elif not math.isnan(traj.yawspeed):
            self._yaw_hold_rad = wrap_pi(self._yaw_hold_rad + traj.yawspeed * dt_s)
        if not math.isnan(traj.yawspeed):
            self.yawspeed_ff_rad_s = traj.yawspeed
        self.q_sp, self.thrust_sp = attitude_from_thrust(thr[0], thr[1], thr[2], self._yaw_hold_rad)
        self._integrate = not self.landed

    def _attitude_setpoint(self, sp: OffboardSetpoint, dt_s: float) -> None:
        del dt_s
        self.thrust_sp = sp.thrust
        if sp.kind is SetpointKind.ATTITUDE:
            self.q_sp = sp.q_sp
            self.yawspeed_ff_rad_s = sp.yawspeed_rad_s
        else:
            r = sp.rates_sp
            self._rates_sp = (
                r[0] if r[0] == r[0] else 0.0,
                r[1] if r[1] == r[1] else 0.0,
                r[2] if r[2] == r[2] else 0.0,
            )
        if self.landed and sp.thrust < 0.5 * self._pv["MPC_THR_HOVER"]:
            self._idle_on_ground()
            return
        self._motors = None
        self._integrate = not self.landed

    def _climb_demanded(self, traj: TrajectorySetpoint) -> bool:
        d = self.est.d_m
        if not math.isnan(traj.z) and traj.z < d - 0.3:
            return True
        if not math.isnan(traj.vz) and traj.vz < -0.3:
            return True
        return not math.isnan(traj.az) and traj.az < -1.0

    def _idle_on_ground(self) -> None:
        self._motors = _MOTORS_IDLE
        self.thrust_sp = 0.0
        self.pos_ctrl.reset()
        self.inner.reset_integrators()
        self._integrate = False
        self._yaw_hold_rad = self.dyn.yaw_rad

    # ------------------------------------------------------------------ sensors for telemetry
    def sensor_bits(self) -> tuple[int, int, int]:
        """SYS_STATUS (present, enabled, health) as PX4 fills them."""
        t = telemetry
        present = (
            t.SENSOR_GYRO | t.SENSOR_ACCEL | t.SENSOR_MAG | t.SENSOR_ABS_PRESSURE | t.SENSOR_AHRS
            | t.SENSOR_ATTITUDE_STABILIZATION | t.SENSOR_YAW_POSITION | t.SENSOR_Z_ALTITUDE_CONTROL
            | t.SENSOR_XY_POSITION_CONTROL | t.SENSOR_MOTOR_OUTPUTS | t.SENSOR_BATTERY | t.SENSOR_LOGGING
            | t.SENSOR_PREARM_CHECK
        )  # fmt: skip
        health = present & ~t.SENSOR_PREARM_CHECK
        est = self.est
        if est.gnss_fusing:
            present |= t.SENSOR_GPS
            if not est.gps_glitch:
                health |= t.SENSOR_GPS
        if est.ev_fusing:
            present |= t.SENSOR_VISION_POSITION
            if est.xy_valid:
                health |= t.SENSOR_VISION_POSITION
        if self.armable():
            health |= t.SENSOR_PREARM_CHECK
        return present, present, health

    def estimator_flags(self) -> int:
        t = telemetry
        e = self.est
        flags = t.EST_ATTITUDE | t.EST_VELOCITY_VERT | t.EST_POS_VERT_ABS | t.EST_POS_VERT_AGL
        if e.xy_valid:
            flags |= t.EST_VELOCITY_HORIZ | t.EST_POS_HORIZ_REL
        if e.global_valid:
            flags |= t.EST_POS_HORIZ_ABS
        if not e.origin_valid and not e.xy_valid:
            flags |= t.EST_CONST_POS_MODE
        if e.h_aiding:
            flags |= t.EST_PRED_POS_HORIZ_REL
        if e.gnss_fusing:
            flags |= t.EST_PRED_POS_HORIZ_ABS
        if e.gps_glitch:
            flags |= t.EST_GPS_GLITCH
        return flags

    # ------------------------------------------------------------------ outgoing
    @property
    def any_link_active(self) -> bool:
        return self.links[0].active or self.links[1].active

    def statustext(self, severity: int, text: str) -> None:
        """Send STATUSTEXT on every active link.

        Identical texts go out at most once per second: hostile input must not turn the autopilot
        into a flood (PX4 has no such limit; it also never sees 10,000 bad setpoints a second).
        """
        last = self._statustext_sent.get(text)
        if last is not None and self.t_s - last < _STATUSTEXT_REPEAT_S:
            return
        self._statustext_sent[text] = self.t_s
        if len(self._statustext_sent) > 256:
            self._statustext_sent.clear()
        log.info("%s: %s", self.name, text)
        self._broadcast(
            mavlink.MAVLink_statustext_message(severity, text[:50].encode("ascii", "replace"), 0, 0)
        )

    def _broadcast(self, msg: mavlink.MAVLink_message | None) -> None:
        if msg is None:
            return
        for link in self.links:
            if link.active:
                link.outbox.append(msg)

    def _reply(self, link: int | None, msg: mavlink.MAVLink_message | None) -> None:
        if msg is None or link is None or not 0 <= link < len(self.links):
            return
        out = self.links[link]
        if out.active:
            out.outbox.append(msg)

    def service_links(self, t_s: float) -> None:
        """Queue the streams that are due at ``t_s`` on every active link."""
        self.t_s = t_s
        gps = self.gps_last
        for link in self.links:
            if not link.active:
                continue
            due = link.next_due_s
            for msg_id, interval in link.intervals_s.items():
                if interval == telemetry.ON_UPDATE:
                    # On every receiver update; at 1 Hz with "no fix" once data stops.
                    fresh = gps is not None and gps.t_s > link._gps_sent_t_s and t_s - gps.t_s <= 1.0
                    if fresh and gps is not None:
                        link._gps_sent_t_s = gps.t_s
                    elif t_s >= due.get(msg_id, 0.0) and (gps is None or t_s - gps.t_s > 1.0):
                        due[msg_id] = t_s + 1.0
                    else:
                        continue
                else:
                    next_s = due.get(msg_id, 0.0)
                    if t_s < next_s:
                        continue
                    next_s += interval
                    due[msg_id] = next_s if next_s > t_s else t_s + interval
                msg = telemetry.BUILDERS[msg_id](self)
                if msg is not None:
                    link.outbox.append(msg)

    # ------------------------------------------------------------------ incoming
    def handle_message(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        """Process one incoming MAVLink message (a pymavlink message object).

        ``link`` is the link index it arrived on (None for in-process senders, which get no reply).
        Never raises on hostile content: a handler bug is counted in ``counters['handler_errors']``
        and logged, and the message is dropped.
        """
        self.counters["messages_in"] += 1
        handler = self._handlers.get(msg.get_type())
        if handler is None:
            self.counters["ignored_messages"] += 1
            return
        try:
            handler(msg, link, src_system, src_component)
        except Exception:
            # The boundary to untrusted input: never let one message take the vehicle down.
            self.counters["handler_errors"] += 1
            log.exception("%s: error handling %s", self.name, msg.get_type())

    def _for_us(self, target_system: int, target_component: int | None = None) -> bool:
        if target_system not in (0, self.sysid):
            self.counters["other_target"] += 1
            return False
        if target_component is not None and target_component not in (0, 1):
            self.counters["other_target"] += 1
            return False
        return True

    def _on_heartbeat(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        self.counters["heartbeats_in"] += 1

    # --- commands
    def _on_command_long(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        params = tuple(_fin(getattr(msg, f"param{i}")) for i in range(1, 8))
        self._command(int(msg.command), params, link, src_system, src_component)

    def _on_command_int(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        params = (
            _fin(msg.param1), _fin(msg.param2), _fin(msg.param3), _fin(msg.param4),
            int(msg.x) * 1e-7, int(msg.y) * 1e-7, _fin(msg.z),
        )  # fmt: skip
        self._command(int(msg.command), params, link, src_system, src_component)

    def _ack(self, command: int, result: int, link: int | None, src_system: int, src_component: int) -> None:
        self._reply(
            link, mavlink.MAVLink_command_ack_message(command, result, 0, 0, src_system, src_component)
        )

    def _command(
        self, command: int, p: tuple[float, ...], link: int | None, src_system: int, src_component: int
    ) -> None:
        handler = _COMMANDS.get(command)
        if handler is None:
            result = UNSUPPORTED
        else:
            # Decide on the current state: a setpoint that arrived since the last 50 Hz update counts
            # (MAVSDK sends its first setpoint and the mode switch back to back).
            self._update_flags()
            result = handler(self, p, link)
        self._ack(command, result, link, src_system, src_component)

    def _cmd_arm_disarm(self, p: tuple[float, ...], link: int | None) -> int:
        forced = p[1] == FORCE_MAGIC
        if p[0] == 1.0:
            result, text = self._arm(forced)
            if text:
                self.statustext(SEV_CRITICAL, text)
            return result
        if p[0] == 0.0:
            if not self.armed:
                return ACCEPTED
            if not forced and not self.landed:
                self.statustext(SEV_CRITICAL, "Disarming denied: not landed")
                return TEMPORARILY_REJECTED
            self._disarm("Disarmed by external command")
            return ACCEPTED
        return UNSUPPORTED

    def _cmd_set_mode(self, p: tuple[float, ...], link: int | None) -> int:
        base, main, sub = p[0], p[1], p[2]
        if math.isnan(base) or math.isnan(main) or not int(base) & 1:
            return DENIED
        nav = nav_state_from_mode(int(main), int(sub) if not math.isnan(sub) else 0)
        if nav is None:
            return DENIED
        return self._request_mode(nav)

    def _request_mode(self, nav: NavState) -> int:
        if nav is NavState.AUTO_LAND or not self.armed or mode_can_run(nav, self.flags):
            if nav is NavState.AUTO_LAND and self.armed and nav is not self.user_mode:
                self.statustext(SEV_INFO, "Landing at current position")
            self._set_user_mode(nav)
            return ACCEPTED
        self.statustext(SEV_CRITICAL, f"Switching to {nav.ui_name} is currently not available")
        return TEMPORARILY_REJECTED

    def _cmd_takeoff(self, p: tuple[float, ...], link: int | None) -> int:
        if self.armed and not mode_can_run(NavState.AUTO_TAKEOFF, self.flags):
            self.statustext(SEV_CRITICAL, "Switching to Takeoff is currently not available")
            return TEMPORARILY_REJECTED
        self._takeoff_target_d_m = self._takeoff_d_from_alt(p[6])
        self._set_user_mode(NavState.AUTO_TAKEOFF)
        return ACCEPTED

    def _cmd_land(self, p: tuple[float, ...], link: int | None) -> int:
        return self._request_mode(NavState.AUTO_LAND)

    def _cmd_rtl(self, p: tuple[float, ...], link: int | None) -> int:
        return self._request_mode(NavState.AUTO_RTL)

    def _cmd_reposition(self, p: tuple[float, ...], link: int | None) -> int:
        lat, lon, alt = p[4], p[5], p[6]
        if not self.flags.global_position_valid or math.isnan(lat) or math.isnan(lon):
            return TEMPORARILY_REJECTED
        if abs(lat) > 90.0 or abs(lon) > 180.0:
            return DENIED
        n, e, _ = self.origin.to_ned(lat, lon, 0.0)
        d = self.origin.alt0_m - alt if not math.isnan(alt) else self.est.d_m
        if abs(n) > 1e6 or abs(e) > 1e6:
            return DENIED
        if p[0] == p[0] and p[0] > 0:
            self.navigator.set_cruise_speed(p[0])
        self._hold_target = (n, e, d)
        result = self._request_mode(NavState.AUTO_LOITER)
        if result == ACCEPTED:
            self.navigator.set_hold_target((n, e, d), p[3])
        return result

    def _cmd_change_speed(self, p: tuple[float, ...], link: int | None) -> int:
        speed = p[1]
        if math.isnan(speed):
            return DENIED
        self.navigator.set_cruise_speed(min(speed, self._pv["MPC_XY_VEL_MAX"]) if speed > 0 else None)
        return ACCEPTED

    def _cmd_set_home(self, p: tuple[float, ...], link: int | None) -> int:
        if p[0] == 1.0:
            if not self.flags.global_position_valid:
                return DENIED
            self._set_home_here()
            return ACCEPTED
        lat, lon, alt = p[4], p[5], p[6]
        if (
            not (math.isfinite(lat) and math.isfinite(lon) and math.isfinite(alt))
            or abs(lat) > 90
            or abs(lon) > 180
        ):
            return DENIED
        n, e, d = self.origin.to_ned(lat, lon, alt)
        self.home = Home(lat, lon, alt, n, e, d)
        self._broadcast(telemetry.home_position(self))
        return ACCEPTED

    def _cmd_terminate(self, p: tuple[float, ...], link: int | None) -> int:
        if p[0] == p[0] and p[0] > 0.5:
            self.statustext(SEV_EMERGENCY, "Flight termination active")
            self._disarm(None)
        return ACCEPTED

    def _cmd_set_message_interval(self, p: tuple[float, ...], link: int | None) -> int:
        if link is None or not (p[0] == p[0] and p[1] == p[1]):
            return FAILED
        return ACCEPTED if self.links[link].set_interval(int(p[0]), p[1]) else FAILED

    def _cmd_request_message(self, p: tuple[float, ...], link: int | None) -> int:
        if p[0] != p[0]:
            return DENIED
        return self._send_requested(int(p[0]), link)

    def _send_requested(self, msg_id: int, link: int | None) -> int:
        builder = telemetry.BUILDERS.get(msg_id)
        msg = builder(self) if builder is not None else None
        if msg is None:
            return DENIED
        self._reply(link, msg)
        return ACCEPTED

    def _cmd_request_autopilot_capabilities(self, p: tuple[float, ...], link: int | None) -> int:
        return self._send_requested(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, link)

    def _cmd_get_home_position(self, p: tuple[float, ...], link: int | None) -> int:
        return self._send_requested(mavlink.MAVLINK_MSG_ID_HOME_POSITION, link)

    def _cmd_inject_failure(self, p: tuple[float, ...], link: int | None) -> int:
        if int(self._pv["SYS_FAILURE_EN"]) != 1:
            self.statustext(SEV_WARNING, "Failure injection disabled")
            return DENIED
        unit = int(p[0]) if p[0] == p[0] else -1
        ftype = int(p[1]) if p[1] == p[1] else -1
        if unit != INJECT_UNIT_GPS or ftype not in _INJECT_TYPES:
            return UNSUPPORTED
        failure = _INJECT_TYPES[ftype]
        self.gps.injected = None if failure is None else failure
        if failure is None:
            self.statustext(SEV_INFO, "CMD_INJECT_FAILURE, GPS ok")
        else:
            self.statustext(SEV_WARNING, f"CMD_INJECT_FAILURE, GPS {failure.value}")
        return ACCEPTED

    # --- setpoints
    def _on_set_position_target_local_ned(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        parsed = parse_local_ned(msg, self.t_s, self.dyn.yaw_rad, self.attitude_q())
        self._accept_setpoint(parsed)

    def _on_set_position_target_global_int(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        origin = self.origin if self.est.origin_valid else None
        home_alt = self.home.alt_m if self.home is not None else self.origin.alt0_m
        self._accept_setpoint(parse_global_int(msg, self.t_s, origin, home_alt))

    def _on_set_attitude_target(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        parsed = parse_attitude_target(msg, self.t_s)
        if parsed is not None:
            self._accept_setpoint(parsed)

    def _accept_setpoint(self, parsed: OffboardSetpoint | str) -> None:
        if isinstance(parsed, str):
            self.counters["setpoints_refused"] += 1
            self.statustext(SEV_CRITICAL, parsed)
            return
        self.counters["setpoints"] += 1
        self.offboard_sp = parsed

    # --- external vision
    def _on_vision_position_estimate(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        x, y, z = _fin(msg.x), _fin(msg.y), _fin(msg.z)
        if math.isnan(x) or math.isnan(y) or abs(x) > 1e6 or abs(y) > 1e6:
            self.counters["vision_refused"] += 1
            return
        cov = list(msg.covariance) if msg.covariance is not None else []
        std = NAN
        if len(cov) >= 7:
            vx, vy = _fin(cov[0]), _fin(cov[6])
            if not math.isnan(vx) and not math.isnan(vy) and vx > 0 and vy > 0:
                std = math.sqrt(max(vx, vy))
        self._vision = VisionSample(self.t_s, x, y, z, std)
        self.counters["vision"] += 1

    def _on_odometry(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if int(msg.frame_id) not in _EV_FRAMES:
            self.counters["vision_refused"] += 1
            return
        x, y, z = _fin(msg.x), _fin(msg.y), _fin(msg.z)
        if math.isnan(x) or math.isnan(y) or abs(x) > 1e6 or abs(y) > 1e6:
            self.counters["vision_refused"] += 1
            return
        cov = list(msg.pose_covariance) if msg.pose_covariance is not None else []
        std = NAN
        if len(cov) >= 7:
            vx, vy = _fin(cov[0]), _fin(cov[6])
            if not math.isnan(vx) and not math.isnan(vy) and vx > 0 and vy > 0:
                std = math.sqrt(max(vx, vy))
        vel: tuple[float, float, float] | None = None
        bvx, bvy, bvz = _fin(msg.vx), _fin(msg.vy), _fin(msg.vz)
        if max(abs(bvx), abs(bvy), abs(bvz)) < 100.0:  # False for NaN
            if int(msg.child_frame_id) in (mavlink.MAV_FRAME_BODY_FRD, mavlink.MAV_FRAME_BODY_NED):
                w, qx, qy, qz = self.attitude_q()
                vel = (
                    (1 - 2 * (qy * qy + qz * qz)) * bvx
                    + 2 * (qx * qy - w * qz) * bvy
                    + 2 * (qx * qz + w * qy) * bvz,
                    2 * (qx * qy + w * qz) * bvx
                    + (1 - 2 * (qx * qx + qz * qz)) * bvy
                    + 2 * (qy * qz - w * qx) * bvz,
                    2 * (qx * qz - w * qy) * bvx
                    + 2 * (qy * qz + w * qx) * bvy
                    + (1 - 2 * (qx * qx + qy * qy)) * bvz,
                )
            else:
                vel = (bvx, bvy, bvz)
        self._vision = VisionSample(self.t_s, x, y, z, std, vel)
        self.counters["vision"] += 1

    # --- parameters
    def _param_value(self, name: str) -> mavlink.MAVLink_message:
        spec = self.params.spec(name)
        if spec is None:
            raise KeyError(name)
        index = self.params.index_of(name)
        return mavlink.MAVLink_param_value_message(
            name.encode("ascii"), encode_value(self.params[name], spec.type), spec.type, len(self.params),
            index if index is not None else 65535,
        )  # fmt: skip

    def _on_param_request_list(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        for name in self.params.names:
            self._reply(link, self._param_value(name))

    def _on_param_request_read(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        index = int(msg.param_index)
        if index == -1:
            name = _text(msg.param_id)
            if self.params.spec(name) is None:
                return  # PX4 stays silent on unknown names
        elif 0 <= index < len(self.params):
            name = self.params.names[index]
        else:
            return
        self._reply(link, self._param_value(name))

    def _on_param_set(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        name = _text(msg.param_id)
        spec = self.params.spec(name)
        if spec is None:
            return
        value = decode_value(float(msg.param_value), int(msg.param_type))
        if value is not None:
            if spec.type == PARAM_TYPE_INT32 and int(msg.param_type) == 9:
                value = round(value)  # a float sent for an int parameter: take its value
            self.params.set(name, value)
        # PX4 answers every set (changed or not) with the stored value, on every link.
        self._broadcast(self._param_value(name))

    # --- misc
    def _on_timesync(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if int(msg.tc1) == 0:
            self._reply(link, mavlink.MAVLink_timesync_message(int(self.t_s * 1e9), int(msg.ts1)))

    def _on_ping(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if int(msg.target_system) == 0:
            self._reply(
                link,
                mavlink.MAVLink_ping_message(int(self.t_s * 1e6), int(msg.seq), src_system, src_component),
            )

    def _on_mission_request_list(
        self, msg: Any, link: int | None, src_system: int, src_component: int
    ) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        mission_type = int(getattr(msg, "mission_type", 0) or 0)
        self._reply(link, mavlink.MAVLink_mission_count_message(src_system, src_component, 0, mission_type))

    def _on_mission_count(self, msg: Any, link: int | None, src_system: int, src_component: int) -> None:
        if not self._for_us(msg.target_system, msg.target_component):
            return
        mission_type = int(getattr(msg, "mission_type", 0) or 0)
        self._reply(
            link,
            mavlink.MAVLink_mission_ack_message(
                src_system, src_component, mavlink.MAV_MISSION_UNSUPPORTED, mission_type
            ),
        )


_CommandHandler = Callable[[Autopilot, tuple[float, ...], "int | None"], int]

_COMMANDS: Final[dict[int, _CommandHandler]] = {
    mavlink.MAV_CMD_COMPONENT_ARM_DISARM: Autopilot._cmd_arm_disarm,
    mavlink.MAV_CMD_DO_SET_MODE: Autopilot._cmd_set_mode,
    mavlink.MAV_CMD_NAV_TAKEOFF: Autopilot._cmd_takeoff,
    mavlink.MAV_CMD_NAV_LAND: Autopilot._cmd_land,
    mavlink.MAV_CMD_NAV_RETURN_TO_LAUNCH: Autopilot._cmd_rtl,
    mavlink.MAV_CMD_DO_REPOSITION: Autopilot._cmd_reposition,
    mavlink.MAV_CMD_DO_CHANGE_SPEED: Autopilot._cmd_change_speed,
    mavlink.MAV_CMD_DO_SET_HOME: Autopilot._cmd_set_home,
    mavlink.MAV_CMD_DO_FLIGHTTERMINATION: Autopilot._cmd_terminate,
    mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: Autopilot._cmd_set_message_interval,
    mavlink.MAV_CMD_REQUEST_MESSAGE: Autopilot._cmd_request_message,
    mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES: Autopilot._cmd_request_autopilot_capabilities,
    mavlink.MAV_CMD_GET_HOME_POSITION: Autopilot._cmd_get_home_position,
    mavlink.MAV_CMD_INJECT_FAILURE: Autopilot._cmd_inject_failure,
}
