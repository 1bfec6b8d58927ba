"""The autopilot's state and what reads it: parameters, the estimate, health bits, outgoing MAVLink.

One part of :class:`sitl.autopilot.autopilot.Autopilot` (see there): :class:`AutopilotState` holds the
vehicle's state that more than one part reads or writes (the estimator, parameters, commander state,
setpoints, the inner loop's inputs, the links' outboxes); its methods only read it, apply parameters, or
queue messages on the links. :mod:`sitl.autopilot.telemetry` builds the messages from it.
"""

from __future__ import annotations

import logging
import math
from collections import Counter, deque
from dataclasses import dataclass
from typing import Final

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from sitl.autopilot import telemetry
from sitl.autopilot.attitude import Quat, quat_from_euler, wrap_pi
from sitl.autopilot.commander import Action, DisarmTimer, Flags, ValidityChecks, mode_can_run
from sitl.autopilot.control import NAN, PositionController, PositionLimits
from sitl.autopilot.estimator import Estimator, VisionSample
from sitl.autopilot.inner_loop import AttitudeGains, InnerLoop
from sitl.autopilot.modes import NavState
from sitl.autopilot.navigator import Navigator, NavLimits, RtlPhase
from sitl.autopilot.offboard import OffboardSetpoint
from sitl.autopilot.params import ParamStore
from sitl.physics.dynamics import QUAD, QuadDynamics, QuadModel
from sitl.physics.geo import LocalProjection
from sitl.physics.gps import GpsSample, GpsSensor
from sitl.physics.heading_error import HeadingError

log = logging.getLogger("sitl.autopilot")

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

MOTORS_OFF = (0.0, 0.0, 0.0, 0.0)
#: Armed on the ground, PX4 spins the motors at idle.
MOTORS_IDLE = (0.03, 0.03, 0.03, 0.03)
_STATUSTEXT_REPEAT_S = 1.0


@dataclass(frozen=True, slots=True)
class GlobalEstimate:
    """What a vehicle's autopilot believes its global position is (its GLOBAL_POSITION_INT).

    Geodetic (deg, m above mean sea level), velocity NED (m/s), heading (deg): what a vehicle's companion
    would share with others. An estimate, with the autopilot's errors, never the ground truth.
    """

    lat_deg: float
    lon_deg: float
    alt_amsl_m: float
    v_ned_m_s: tuple[float, float, float]
    yaw_deg: float


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


class AutopilotState:
    """One vehicle's autopilot state, what :class:`~sitl.autopilot.autopilot.Autopilot`'s parts share.

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
        heading_error: PX4's heading-estimate error (None: a perfect heading).
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
        heading_error: HeadingError | None = None,
    ) -> None:
        self.name = name
        #: PX4's heading-estimate error (None: the true heading, a perfect estimate).
        self.heading_error = heading_error
        self.sysid = sysid
        self.dyn = dyn
        self.gps = gps
        self.speed_factor = speed_factor
        self.epoch_unix_s = epoch_unix_s
        self.spawn_n, self.spawn_e = spawn_ned_m[0], spawn_ned_m[1]
        lat, lon, alt = world.to_geodetic(spawn_ned_m[0], spawn_ned_m[1], 0.0)
        self.origin = LocalProjection(lat, lon, alt)
        self.params = ParamStore({"MAV_SYS_ID": float(sysid), **(params or {})})
        #: The store's live value dict (a plain dict lookup: these are read many times a tick).
        self.pv = self.params.values
        self.params_version = -1
        self.est = Estimator(self.origin, rng)
        self.validity = ValidityChecks()
        self.disarm_timer = DisarmTimer()
        self.navigator = Navigator()
        self.pos_ctrl = PositionController(PositionLimits())
        self.inner = InnerLoop(model, AttitudeGains())
        self.model = model
        self.links = [LinkOutput(telemetry.ONBOARD_RATES_HZ), LinkOutput(telemetry.NORMAL_RATES_HZ)]
        self.battery = Battery()
        self.battery_dt_s = 0.0
        self.counters: Counter[str] = Counter()
        # Commander state.
        self.t_s = 0.0
        self.armed = False
        self.user_mode = NavState.AUTO_LOITER  # PX4 boots in Hold
        self.nav_state = NavState.AUTO_LOITER
        self.failsafe_action = Action.NONE
        self.flags = Flags()
        self.home: Home | None = None
        self.gps_last: GpsSample | None = None
        self.landed = True
        self.takeoff_target_d_m = NAN
        self.hold_target: tuple[float, float, float] | None = None
        # Setpoints.
        self.offboard_sp: OffboardSetpoint | None = None
        self.vision: VisionSample | None = None
        # Inner-loop inputs (read every physics tick).
        self.q_sp: Quat = (1.0, 0.0, 0.0, 0.0)
        self.thrust_sp = 0.0
        self.yawspeed_ff_rad_s = NAN
        self.rates_sp: tuple[float, float, float] | None = None
        self.motors: tuple[float, float, float, float] | None = MOTORS_OFF
        self.integrate = False
        self._statustext_sent: dict[str, float] = {}
        #: The last STATUSTEXTs sent, (sim time s, MAV_SEVERITY, text): what a harness records of the run.
        self.texts_sent: deque[tuple[float, int, str]] = deque(maxlen=2000)
        self.apply_params()

    def global_estimate(self) -> GlobalEstimate | None:
        """The global position this autopilot reports (GLOBAL_POSITION_INT); None before it has an origin."""
        e = self.est
        if not e.origin_valid:
            return None
        lat, lon, alt = self.origin.to_geodetic(e.n_m, e.e_m, e.d_m)
        return GlobalEstimate(
            lat, lon, alt, (e.vn_m_s, e.ve_m_s, e.vd_m_s), math.degrees(self.yaw_est_rad()) % 360.0
        )

    def yaw_est_rad(self) -> float:
        """The heading PX4 estimates, rad: the true one plus :attr:`heading_error`'s error.

        Everything the autopilot does with its heading reads this: the attitude loop holds it, body-frame
        setpoints turn with it, and telemetry reports it. Roll and pitch are the true ones.
        """
        err = self.heading_error
        yaw = self.dyn.yaw_rad
        return yaw if err is None else wrap_pi(yaw + err.rad)

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
            yaw_rad=self.yaw_est_rad(),
        )

    # ------------------------------------------------------------------ time
    def time_boot_ms(self) -> int:
        return int(self.t_s * 1000.0) & 0xFFFFFFFF

    def unix_time_us(self) -> int:
        return int((self.epoch_unix_s + self.t_s) * 1e6)

    # ------------------------------------------------------------------ parameters
    def apply_params(self) -> None:
        p = self.params
        self.params_version = p.version
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
        return quat_from_euler(d.roll_rad, d.pitch_rad, self.yaw_est_rad())

    # ------------------------------------------------------------------ commander state
    def armable(self) -> bool:
        return mode_can_run(self.user_mode, self.flags)

    def system_status(self) -> int:
        if self.armed:
            return STATE_CRITICAL if self.failsafe_action is not Action.NONE else STATE_ACTIVE
        return STATE_STANDBY if self.armable() else STATE_UNINIT

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
        self.texts_sent.append((self.t_s, severity, text))
        self.broadcast(
            mavlink.MAVLink_statustext_message(severity, text[:50].encode("ascii", "replace"), 0, 0)
        )

    def broadcast(self, msg: mavlink.MAVLink_message | None) -> None:
        if msg is None:
            return
        for link in self.links:
            if link.active:
                link.outbox.append(msg)

    def reply(self, link: int | None, msg: mavlink.MAVLink_message | None) -> None:
        if msg is None or link is None or not 0 <= link < len(self.links):
            return
        out = self.links[link]
        if out.active:
            out.outbox.append(msg)
