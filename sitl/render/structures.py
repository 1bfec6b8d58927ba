"""Structures standing in the world: buildings, trees, poles, walls and branches, as meshes. Pure numpy.

The world's random ones are scattered by :func:`random_structures`; a scenario's occluders are placed on
purpose. :func:`solid_structures` repeats them without building geometry (the evaluation's collisions).
"""

from __future__ import annotations

import math

import numpy as np

from sitl.render.config import RGB, OccluderSpec, VisualConfig
from sitl.render.meshes import (
    Kind,
    Mesh,
    MeshBuilder,
    Rz,
    box,
    concat,
    cone,
    cylinder,
    ellipsoid,
    quads_to_mesh,
)

#: Colours (linear) the random structures pick from: walls, roofs and tree crowns.
WALL_RGB: tuple[RGB, ...] = (
    (0.45, 0.44, 0.42),
    (0.55, 0.50, 0.42),
    (0.30, 0.12, 0.08),
    (0.65, 0.65, 0.62),
    (0.25, 0.27, 0.30),
)
ROOF_RGB: tuple[RGB, ...] = ((0.12, 0.05, 0.04), (0.08, 0.08, 0.09), (0.25, 0.24, 0.22), (0.05, 0.07, 0.10))
CROWN_RGB: tuple[RGB, ...] = (
    (0.05, 0.10, 0.03),
    (0.07, 0.12, 0.04),
    (0.16, 0.13, 0.10),
    (0.22, 0.12, 0.04),
    (0.12, 0.11, 0.10),
)


def _prism_roof(w: float, d: float, h: float) -> Mesh:
    """A gable roof over a w x d footprint (ridge along x), base at z = 0, apex at z = -h (NED up)."""
    x, y = w / 2.0, d / 2.0
    slopes = np.array(
        [
            [[x, -y, 0.0], [-x, -y, 0.0], [-x, 0.0, -h], [x, 0.0, -h]],
            [[-x, y, 0.0], [x, y, 0.0], [x, 0.0, -h], [-x, 0.0, -h]],
        ]
    )
    uv = np.array([[[0.0, 0.0], [w, 0.0], [w, y], [0.0, y]]] * 2)
    roof = quads_to_mesh(slopes, uv)
    gables = np.array(
        [[[x, y, 0.0], [x, -y, 0.0], [x, 0.0, -h]], [[-x, -y, 0.0], [-x, y, 0.0], [-x, 0.0, -h]]]
    )
    pos = gables.reshape(-1, 3)
    nrm = np.repeat(np.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0]]), 3, axis=0)
    gm = Mesh(pos, nrm, pos[:, [1, 2]] * np.array([1.0, -1.0]))
    return concat([roof, gm])


def add_structure(b: MeshBuilder, spec: OccluderSpec, rng: np.random.Generator) -> None:
    """One building, tree, pole or wall standing at ``spec.p_ned_m``."""
    R = Rz(math.radians(spec.yaw_deg))
    t = np.asarray(spec.p_ned_m, dtype=np.float64)
    w, d, h = spec.resolved_size_m
    if spec.kind == "branch":
        b.add(box((w, d, h)).transformed(R, t), spec.rgb or (0.09, 0.07, 0.05), Kind.BARK)
        return
    t[2] = 0.0  # everything else stands on the ground
    if spec.kind in ("building", "wall"):
        wall = spec.rgb or WALL_RGB[int(rng.integers(len(WALL_RGB)))]
        kind = Kind.WALL if spec.kind == "building" else Kind.PLAIN
        b.add(box((w, d, h), (0.0, 0.0, -h / 2.0)).transformed(R, t), wall, kind)
        if spec.kind == "building":
            roof_rgb = ROOF_RGB[int(rng.integers(len(ROOF_RGB)))]
            if h < 12.0 and rng.random() < 0.6:
                roof = _prism_roof(w * 1.05, d * 1.05, min(w, d) * rng.uniform(0.25, 0.45))
                b.add(roof.transformed(R, t + R @ np.array([0.0, 0.0, -h])), roof_rgb, Kind.ROOF)
            else:
                b.add(box((w, d, 0.3), (0.0, 0.0, -h - 0.15)).transformed(R, t), roof_rgb, Kind.ROOF)
    elif spec.kind == "pole":
        radius = max(w, 0.05)
        rgb = spec.rgb or ((0.22, 0.16, 0.10) if rng.random() < 0.5 else (0.35, 0.35, 0.34))
        b.add(cylinder(radius, -h, 0.0, 8).transformed(R, t), rgb, Kind.BARK)
        b.add(box((0.12, max(d, 1.6), 0.12), (0.0, 0.0, -h + 0.6)).transformed(R, t), rgb, Kind.BARK)
    else:
        crown_w = w
        trunk_r = max(0.08, 0.03 * crown_w)
        sparse = float(rng.uniform(0.05, 0.45))
        rgb = spec.rgb or CROWN_RGB[int(rng.integers(len(CROWN_RGB)))]
        bark = (0.10, 0.08, 0.06)
        if spec.kind == "conifer":
            rgb = spec.rgb or (0.03, 0.065, 0.03)
            b.add(cylinder(trunk_r, -h * 0.3, 0.0, 6).transformed(R, t), bark, Kind.BARK)
            for j, (z0, z1, r) in enumerate(((-0.15, -0.55, 0.5), (-0.4, -0.8, 0.38), (-0.65, -1.0, 0.25))):
                crown = cone(crown_w * r, z0 * h, z1 * h, 10)
                b.add(crown.transformed(R @ Rz(j * 0.7), t), rgb, _foliage_kind(0.1 * sparse))
        else:
            trunk_h = h * rng.uniform(0.3, 0.45)
            b.add(cylinder(trunk_r, -trunk_h - 0.5, 0.0, 6).transformed(R, t), bark, Kind.BARK)
            crown_h = h - trunk_h
            n_blobs = int(rng.integers(1, 4))
            for _ in range(n_blobs):
                off = rng.normal(0.0, crown_w * 0.12, 3) * np.array([1.0, 1.0, 0.5])
                radii = (
                    crown_w / 2.0 * rng.uniform(0.7, 1.0),
                    crown_w / 2.0 * rng.uniform(0.7, 1.0),
                    crown_h / 2.0,
                )
                centre = t + R @ (np.array([0.0, 0.0, -trunk_h - crown_h / 2.0]) + off)
                b.add(
                    ellipsoid(radii, 9, 6).transformed(Rz(rng.uniform(0, 6.3)), centre),
                    rgb,
                    _foliage_kind(sparse),
                )


def _foliage_kind(sparse: float) -> float:
    """Foliage kind with a sparsity in its fractional part (the shader reads fract(kind))."""
    return float(Kind.FOLIAGE) + min(max(sparse, 0.0), 0.95)


def random_structures(visual: VisualConfig, rng: np.random.Generator) -> list[OccluderSpec]:
    """Scatter ``visual.structures`` buildings, trees and poles in the annulus around home."""
    out: list[OccluderSpec] = []
    kinds = ("building", "tree", "conifer", "pole")
    probs = (0.22, 0.45, 0.18, 0.15)
    for _ in range(visual.structures):
        kind = kinds[int(rng.choice(4, p=probs))]
        r = math.sqrt(rng.uniform(visual.clear_radius_m**2, visual.world_radius_m**2))
        a = rng.uniform(0.0, 2.0 * math.pi)
        p = (r * math.cos(a), r * math.sin(a), 0.0)
        if kind == "building":
            size = (rng.uniform(6, 22), rng.uniform(6, 22), rng.uniform(4, 24))
        elif kind in ("tree", "conifer"):
            hgt = rng.uniform(6, 22)
            size = (hgt * rng.uniform(0.35, 0.7), 0.0, hgt)
        else:
            size = (rng.uniform(0.1, 0.2), rng.uniform(1.2, 2.4), rng.uniform(7, 12))
        out.append(OccluderSpec(kind=kind, p_ned_m=p, size_m=size, yaw_deg=float(rng.uniform(0, 360))))
    return out


def solid_structures(visual: VisualConfig) -> tuple[OccluderSpec, ...]:
    """Every structure :func:`build_world` stands in the scene: the random ones and the occluders.

    The random ones are the first draws of the world's generator, so this repeats them exactly without
    building any geometry (the evaluation's collision check needs them, not the meshes).
    """
    rng = np.random.default_rng(visual.seed)
    return (*random_structures(visual, rng), *visual.occluders)
