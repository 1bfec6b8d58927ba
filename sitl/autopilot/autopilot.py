"""A PX4-like autopilot for one simulated vehicle, driven at the message level.

The autopilot is the only thing a MAVLink client talks to. It is transport-free: the UDP server
(:mod:`sitl.serve.server`) and the lockstep harness (:mod:`sitl.world.lockstep`) both feed it pymavlink
message objects through its endpoint's ``handle_message`` and collect what it sends with
:meth:`Autopilot.drain_outbox`, so tests and evaluation run exactly the code that answers on the wire.
The world, the pilots and the lab see it through :class:`Autopilot`'s methods (its clock, its links, its
own estimate, its mode and messages), never through its state.

Loops (PX4's, at the rates PX4 SITL runs them):

* every physics tick (200 Hz, PX4's IMU_INTEG_RATE): :meth:`inner_update` - attitude and rate
  control and the mixer;
* 50 Hz: :meth:`outer_update` - sensors (GPS 10 Hz), the estimator, the commander (arming, modes,
  failsafes, auto-disarm), the navigator or offboard setpoint, the position controller;
* streams: the endpoint's ``service_links`` sends each link's default streams at PX4's rates, but only for
  links that are active - no message is built when nobody listens.

Links: index 0 is the API link (PX4 "onboard" mode, the one MAVSDK uses on 14540+i), index 1 the
GCS link ("normal" mode, QGroundControl on 14550). Command ACKs and parameter replies go back on the
link the request came from; STATUSTEXT, HEARTBEAT and parameter changes go to every active link.

The autopilot owns its parts, one module each: ``state`` (:mod:`sitl.autopilot.state`: what more than
one part reads - the estimator, parameters, commander state, setpoints, health bits, the links' outboxes),
``flight`` (:mod:`sitl.autopilot.flight`: commander, land detector, control) and ``mavlink``
(:mod:`sitl.autopilot.mavlink`: incoming messages, :mod:`sitl.autopilot.commands`, outgoing streams);
:class:`Autopilot` runs the loops over them.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass

from pymavlink.dialects.v20 import common as mavlink

from companion.kernel.frames import R_from_euler
from sitl.autopilot.flight import FlightLogic
from sitl.autopilot.mavlink import MavlinkEndpoint
from sitl.autopilot.state import AutopilotState, AutopilotStatus, GlobalEstimate, Home
from sitl.physics.dynamics import GRAVITY_M_S2

__all__ = ["Autopilot", "AutopilotStatus", "OwnEstimate"]


@dataclass(frozen=True, slots=True)
class OwnEstimate:
    """The autopilot's own estimate as its companion would share it (the EKF's, never the truth).

    ``p_local_ned_m``: position from the vehicle's EKF origin (local NED, m); ``v_ned_m_s``: velocity
    (NED, m/s); ``yaw_rad``: the heading PX4 estimates; ``global_valid``: PX4 calls its global position
    valid (what it reports in GLOBAL_POSITION_INT).
    """

    global_valid: bool
    p_local_ned_m: tuple[float, float, float]
    v_ned_m_s: tuple[float, float, float]
    yaw_rad: float


class Autopilot:
    """One vehicle's PX4: estimator, commander, navigator, controllers and MAVLink endpoints.

    Built on the vehicle's :class:`~sitl.autopilot.state.AutopilotState` (its arguments are the vehicle's:
    dynamics, sensors, spawn point, parameters); the flight logic and the endpoint act on that state.
    """

    def __init__(self, state: AutopilotState) -> None:
        self.state = state
        self.flight = FlightLogic(state)
        self.mavlink = MavlinkEndpoint(state, self.flight)
        self.name = state.name
        self.sysid = state.sysid

    # ------------------------------------------------------------------ what the world and harnesses see
    def set_time(self, t_s: float) -> None:
        """The world's clock for this physics tick, s."""
        self.state.t_s = t_s

    @property
    def any_link_active(self) -> bool:
        return self.state.any_link_active

    def link_active(self, index: int) -> bool:
        return self.state.links[index].active

    def open_link(self, index: int) -> None:
        """Start link ``index``'s default streams (PX4 streams on every configured link)."""
        self.state.links[index].active = True

    def close_link(self, index: int) -> None:
        """Stop link ``index``'s streams and drop what it has not sent yet."""
        out = self.state.links[index]
        out.active = False
        out.outbox.clear()

    def drain_outbox(self, index: int) -> list[mavlink.MAVLink_message]:
        """What the autopilot sent on link ``index`` since the last drain, oldest first."""
        box = self.state.links[index].outbox
        if not box:
            return []
        out = list(box)
        box.clear()
        return out

    def own_estimate(self) -> OwnEstimate:
        """The EKF's position, velocity and heading (see :class:`OwnEstimate`)."""
        e, s = self.state.est, self.state
        return OwnEstimate(
            bool(e.global_valid), (e.n_m, e.e_m, e.d_m), (e.vn_m_s, e.ve_m_s, e.vd_m_s), s.yaw_est_rad()
        )

    def global_estimate(self) -> GlobalEstimate | None:
        """The global position the autopilot reports (GLOBAL_POSITION_INT); None before it has an origin."""
        return self.state.global_estimate()

    @property
    def home(self) -> Home | None:
        return self.state.home

    def time_boot_ms(self) -> int:
        return self.state.time_boot_ms()

    def status(self) -> AutopilotStatus:
        return self.state.status()

    def mode(self) -> tuple[str, bool]:
        """The flight mode (PX4's UI name) and whether it is armed."""
        return self.state.nav_state.ui_name, self.state.armed

    def status_texts(self) -> list[tuple[float, int, str]]:
        """The STATUSTEXTs sent so far: (sim time s, MAV_SEVERITY, text)."""
        return list(self.state.texts_sent)

    @property
    def counters(self) -> Counter[str]:
        """Messages in, handler errors, setpoints taken and refused."""
        return self.state.counters

    # ------------------------------------------------------------------ physics-rate loop
    def inner_update(self, dt_s: float) -> tuple[float, float, float, float]:
        """Attitude -> rates -> motors for this physics tick (motor commands 0..1, PX4 order)."""
        s = self.state
        fixed = s.motors
        if fixed is not None:
            return fixed
        d = s.dyn
        rates = s.rates_sp
        if rates is None:
            return s.inner.update(
                d.roll_rad, d.pitch_rad, s.yaw_est_rad(), d.p_rad_s, d.q_rad_s, d.r_rad_s,
                s.q_sp, s.yawspeed_ff_rad_s, s.thrust_sp, dt_s, s.integrate,
            )  # fmt: skip
        rp, rq, rr = rates
        return s.inner.rates_to_motors(
            rp, rq, rr, s.thrust_sp, d.p_rad_s, d.q_rad_s, d.r_rad_s, dt_s, s.integrate
        )

    def _imu_accel_ned(self) -> tuple[float, float, float]:
        """The acceleration an IMU-only estimate integrates, NED m/s^2.

        Specific force turned with the estimated attitude, plus gravity: aerodynamic drag is not in it
        (EKF2 fuses no drag by default).
        """
        s = self.state
        d = s.dyn
        fx, fy, fz = d.specific_force_body()
        R = R_from_euler(d.roll_rad, d.pitch_rad, s.yaw_est_rad())
        return (
            float(R[0, 0] * fx + R[0, 1] * fy + R[0, 2] * fz),
            float(R[1, 0] * fx + R[1, 1] * fy + R[1, 2] * fz),
            float(R[2, 0] * fx + R[2, 1] * fy + R[2, 2] * fz) + GRAVITY_M_S2,
        )

    # ------------------------------------------------------------------ 50 Hz loop
    def outer_update(self, t_s: float, dt_s: float) -> None:
        """Sensors, estimator, commander, navigator and position control at sim time ``t_s``."""
        s = self.state
        s.t_s = t_s
        if s.heading_error is not None:
            s.heading_error.update(dt_s)
        if s.params_version != s.params.version:
            s.apply_params()
        n, e, d, vn, ve, vd = s.dyn.kinematics()
        gps = s.gps.sample(t_s, (n, e, d), (vn, ve, vd))
        if gps is not None:
            s.gps_last = gps
        vision = s.vision if int(s.pv["EKF2_EV_CTRL"]) & 1 else None
        events = s.est.update(
            t_s,
            dt_s,
            p_local_true_m=(n - s.spawn_n, e - s.spawn_e, d),
            v_true_m_s=(vn, ve, vd),
            gps=gps,
            vision=vision,
            a_imu_ned_m_s2=self._imu_accel_ned() if s.est.dead_reckoning else None,
        )
        for severity, text in events.texts:
            s.statustext(severity, text)
        self.flight.step(dt_s)
        if s.disarm_timer.update(t_s, s.armed, s.landed, s.pv["COM_DISARM_LAND"], s.pv["COM_DISARM_PRFLT"]):
            self.flight.disarm(
                "Disarmed by landing" if s.disarm_timer.flown else "Disarmed by auto preflight disarming"
            )
        s.battery_dt_s += dt_s
        if s.battery_dt_s >= 0.1:
            s.battery.update(s.battery_dt_s, s.thrust_sp if s.armed else 0.0)
            s.battery_dt_s = 0.0
