"""Distractors: birds, balloons, small aeroplanes and debris that a dataset scatters around the leader.

Pure numpy: meshes in their own frame, and :func:`distractor_vertices` to place them (NED) for a frame.
"""

from __future__ import annotations

import numpy as np

from sitl.render.config import RGB
from sitl.render.meshes import (
    F32,
    F64,
    Kind,
    Mesh,
    MeshBuilder,
    Rx,
    box,
    concat,
    cylinder,
    double_sided,
    ellipsoid,
    quads_to_mesh,
)


def bird_mesh(span_m: float, flap_rad: float) -> Mesh:
    """A bird in its own frame (x forward, z down): slim body, two wings raised by ``flap_rad``."""
    body = ellipsoid((span_m * 0.22, span_m * 0.06, span_m * 0.06), 8, 4)
    half = span_m / 2.0
    chord = span_m * 0.22
    wing = np.array(
        [
            [
                [chord * 0.4, 0.0, 0.0],
                [chord * 0.1, half, 0.0],
                [-chord * 0.3, half * 0.9, 0.0],
                [-chord * 0.6, 0.0, 0.0],
            ]
        ]
    )
    w_mesh = double_sided(quads_to_mesh(wing))
    right = w_mesh.transformed(Rx(-flap_rad))
    left = w_mesh.transformed(np.diag([1.0, -1.0, 1.0])).transformed(Rx(flap_rad))
    left = Mesh(left.pos[np.arange(left.n_vertices).reshape(-1, 3)[:, ::-1].reshape(-1)], -left.nrm, left.uv)
    tail = double_sided(
        quads_to_mesh(
            np.array(
                [
                    [
                        [-chord * 0.5, -span_m * 0.04, 0.0],
                        [-chord * 0.5, span_m * 0.04, 0.0],
                        [-chord * 1.1, span_m * 0.07, 0.0],
                        [-chord * 1.1, -span_m * 0.07, 0.0],
                    ]
                ]
            )
        )
    )
    return concat([body, right, left, tail])


def balloon_mesh(radius_m: float) -> Mesh:
    """A party balloon with a short string hanging below it (+z)."""
    return concat(
        [
            ellipsoid((radius_m, radius_m, radius_m * 1.15), 10, 6),
            cylinder(radius_m * 0.02, 0.0, radius_m * 4.0, 4, caps=False).transformed(t=(0.0, 0.0, radius_m)),
        ]
    )


def plane_mesh(span_m: float) -> Mesh:
    """A small aeroplane: fuselage, wing, tailplane, fin."""
    length = span_m * 0.8
    return concat(
        [
            ellipsoid((length / 2.0, span_m * 0.05, span_m * 0.06), 10, 5),
            box((span_m * 0.16, span_m, span_m * 0.015)),
            box((span_m * 0.08, span_m * 0.35, span_m * 0.01), (-length * 0.42, 0.0, 0.0)),
            box((span_m * 0.1, span_m * 0.01, span_m * 0.14), (-length * 0.42, 0.0, -span_m * 0.07)),
        ]
    )


def debris_mesh(size_m: float) -> Mesh:
    """A tumbling leaf or plastic scrap: a crumpled double-sided quad."""
    q = np.array(
        [
            [
                [size_m, 0.0, 0.0],
                [0.0, size_m * 0.6, size_m * 0.2],
                [-size_m, 0.0, 0.0],
                [0.0, -size_m * 0.6, -size_m * 0.2],
            ]
        ]
    )
    return double_sided(quads_to_mesh(q))


def distractor_vertices(items: list[tuple[Mesh, F64, F64, RGB, Kind]]) -> F32:
    """Vertex array of placed distractor meshes: (mesh, R_ned_obj, p_ned_m, rgb, kind) each."""
    b = MeshBuilder()
    for mesh, R, p, rgb, kind in items:
        b.add(mesh.transformed(R, p), rgb, kind)
    return b.build()
