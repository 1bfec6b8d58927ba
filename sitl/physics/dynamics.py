"""Rigid-body dynamics of one quad-X in JSBSim (no asyncio, no sockets, time advances by ``step``).

The airframe lives in ``sitl/models/aircraft/wingman_quad/wingman_quad.xml``: four BODY-frame
external-reaction rotor forces with a first-order motor lag, rotor yaw torques, body drag on the
air-relative velocity, and four sprung landing legs. :data:`QUAD` mirrors the numbers the autopilot's
control allocation needs (PX4 has them as CA_* parameters).

Speed matters here: a physics tick is one ``FGFDMExec.run()`` plus a handful of property reads through
pre-fetched property nodes (about 12 us), and everything else in this module is plain-float Python.
The JSBSim step is whatever ``dt_s`` the world passes (``[world] physics_rate_hz``, 200 Hz by default).
"""

from __future__ import annotations

import contextlib
import ctypes
import importlib.resources
import math
import os
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import jsbsim
import numpy as np
from numpy.typing import NDArray

from companion.kernel.frames import R_from_euler, quat_from_R
from sitl.physics.geo import LocalProjection

#: The JSBSim aircraft files ship inside the package (package data: found the same way in a checkout and in
#: an installed wheel).
MODEL_ROOT = Path(str(importlib.resources.files("sitl") / "models"))
MODEL_NAME = "wingman_quad"

_FT = 0.3048
#: Newtons in one pound-force.
_LBF_N = 4.4482216
GRAVITY_M_S2 = 9.80665


@dataclass(frozen=True, slots=True)
class QuadModel:
    """The physical constants of ``wingman_quad.xml`` the autopilot's allocation and controllers use."""

    mass_kg: float = 1.5
    #: Rotor offset from the CG along body x and y (quad-X, 0.45 m motor-to-motor diagonal), m.
    arm_xy_m: float = 0.159
    max_thrust_per_motor_n: float = 7.355
    #: Rotor yaw reaction torque per newton of thrust, m.
    yaw_moment_per_thrust_m: float = 0.016
    ixx_kg_m2: float = 0.0165
    iyy_kg_m2: float = 0.0165
    izz_kg_m2: float = 0.029
    motor_tau_s: float = 0.03
    #: Height of the CG above the ground with the legs on it, m (legs 0.10 m, ~9 mm spring sag).
    rest_height_m: float = 0.091

    @property
    def hover_thrust(self) -> float:
        """Normalised collective thrust (0..1) that balances gravity."""
        return self.mass_kg * GRAVITY_M_S2 / (4.0 * self.max_thrust_per_motor_n)


QUAD = QuadModel()


@dataclass(frozen=True, slots=True)
class VehicleTruth:
    """The true state of one vehicle at ``t_s`` (sim time): what the renderer and evaluators may see.

    Attributes:
        t_s: Sim time, s.
        p_ned_m: Position of the CG in the shared world NED frame (origin: world home), m.
        v_ned_m_s: Velocity in NED, m/s.
        q_ned_body_wxyz: Attitude, body FRD -> NED, unit quaternion (w, x, y, z).
        omega_body_rad_s: Angular rate in body FRD, rad/s.
    """

    t_s: float
    p_ned_m: NDArray[np.float64]
    v_ned_m_s: NDArray[np.float64]
    q_ned_body_wxyz: NDArray[np.float64]
    omega_body_rad_s: NDArray[np.float64]


@contextlib.contextmanager
def silenced_stdio() -> Iterator[None]:
    """Point file descriptors 1 and 2 at /dev/null: JSBSim's C++ writes straight to them."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 1)
        os.dup2(devnull, 2)
        yield
    finally:
        # C stdio may still hold JSBSim's text in its buffer: flush it into /dev/null first.
        with contextlib.suppress(OSError, AttributeError):
            ctypes.CDLL(None).fflush(None)
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in (*saved, devnull):
            os.close(fd)


class QuadDynamics:
    """One JSBSim instance of the Wingman quad, placed in a shared world frame.

    After each :meth:`step` the fast attributes ``p_rad_s, q_rad_s, r_rad_s`` (body rates) and
    ``roll_rad, pitch_rad, yaw_rad`` (ZYX Euler angles, body -> NED) hold the new state; the inner
    control loop reads only those. Slower consumers call :meth:`kinematics`.

    Args:
        world: Projection of the shared world NED frame (origin: world home, on the ground).
        spawn_ned_m: Where the vehicle starts, world NED (down is ignored: it starts on the ground).
        spawn_yaw_rad: Initial heading.
        dt_s: Physics time step.
        linear_drag_per_s: A further isotropic linear drag per unit mass (1/s), on the air-relative velocity.
    """

    def __init__(
        self,
        world: LocalProjection,
        spawn_ned_m: tuple[float, float, float],
        spawn_yaw_rad: float,
        dt_s: float,
        linear_drag_per_s: float = 0.0,
    ) -> None:
        self._world = world
        self.dt_s = dt_s
        lat_deg, lon_deg, _ = world.to_geodetic(spawn_ned_m[0], spawn_ned_m[1], 0.0)
        with silenced_stdio():
            fdm = jsbsim.FGFDMExec(str(MODEL_ROOT), None)
            fdm.set_debug_level(0)
            if not fdm.load_model(MODEL_NAME):
                raise RuntimeError(f"JSBSim could not load {MODEL_ROOT / 'aircraft' / MODEL_NAME}")
            fdm["ic/lat-geod-deg"] = lat_deg
            fdm["ic/long-gc-deg"] = lon_deg
            fdm["ic/terrain-elevation-ft"] = world.alt0_m / _FT
            fdm["ic/h-agl-ft"] = (QUAD.rest_height_m + 0.005) / _FT
            fdm["ic/psi-true-deg"] = math.degrees(spawn_yaw_rad) % 360.0
            fdm.set_dt(dt_s)
            # N/(m/s) in JSBSim's lbf per ft/s.
            fdm["aero/extra-linear-drag-lbf_fps"] = linear_drag_per_s * QUAD.mass_kg * _FT / _LBF_N
            if not fdm.run_ic():
                raise RuntimeError("JSBSim rejected the initial conditions")
        self._fdm = fdm
        pm = fdm.get_property_manager()

        def node(name: str) -> jsbsim.FGPropertyNode:
            found = pm.get_node(name, False)
            if found is None:
                raise RuntimeError(f"{MODEL_NAME}.xml lacks the property {name}")
            return found

        self._cmd = [node(f"fcs/esc-cmd-{i}") for i in range(4)]
        names = ("velocities/p-rad_sec", "velocities/q-rad_sec", "velocities/r-rad_sec")
        self._rate_nodes = [node(n) for n in names]
        names = ("attitude/phi-rad", "attitude/theta-rad", "attitude/psi-rad")
        self._att_nodes = [node(n) for n in names]
        names = ("position/lat-geod-deg", "position/long-gc-deg", "position/h-sl-meters")
        self._pos_nodes = [node(n) for n in names]
        names = ("velocities/v-north-fps", "velocities/v-east-fps", "velocities/v-down-fps")
        self._vel_nodes = [node(n) for n in names]
        names = ("atmosphere/wind-north-fps", "atmosphere/wind-east-fps", "atmosphere/wind-down-fps")
        self._wind_nodes = [node(n) for n in names]
        names = (
            "accelerations/a-pilot-x-ft_sec2",
            "accelerations/a-pilot-y-ft_sec2",
            "accelerations/a-pilot-z-ft_sec2",
        )
        self._acc_nodes = [node(n) for n in names]
        self.p_rad_s = self.q_rad_s = self.r_rad_s = 0.0
        self.roll_rad = self.pitch_rad = 0.0
        self.yaw_rad = spawn_yaw_rad
        self._read_fast()

    def _read_fast(self) -> None:
        p, q, r = self._rate_nodes
        self.p_rad_s = p.get_double_value()
        self.q_rad_s = q.get_double_value()
        self.r_rad_s = r.get_double_value()
        phi, theta, psi = self._att_nodes
        self.roll_rad = phi.get_double_value()
        self.pitch_rad = theta.get_double_value()
        yaw = psi.get_double_value()
        self.yaw_rad = yaw - 2.0 * math.pi if yaw > math.pi else yaw

    def step(self, u0: float, u1: float, u2: float, u3: float) -> None:
        """Advance one physics tick with normalised motor commands (0..1, PX4 motor order)."""
        c = self._cmd
        c[0].set_double_value(u0)
        c[1].set_double_value(u1)
        c[2].set_double_value(u2)
        c[3].set_double_value(u3)
        self._fdm.run()
        # _read_fast, inlined: this runs 250 times per sim second per vehicle.
        p, q, r = self._rate_nodes
        self.p_rad_s = p.get_double_value()
        self.q_rad_s = q.get_double_value()
        self.r_rad_s = r.get_double_value()
        phi, theta, psi = self._att_nodes
        self.roll_rad = phi.get_double_value()
        self.pitch_rad = theta.get_double_value()
        yaw = psi.get_double_value()
        self.yaw_rad = yaw - 2.0 * math.pi if yaw > math.pi else yaw

    def set_wind_ned(self, wind_n_m_s: float, wind_e_m_s: float, wind_d_m_s: float) -> None:
        """Air-mass velocity in NED (the direction the air moves towards), m/s."""
        n, e, d = self._wind_nodes
        n.set_double_value(wind_n_m_s / _FT)
        e.set_double_value(wind_e_m_s / _FT)
        d.set_double_value(wind_d_m_s / _FT)

    def kinematics(self) -> tuple[float, float, float, float, float, float]:
        """(north, east, down) in world NED, m, and (vn, ve, vd), m/s."""
        lat, lon, h = self._pos_nodes
        n_m, e_m, d_m = self._world.to_ned(
            lat.get_double_value(), lon.get_double_value(), h.get_double_value()
        )
        vn, ve, vd = self._vel_nodes
        return (
            n_m,
            e_m,
            d_m,
            vn.get_double_value() * _FT,
            ve.get_double_value() * _FT,
            vd.get_double_value() * _FT,
        )

    def specific_force_body(self) -> tuple[float, float, float]:
        """What an accelerometer at the CG measures, body FRD, m/s^2 (about (0, 0, -g) at rest)."""
        x, y, z = self._acc_nodes
        return x.get_double_value() * _FT, y.get_double_value() * _FT, z.get_double_value() * _FT

    def truth(self, t_s: float) -> VehicleTruth:
        """The full true state (allocates arrays: call it at render or log rate, not per tick)."""
        n, e, d, vn, ve, vd = self.kinematics()
        q = quat_from_R(R_from_euler(self.roll_rad, self.pitch_rad, self.yaw_rad))
        return VehicleTruth(
            t_s=t_s,
            p_ned_m=np.array([n, e, d]),
            v_ned_m_s=np.array([vn, ve, vd]),
            q_ned_body_wxyz=q,
            omega_body_rad_s=np.array([self.p_rad_s, self.q_rad_s, self.r_rad_s]),
        )
