"""The leader: quad-X airframes (body, four arms, motors, rotor discs, landing gear) in body FRD.

Five looks so the detector does not learn one: an F450 kit frame, a Phantom-like white shell, a 5-inch
racer, a heavy-lift quad and a micro quad with prop guards. A sixth, a yellow hexacopter (``hexa``), is
never drawn by the dataset generator: it is the airframe a detector has not seen, for fine-tuning tests.
Geometry is built at the airframe's usual size and scaled uniformly to ``LeaderLook.span_m``
(motor-to-motor diagonal). Quad motors sit at +-45 and +-135 deg (quad-X), the hexa's every 60 deg from
30 deg; rotor discs spin in the body x-y plane above the motors (z is down in FRD).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from sitl.render.config import AIRFRAME_SPAN_M, RGB, LeaderLook
from sitl.render.meshes import (
    F32,
    Kind,
    Mesh,
    MeshBuilder,
    Ry,
    Rz,
    box,
    concat,
    cylinder,
    disc,
    double_sided,
    ellipsoid,
)

_MOTOR_ANGLES_RAD = (math.radians(45.0), math.radians(135.0), math.radians(-135.0), math.radians(-45.0))


@dataclass(frozen=True, slots=True)
class LeaderModel:
    """Vertex arrays of a leader in body FRD, m, plus what truth and tests need to know about it."""

    opaque: F32
    #: Rotor discs, drawn translucent after everything opaque.
    rotors: F32
    #: Radius of a sphere about the body origin that contains the whole model (props included), m.
    bound_radius_m: float
    #: Half extents of the central hub box (x, y, z), m: what a ray through the centre hits first.
    hub_half_m: tuple[float, float, float]
    span_m: float


@dataclass(frozen=True, slots=True)
class _Livery:
    body: RGB
    arm: RGB
    accent: RGB
    prop: RGB


_LIVERIES: dict[str, _Livery] = {
    "f450": _Livery((0.03, 0.03, 0.035), (0.70, 0.70, 0.68), (0.55, 0.03, 0.02), (0.02, 0.02, 0.02)),
    "phantom": _Livery((0.78, 0.78, 0.76), (0.78, 0.78, 0.76), (0.45, 0.32, 0.08), (0.75, 0.75, 0.75)),
    "racer": _Livery((0.02, 0.02, 0.02), (0.025, 0.025, 0.025), (0.80, 0.22, 0.02), (0.60, 0.30, 0.02)),
    "heavy": _Livery((0.06, 0.06, 0.065), (0.02, 0.02, 0.02), (0.75, 0.50, 0.02), (0.03, 0.03, 0.03)),
    "micro": _Livery((0.02, 0.02, 0.02), (0.03, 0.03, 0.03), (0.65, 0.05, 0.03), (0.55, 0.55, 0.55)),
    "hexa": _Livery((0.85, 0.65, 0.02), (0.80, 0.80, 0.78), (0.10, 0.30, 0.75), (0.60, 0.60, 0.62)),
}


def _arm(r0: float, r1: float, width: float, thick: float, angle: float, *, z: float = 0.0) -> Mesh:
    """A rectangular arm along a body-frame azimuth from radius r0 to r1."""
    length = r1 - r0
    m = box((length, width, thick), ((r0 + r1) / 2.0, 0.0, z))
    return m.transformed(Rz(angle))


def _tube(
    p0: tuple[float, float, float], p1: tuple[float, float, float], radius: float, seg: int = 6
) -> Mesh:
    """A thin cylinder between two points."""
    a, b = np.asarray(p0, dtype=np.float64), np.asarray(p1, dtype=np.float64)
    d = b - a
    length = float(np.linalg.norm(d))
    m = cylinder(radius, 0.0, length, seg, caps=False)
    z = d / length
    helper = np.array([1.0, 0.0, 0.0]) if abs(z[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    return m.transformed(np.column_stack([x, y, z]), a)


def _motor_xy(r: float, angle: float) -> tuple[float, float]:
    return r * math.cos(angle), r * math.sin(angle)


def _rotors(r_motor: float, r_prop: float, z_prop: float, b: MeshBuilder, rgb: RGB) -> None:
    for ang in _MOTOR_ANGLES_RAD:
        x, y = _motor_xy(r_motor, ang)
        b.add(double_sided(disc(r_prop, 20)).transformed(t=(x, y, z_prop)), rgb, Kind.ROTOR)


def _motors(b: MeshBuilder, r_motor: float, radius: float, z_top: float, z_bot: float, *, rgb: RGB) -> None:
    for ang in _MOTOR_ANGLES_RAD:
        x, y = _motor_xy(r_motor, ang)
        b.add(cylinder(radius, z_top, z_bot, 10).transformed(t=(x, y, 0.0)), rgb, Kind.METAL)
        b.add(cylinder(radius * 0.35, z_top - 0.008, z_top, 6).transformed(t=(x, y, 0.0)), rgb, Kind.METAL)


def _leds(b: MeshBuilder, r: float, z: float, size: float) -> None:
    for ang, rgb in zip(
        _MOTOR_ANGLES_RAD,
        ((0.0, 1.5, 0.1), (1.5, 0.02, 0.02), (1.5, 0.02, 0.02), (0.0, 1.5, 0.1)),
        strict=True,
    ):
        x, y = _motor_xy(r, ang)
        b.add(box((size, size, size * 0.6), (x, y, z)), rgb, Kind.EMISSIVE)


def _f450(b: MeshBuilder, rot: MeshBuilder, lv: _Livery) -> tuple[float, float, tuple[float, float, float]]:
    r_m, r_p = 0.225, 0.127
    hub = (0.045, 0.045, 0.022)
    b.add(box((2 * hub[0], 2 * hub[1], 2 * hub[2])), lv.body, Kind.PLAIN)
    b.add(box((0.15, 0.13, 0.004), (0.0, 0.0, -0.024)), lv.arm, Kind.GLOSSY)
    b.add(box((0.15, 0.13, 0.004), (0.0, 0.0, 0.024)), (0.05, 0.12, 0.05), Kind.PLAIN)
    b.add(box((0.05, 0.04, 0.015), (0.0, 0.0, -0.034)), (0.02, 0.02, 0.02), Kind.PLAIN)
    b.add(_tube((-0.03, 0.0, -0.03), (-0.03, 0.0, -0.10), 0.004), (0.05, 0.05, 0.05), Kind.PLAIN)
    b.add(
        cylinder(0.03, -0.112, -0.100, 10).transformed(t=(-0.03, 0.0, 0.0)), (0.05, 0.05, 0.05), Kind.GLOSSY
    )
    b.add(
        box((0.13, 0.045, 0.035), (0.0, 0.0, 0.045)),
        lv.accent if lv.accent[2] > 0.3 else (0.05, 0.08, 0.3),
        Kind.PLAIN,
    )
    for i, ang in enumerate(_MOTOR_ANGLES_RAD):
        colour = lv.accent if i in (0, 3) else lv.arm  # front arms in the accent colour, as on kit frames
        b.add(_arm(0.04, r_m + 0.02, 0.04, 0.022, ang, z=0.0), colour, Kind.GLOSSY)
    _motors(b, r_m, 0.014, -0.045, -0.011, rgb=(0.35, 0.35, 0.37))
    _leds(b, r_m - 0.03, 0.016, 0.012)
    for sx in (1.0, -1.0):
        for sy in (1.0, -1.0):
            foot = (sx * 0.10, sy * 0.10, 0.17)
            b.add(_tube((sx * 0.045, sy * 0.045, 0.02), foot, 0.006), (0.03, 0.03, 0.03), Kind.PLAIN)
            b.add(ellipsoid((0.012, 0.012, 0.012), 6, 4).transformed(t=foot), (0.02, 0.02, 0.02), Kind.PLAIN)
    _rotors(r_m, r_p, -0.05, rot, lv.prop)
    return r_m, r_p, hub


def _phantom(
    b: MeshBuilder, rot: MeshBuilder, lv: _Livery
) -> tuple[float, float, tuple[float, float, float]]:
    r_m, r_p = 0.175, 0.12
    hub = (0.075, 0.06, 0.045)
    b.add(ellipsoid((0.13, 0.10, 0.05), 14, 8), lv.body, Kind.GLOSSY)
    b.add(box((2 * hub[0], 2 * hub[1], 2 * hub[2])), lv.body, Kind.GLOSSY)
    b.add(box((0.16, 0.02, 0.003), (0.0, 0.0, -0.05)), lv.accent, Kind.GLOSSY)
    for ang in _MOTOR_ANGLES_RAD:
        b.add(_arm(0.05, r_m, 0.035, 0.026, ang, z=-0.005), lv.arm, Kind.GLOSSY)
        b.add(_arm(0.07, r_m - 0.02, 0.012, 0.002, ang, z=-0.019), lv.accent, Kind.GLOSSY)
    _motors(b, r_m, 0.018, -0.045, 0.01, rgb=lv.body)
    _leds(b, r_m, 0.018, 0.01)
    for sy in (1.0, -1.0):
        for sx in (1.0, -1.0):
            b.add(
                _tube((sx * 0.04, sy * 0.05, 0.03), (sx * 0.06, sy * 0.10, 0.16), 0.006), lv.body, Kind.GLOSSY
            )
        b.add(_tube((-0.1, sy * 0.10, 0.16), (0.1, sy * 0.10, 0.16), 0.007), lv.body, Kind.GLOSSY)
    b.add(box((0.04, 0.035, 0.03), (0.07, 0.0, 0.07)), (0.03, 0.03, 0.03), Kind.METAL)
    b.add(_tube((0.06, 0.0, 0.04), (0.06, 0.0, 0.06), 0.008), (0.4, 0.4, 0.4), Kind.METAL)
    _rotors(r_m, r_p, -0.05, rot, lv.prop)
    return r_m, r_p, hub


def _racer(b: MeshBuilder, rot: MeshBuilder, lv: _Livery) -> tuple[float, float, tuple[float, float, float]]:
    r_m, r_p = 0.11, 0.064
    hub = (0.04, 0.02, 0.016)
    b.add(box((2 * hub[0], 2 * hub[1], 2 * hub[2])), lv.body, Kind.PLAIN)
    b.add(box((0.075, 0.035, 0.028), (0.0, 0.0, -0.034)), (0.15, 0.15, 0.02), Kind.PLAIN)
    b.add(box((0.05, 0.03, 0.02), (0.01, 0.0, -0.022)).transformed(Ry(0.3)), lv.accent, Kind.GLOSSY)
    b.add(box((0.016, 0.016, 0.016), (0.045, 0.0, -0.005)), (0.02, 0.02, 0.02), Kind.METAL)
    for ang in _MOTOR_ANGLES_RAD:
        b.add(_arm(0.015, r_m + 0.012, 0.024, 0.005, ang, z=0.004), lv.arm, Kind.PLAIN)
    _motors(b, r_m, 0.013, -0.022, 0.0, rgb=(0.4, 0.4, 0.42))
    b.add(_tube((-0.04, 0.0, -0.015), (-0.07, 0.0, -0.06), 0.002), (0.02, 0.02, 0.02), Kind.PLAIN)
    _rotors(r_m, r_p, -0.026, rot, lv.prop)
    return r_m, r_p, hub


def _heavy(b: MeshBuilder, rot: MeshBuilder, lv: _Livery) -> tuple[float, float, tuple[float, float, float]]:
    r_m, r_p = 0.45, 0.20
    hub = (0.15, 0.125, 0.06)
    b.add(box((2 * hub[0], 2 * hub[1], 2 * hub[2])), lv.body, Kind.PLAIN)
    b.add(ellipsoid((0.12, 0.10, 0.05), 12, 6).transformed(t=(0.0, 0.0, -0.06)), lv.body, Kind.GLOSSY)
    b.add(box((0.3, 0.03, 0.004), (0.0, 0.08, -0.061)), lv.accent, Kind.PLAIN)
    b.add(box((0.3, 0.03, 0.004), (0.0, -0.08, -0.061)), lv.accent, Kind.PLAIN)
    b.add(box((0.22, 0.14, 0.07), (0.0, 0.0, 0.095)), (0.08, 0.08, 0.09), Kind.PLAIN)
    for ang in _MOTOR_ANGLES_RAD:
        x, y = _motor_xy(r_m, ang)
        b.add(_tube((0.0, 0.0, -0.02), (x, y, -0.02), 0.016, 8), lv.arm, Kind.GLOSSY)
    _motors(b, r_m, 0.032, -0.08, -0.005, rgb=(0.05, 0.05, 0.05))
    _leds(b, r_m, 0.005, 0.02)
    for sy in (1.0, -1.0):
        for sx in (1.0, -1.0):
            b.add(
                _tube((sx * 0.1, sy * 0.1, 0.06), (sx * 0.12, sy * 0.22, 0.32), 0.01),
                (0.02, 0.02, 0.02),
                Kind.PLAIN,
            )
        b.add(_tube((-0.22, sy * 0.22, 0.32), (0.22, sy * 0.22, 0.32), 0.012), (0.02, 0.02, 0.02), Kind.PLAIN)
    _rotors(r_m, r_p, -0.085, rot, lv.prop)
    return r_m, r_p, hub


def _micro(b: MeshBuilder, rot: MeshBuilder, lv: _Livery) -> tuple[float, float, tuple[float, float, float]]:
    r_m, r_p = 0.06, 0.028
    hub = (0.025, 0.02, 0.012)
    b.add(ellipsoid((0.035, 0.028, 0.014), 12, 6), lv.body, Kind.GLOSSY)
    b.add(box((2 * hub[0], 2 * hub[1], 2 * hub[2])), lv.body, Kind.GLOSSY)
    b.add(ellipsoid((0.015, 0.012, 0.006), 8, 4).transformed(t=(0.008, 0.0, -0.012)), lv.accent, Kind.GLOSSY)
    for ang in _MOTOR_ANGLES_RAD:
        b.add(_arm(0.02, r_m, 0.008, 0.006, ang, z=0.0), lv.arm, Kind.PLAIN)
        x, y = _motor_xy(r_m, ang)
        guard = double_sided(cylinder(r_p + 0.004, -0.012, -0.004, 16, caps=False))
        b.add(guard.transformed(t=(x, y, 0.0)), lv.arm, Kind.PLAIN)
        for leg_z in (0.012, 0.02):
            b.add(box((0.004, 0.004, 0.02), (x * 0.7, y * 0.7, leg_z)), lv.arm, Kind.PLAIN)
    _motors(b, r_m, 0.006, -0.014, 0.002, rgb=(0.5, 0.5, 0.5))
    _rotors(r_m, r_p, -0.016, rot, lv.prop)
    return r_m, r_p, hub


def _hexa(b: MeshBuilder, rot: MeshBuilder, lv: _Livery) -> tuple[float, float, tuple[float, float, float]]:
    r_m, r_p = 0.275, 0.11
    hub = (0.07, 0.07, 0.03)
    angles = [math.radians(30.0 + 60.0 * i) for i in range(6)]
    b.add(cylinder(0.085, -0.03, 0.03, 6), lv.body, Kind.GLOSSY)  # a hexagonal centre plate stack
    b.add(ellipsoid((0.07, 0.07, 0.045), 12, 6).transformed(t=(0.0, 0.0, -0.04)), lv.body, Kind.GLOSSY)
    b.add(box((0.05, 0.02, 0.01), (0.06, 0.0, -0.03)), lv.accent, Kind.GLOSSY)
    for ang in angles:
        x, y = _motor_xy(r_m, ang)
        b.add(_tube((0.0, 0.0, -0.005), (x, y, -0.005), 0.011, 8), lv.arm, Kind.GLOSSY)
        b.add(cylinder(0.02, -0.04, 0.0, 10).transformed(t=(x, y, 0.0)), lv.accent, Kind.METAL)
        rot.add(double_sided(disc(r_p, 20)).transformed(t=(x, y, -0.045)), lv.prop, Kind.ROTOR)
    for sy in (1.0, -1.0):
        for sx in (1.0, -1.0):
            b.add(
                _tube((sx * 0.05, sy * 0.05, 0.03), (sx * 0.07, sy * 0.13, 0.19), 0.006), lv.arm, Kind.PLAIN
            )
        b.add(_tube((-0.13, sy * 0.13, 0.19), (0.13, sy * 0.13, 0.19), 0.007), lv.arm, Kind.PLAIN)
    return r_m, r_p, hub


_BUILDERS = {
    "f450": _f450,
    "phantom": _phantom,
    "racer": _racer,
    "heavy": _heavy,
    "micro": _micro,
    "hexa": _hexa,
}


def build_leader(look: LeaderLook) -> LeaderModel:
    """Vertex arrays for a leader look, scaled to its span."""
    lv0 = _LIVERIES[look.airframe]
    lv = _Livery(
        look.body_rgb or lv0.body,
        look.arm_rgb or lv0.arm,
        look.accent_rgb or lv0.accent,
        look.prop_rgb or lv0.prop,
    )
    body, rot = MeshBuilder(), MeshBuilder()
    _, _, hub = _BUILDERS[look.airframe](body, rot, lv)
    scale = look.resolved_span_m / AIRFRAME_SPAN_M[look.airframe]
    opaque, rotors = body.build(), rot.build()
    for arr in (opaque, rotors):
        arr[:, 0:3] *= scale
    radius = float(np.max(np.linalg.norm(np.concatenate([opaque[:, :3], rotors[:, :3]]), axis=1)))
    hub_s = (hub[0] * scale, hub[1] * scale, hub[2] * scale)
    return LeaderModel(opaque, rotors, radius, hub_s, look.resolved_span_m)


def leader_triangles_m(model: LeaderModel) -> np.ndarray:
    """All triangles of a leader (opaque and rotor discs) as (T, 3, 3) body-frame vertices, m."""
    pos = np.concatenate([model.opaque[:, :3], model.rotors[:, :3]]).astype(np.float64)
    return pos.reshape(-1, 3, 3)


__all__ = ["LeaderModel", "build_leader", "concat", "leader_triangles_m"]
