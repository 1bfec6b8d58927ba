"""Triangle-mesh primitives and the vertex layout the shaders read. Pure numpy, no GL.

Meshes are non-indexed triangle lists with outward faces counter-clockwise in a right-handed frame
(NED and FRD both are). One vertex is 12 float32: position (3), normal (3), linear albedo RGB (3),
pattern coordinates ``uv`` (2, metres or a local parameterisation, per material) and the material
``kind`` (1, one of :class:`Kind`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

F32 = NDArray[np.float32]
F64 = NDArray[np.float64]

#: Floats per vertex: pos 3, normal 3, rgb 3, uv 2, kind 1.
VERTEX_FLOATS = 12
#: moderngl buffer format of one vertex, matching the attribute names in the shaders.
VERTEX_FORMAT = "3f 3f 3f 2f 1f"
VERTEX_ATTRIBUTES = ("in_pos", "in_nrm", "in_rgb", "in_uv", "in_kind")


class Kind(IntEnum):
    """Material kinds; the scene shader branches on these (keep in sync with ``shaders.py``)."""

    PLAIN = 0
    GLOSSY = 1
    GROUND = 2
    WALL = 3
    ROOF = 4
    FOLIAGE = 5
    BARK = 6
    ROTOR = 7
    METAL = 8
    DISTANT = 9
    EMISSIVE = 10


@dataclass(frozen=True, slots=True)
class Mesh:
    """A triangle list: ``pos``, ``nrm`` (N x 3) and ``uv`` (N x 2), N a multiple of 3."""

    pos: F64
    nrm: F64
    uv: F64

    def transformed(self, R: F64 | None = None, t: F64 | tuple[float, float, float] | None = None) -> Mesh:
        """Rotated by R then translated by t (normals rotated only)."""
        pos, nrm = self.pos, self.nrm
        if R is not None:
            pos = pos @ R.T
            nrm = nrm @ R.T
        if t is not None:
            pos = pos + np.asarray(t, dtype=np.float64)
        return Mesh(pos, nrm, self.uv)

    def scaled(self, s: tuple[float, float, float]) -> Mesh:
        """Non-uniform scale (normals fixed with the inverse transpose)."""
        sv = np.asarray(s, dtype=np.float64)
        nrm = self.nrm / sv
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
        return Mesh(self.pos * sv, nrm, self.uv)

    @property
    def n_vertices(self) -> int:
        return int(self.pos.shape[0])


def _tri_normals(pos: F64) -> F64:
    a, b, c = pos[0::3], pos[1::3], pos[2::3]
    n = np.cross(b - a, c - a)
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    return np.repeat(n, 3, axis=0)


def quads_to_mesh(quads: F64, uvs: F64 | None = None, smooth_nrm: F64 | None = None) -> Mesh:
    """Quads (Q x 4 x 3, counter-clockwise seen from outside) to a triangle mesh."""
    idx = [0, 1, 2, 0, 2, 3]
    pos = quads[:, idx, :].reshape(-1, 3)
    uv = uvs[:, idx, :].reshape(-1, 2) if uvs is not None else np.zeros((pos.shape[0], 2))
    nrm = smooth_nrm[:, idx, :].reshape(-1, 3) if smooth_nrm is not None else _tri_normals(pos)
    return Mesh(pos, nrm, uv)


def box(size: tuple[float, float, float], center: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Mesh:
    """Axis-aligned box; uv in metres along each face (for wall patterns: u horizontal, v along -z)."""
    sx, sy, sz = (s / 2.0 for s in size)
    c = np.asarray(center, dtype=np.float64)
    # Each face: 4 corners counter-clockwise seen from outside (right-handed frame).
    faces = np.array(
        [
            [[sx, sy, -sz], [sx, sy, sz], [sx, -sy, sz], [sx, -sy, -sz]],  # +x
            [[-sx, -sy, -sz], [-sx, -sy, sz], [-sx, sy, sz], [-sx, sy, -sz]],  # -x
            [[-sx, sy, -sz], [-sx, sy, sz], [sx, sy, sz], [sx, sy, -sz]],  # +y
            [[sx, -sy, -sz], [sx, -sy, sz], [-sx, -sy, sz], [-sx, -sy, -sz]],  # -y
            [[sx, sy, sz], [-sx, sy, sz], [-sx, -sy, sz], [sx, -sy, sz]],  # +z
            [[sx, -sy, -sz], [-sx, -sy, -sz], [-sx, sy, -sz], [sx, sy, -sz]],  # -z
        ]
    )
    w = [2 * sy, 2 * sy, 2 * sx, 2 * sx, 2 * sx, 2 * sx]
    h = [2 * sz, 2 * sz, 2 * sz, 2 * sz, 2 * sy, 2 * sy]
    uvs = np.array([[[0.0, h[i]], [0.0, 0.0], [w[i], 0.0], [w[i], h[i]]] for i in range(6)])
    m = quads_to_mesh(faces, uvs)
    return m.transformed(t=c)


def cylinder(radius: float, z0: float, z1: float, segments: int = 12, caps: bool = True) -> Mesh:
    """Cylinder along the z axis from z0 to z1 (z0 < z1), smooth sides; uv = (arc m, z m)."""
    th = np.linspace(0.0, 2.0 * math.pi, segments + 1)
    c, s = np.cos(th), np.sin(th)
    quads, uvs, nrms = [], [], []
    for i in range(segments):
        a = (radius * c[i], radius * s[i])
        b = (radius * c[i + 1], radius * s[i + 1])
        # Seen from outside, CCW: (a, z1) (a, z0)?  Order a@z0 -> b@z0 -> b@z1 -> a@z1 gives normal
        # (b - a) x (z) which points outward for increasing theta in a right-handed frame.
        quads.append([[a[0], a[1], z0], [b[0], b[1], z0], [b[0], b[1], z1], [a[0], a[1], z1]])
        na, nb = (c[i], s[i], 0.0), (c[i + 1], s[i + 1], 0.0)
        nrms.append([na, nb, nb, na])
        u0, u1 = radius * th[i], radius * th[i + 1]
        uvs.append([[u0, z0], [u1, z0], [u1, z1], [u0, z1]])
    side = quads_to_mesh(np.array(quads), np.array(uvs), np.array(nrms))
    if not caps:
        return side
    return concat(
        [
            side,
            disc(radius, segments).transformed(t=(0.0, 0.0, z1)),
            _flip(disc(radius, segments)).transformed(t=(0.0, 0.0, z0)),
        ]
    )


def cone(radius: float, z_base: float, z_tip: float, segments: int = 10) -> Mesh:
    """Cone along z, base disc at ``z_base`` and apex at ``z_tip`` (either order), smooth sides."""
    th = np.linspace(0.0, 2.0 * math.pi, segments + 1)
    h = z_tip - z_base
    slope = radius / abs(h)
    pos, nrm, uv = [], [], []
    sgn = 1.0 if h > 0 else -1.0
    for i in range(segments):
        a = np.array([radius * math.cos(th[i]), radius * math.sin(th[i]), z_base])
        b = np.array([radius * math.cos(th[i + 1]), radius * math.sin(th[i + 1]), z_base])
        tip = np.array([0.0, 0.0, z_tip])
        tri = [a, b, tip] if sgn > 0 else [b, a, tip]
        pos.extend(tri)
        for p in tri:
            ang = math.atan2(p[1], p[0]) if p is not tip else 0.5 * (th[i] + th[i + 1])
            n = np.array([math.cos(ang), math.sin(ang), -sgn * slope])
            nrm.append(n / np.linalg.norm(n))
            uv.append([radius * ang, p[2]])
    side = Mesh(np.array(pos), np.array(nrm), np.array(uv))
    base = disc(radius, segments)
    base = (
        base.transformed(t=(0.0, 0.0, z_base)) if sgn < 0 else _flip(base).transformed(t=(0.0, 0.0, z_base))
    )
    return concat([side, base])


def disc(radius: float, segments: int = 16) -> Mesh:
    """Flat disc in the z = 0 plane facing +z; uv = local (x, y) / radius in [-1, 1]."""
    th = np.linspace(0.0, 2.0 * math.pi, segments + 1)
    pos = []
    for i in range(segments):
        pos.extend(
            [
                [0.0, 0.0, 0.0],
                [radius * math.cos(th[i]), radius * math.sin(th[i]), 0.0],
                [radius * math.cos(th[i + 1]), radius * math.sin(th[i + 1]), 0.0],
            ]
        )
    p = np.array(pos)
    return Mesh(p, np.tile([0.0, 0.0, 1.0], (p.shape[0], 1)), p[:, :2] / radius)


def _flip(m: Mesh) -> Mesh:
    """Reverse winding and normals."""
    idx = np.arange(m.n_vertices).reshape(-1, 3)[:, ::-1].reshape(-1)
    return Mesh(m.pos[idx], -m.nrm[idx], m.uv[idx])


def double_sided(m: Mesh) -> Mesh:
    """The mesh plus its reverse (for thin sheets seen from both sides: wings, discs)."""
    return concat([m, _flip(m)])


def ellipsoid(radii: tuple[float, float, float], seg_u: int = 10, seg_v: int = 6) -> Mesh:
    """Ellipsoid centred at the origin with smooth normals; uv = (longitude, latitude) in rad."""
    r = np.asarray(radii, dtype=np.float64)
    lon = np.linspace(0.0, 2.0 * math.pi, seg_u + 1)
    lat = np.linspace(-math.pi / 2.0, math.pi / 2.0, seg_v + 1)
    LO, LA = np.meshgrid(lon, lat, indexing="xy")  # (seg_v + 1, seg_u + 1)
    d = np.stack([np.cos(LA) * np.cos(LO), np.cos(LA) * np.sin(LO), np.sin(LA)], axis=-1)
    pos = d * r
    nrm = d / r
    nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
    uvg = np.stack([LO, LA], axis=-1)

    # Quad corners (i, j), (i+1, j), (i+1, j+1), (i, j+1): counter-clockwise seen from outside.
    def corners(a: F64) -> F64:
        return np.stack([a[:-1, :-1], a[:-1, 1:], a[1:, 1:], a[1:, :-1]], axis=2).reshape(-1, 4, a.shape[-1])

    return quads_to_mesh(corners(pos), corners(uvg), corners(nrm))


def concat(meshes: list[Mesh]) -> Mesh:
    """One mesh from many."""
    return Mesh(
        np.concatenate([m.pos for m in meshes]),
        np.concatenate([m.nrm for m in meshes]),
        np.concatenate([m.uv for m in meshes]),
    )


class MeshBuilder:
    """Accumulates coloured, typed meshes into one interleaved float32 vertex array."""

    def __init__(self) -> None:
        self._parts: list[F32] = []

    def add(self, mesh: Mesh, rgb: tuple[float, float, float], kind: float) -> None:
        """Append a mesh; ``kind`` is a :class:`Kind`, plus a material parameter in [0, 1) for some."""
        n = mesh.n_vertices
        if n == 0:
            return
        v = np.empty((n, VERTEX_FLOATS), dtype=np.float32)
        v[:, 0:3] = mesh.pos
        v[:, 3:6] = mesh.nrm
        v[:, 6:9] = rgb
        v[:, 9:11] = mesh.uv
        v[:, 11] = float(kind)
        self._parts.append(v)

    def build(self) -> F32:
        if not self._parts:
            return np.zeros((0, VERTEX_FLOATS), dtype=np.float32)
        return np.concatenate(self._parts)


def Rz(angle_rad: float) -> F64:
    """Rotation about z (yaw in NED/FRD)."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def Ry(angle_rad: float) -> F64:
    """Rotation about y."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def Rx(angle_rad: float) -> F64:
    """Rotation about x."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
