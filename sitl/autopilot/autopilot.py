"""A PX4-like autopilot for one simulated vehicle, driven at the message level.

The autopilot is the only thing a MAVLink client talks to. It is transport-free: the UDP server
(:mod:`sitl.serve.server`) and the lockstep harness (:mod:`sitl.world.lockstep`) both feed it pymavlink
message objects through :meth:`Autopilot.handle_message` and collect what it sends from its links'
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

The autopilot is built in layers, one module each: :mod:`sitl.autopilot.state` (the state, parameters,
health bits and the outgoing side), :mod:`sitl.autopilot.flight` (commander, land detector, control),
:mod:`sitl.autopilot.mavlink` (incoming messages and commands) and this module's :class:`Autopilot`
(the loops).
"""

from __future__ import annotations

from dataclasses import dataclass

from companion.kernel.frames import R_from_euler
from sitl.autopilot import telemetry
from sitl.autopilot.mavlink import AutopilotMavlink
from sitl.autopilot.modes import NavState
from sitl.physics.dynamics import GRAVITY_M_S2


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


class Autopilot(AutopilotMavlink):
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
                d.roll_rad, d.pitch_rad, self.yaw_est_rad(), d.p_rad_s, d.q_rad_s, d.r_rad_s,
                self.q_sp, self.yawspeed_ff_rad_s, self.thrust_sp, dt_s, self._integrate,
            )  # fmt: skip
        rp, rq, rr = rates
        return self.inner.rates_to_motors(
            rp, rq, rr, self.thrust_sp, d.p_rad_s, d.q_rad_s, d.r_rad_s, dt_s, self._integrate
        )

    def _imu_accel_ned(self) -> tuple[float, float, float]:
        """The acceleration an IMU-only estimate integrates, NED m/s^2.

        Specific force turned with the estimated attitude, plus gravity: aerodynamic drag is not in it
        (EKF2 fuses no drag by default).
        """
        d = self.dyn
        fx, fy, fz = d.specific_force_body()
        R = R_from_euler(d.roll_rad, d.pitch_rad, self.yaw_est_rad())
        return (
            float(R[0, 0] * fx + R[0, 1] * fy + R[0, 2] * fz),
            float(R[1, 0] * fx + R[1, 1] * fy + R[1, 2] * fz),
            float(R[2, 0] * fx + R[2, 1] * fy + R[2, 2] * fz) + GRAVITY_M_S2,
        )

    # ------------------------------------------------------------------ 50 Hz loop
    def outer_update(self, t_s: float, dt_s: float) -> None:
        """Sensors, estimator, commander, navigator and position control at sim time ``t_s``."""
        self.t_s = t_s
        if self.heading_error is not None:
            self.heading_error.update(dt_s)
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
            a_imu_ned_m_s2=self._imu_accel_ned() if self.est.dead_reckoning else None,
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
