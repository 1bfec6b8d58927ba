"""The world around the vehicles, from a :class:`VisualConfig`: light, ground style, static geometry.

The structures standing in it are built by :mod:`sitl.render.structures`; what flies through a
dataset's frames is :mod:`sitl.render.distractors`.

Pure numpy: builds vertex arrays and uniform values, uploads nothing. Radiometry is in arbitrary linear
units where a white surface facing a high sun reflects about 3; the camera's auto exposure scales it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from sitl.render.config import RGB, VisualConfig
from sitl.render.meshes import F32, F64, Kind, Mesh, MeshBuilder, quads_to_mesh
from sitl.render.structures import CROWN_RGB, add_structure, random_structures

#: Half side of the square ground plane, m (the far clip plane sits beyond it).
GROUND_HALF_M = 3500.0
CLOUD_ALTITUDE_M = 1200.0
CLOUD_TEXEL_M = 9.0

_GROUND_ALBEDO: dict[str, tuple[RGB, float]] = {
    # material: (linear albedo, stereo texturedness)
    "grass": ((0.075, 0.13, 0.035), 1.0),
    "field": ((0.30, 0.24, 0.12), 0.95),
    "dirt": ((0.20, 0.14, 0.085), 1.0),
    "asphalt": ((0.07, 0.07, 0.075), 0.55),
    "gravel": ((0.26, 0.25, 0.23), 0.9),
    "snow": ((0.75, 0.77, 0.80), 0.25),
}


def _mix(a: RGB, b: RGB, t: float) -> RGB:
    return (a[0] + (b[0] - a[0]) * t, a[1] + (b[1] - a[1]) * t, a[2] + (b[2] - a[2]) * t)


def _scale(a: RGB, s: float) -> RGB:
    return (a[0] * s, a[1] * s, a[2] * s)


def _smoothstep(e0: float, e1: float, x: float) -> float:
    t = min(max((x - e0) / (e1 - e0), 0.0), 1.0)
    return t * t * (3.0 - 2.0 * t)


@dataclass(frozen=True, slots=True)
class Lighting:
    """Uniform values for sun, sky, clouds and fog (linear RGB, arbitrary radiometric units)."""

    sun_dir_ned: tuple[float, float, float]
    sun_rgb: RGB
    sky_rgb: RGB
    bounce_rgb: RGB
    zenith_rgb: RGB
    horizon_rgb: RGB
    glow_rgb: RGB
    haze_rgb: RGB
    cloud_lit_rgb: RGB
    cloud_dark_rgb: RGB
    fog_rgb: RGB
    #: Mean scene radiance an auto exposure would settle on; seeds the first frame's exposure.
    typical_radiance: float


def lighting(visual: VisualConfig) -> Lighting:
    """Sun, sky and cloud colours for the time of day, sun elevation and cloud cover.

    Palettes follow photographs: a clear day sky deep blue at the zenith and pale at the horizon; an
    overcast sky neutral light grey (brightest near the zenith); dusk a dim blue sky with a warm glow
    only towards the sun. Fog takes a neutral version of the horizon colour.
    """
    s = math.sin(math.radians(visual.resolved_sun_elevation_deg))
    day = _smoothstep(0.0, 0.35, s)  # 0 at the horizon (dusk), 1 by mid-morning
    cover = visual.cloud_cover
    overcast = _smoothstep(0.55, 0.95, cover)
    dim = 0.3 + 0.7 * day  # overall light level
    sun_i = 3.2 * _smoothstep(-0.08, 0.35, s) * (1.0 - 0.85 * cover**1.5)
    sun_rgb = _scale(_mix((1.0, 0.45, 0.18), (1.0, 0.96, 0.90), day), sun_i)
    grey_top = _scale((0.80, 0.82, 0.86), dim)
    grey_hor = _scale((0.66, 0.68, 0.72), dim)
    zenith = _mix(_mix((0.05, 0.09, 0.26), (0.10, 0.24, 0.70), day), grey_top, overcast)
    horizon = _mix(_mix((0.34, 0.32, 0.38), (0.52, 0.64, 0.84), day), grey_hor, overcast)
    glow = _scale(_mix((1.0, 0.42, 0.12), (0.25, 0.22, 0.18), day), 1.0 - 0.8 * overcast)
    sky = _scale(_mix(zenith, horizon, 0.5), 0.9)
    ground_albedo = 0.15
    bounce = _scale(_mix(sky, sun_rgb, 0.5), ground_albedo * (0.5 + 0.5 * max(s, 0.0)))
    lit = _mix(_scale((1.0, 0.7, 0.55), 0.8), (1.25, 1.25, 1.27), day)
    lit = _mix(lit, _scale((0.92, 0.93, 0.96), dim), overcast)
    dark = _mix(_scale((0.35, 0.34, 0.40), 0.6), (0.62, 0.64, 0.70), day)
    dark = _mix(dark, _scale((0.55, 0.57, 0.62), dim), overcast)
    lum = (horizon[0] + horizon[1] + horizon[2]) / 3.0
    fog = visual.fog_rgb or _mix(horizon, (lum, lum, lum * 1.04), 0.5)
    typical = 0.5 * (zenith[1] + horizon[1]) * 0.7 + 0.3 * 0.15 * (sun_i * 0.6 + sky[1])
    return Lighting(
        sun_dir_ned=visual.sun_dir_ned,
        sun_rgb=sun_rgb,
        sky_rgb=sky,
        bounce_rgb=bounce,
        zenith_rgb=zenith,
        horizon_rgb=horizon,
        glow_rgb=glow,
        haze_rgb=_mix(fog, (0.1, 0.1, 0.1), 0.2),
        cloud_lit_rgb=lit,
        cloud_dark_rgb=dark,
        fog_rgb=fog,
        typical_radiance=max(typical, 0.01),
    )


#: The ground texture tiles with this period, m (patches, rows and the road are periodic over it).
GROUND_PERIOD_M = 1024.0


@dataclass(frozen=True, slots=True)
class GroundStyle:
    """Uniform values of the ground bake: up to four materials, a road, field rows."""

    rgb: tuple[RGB, RGB, RGB, RGB]
    texturedness: tuple[float, float, float, float]
    n_materials: int
    #: (axis: 0 runs north / 1 runs east, offset m, half width m (0 = none), unused).
    road: tuple[float, float, float, float]
    #: (axis, rows per ground period).
    rows: tuple[float, float]


def ground_style(visual: VisualConfig, rng: np.random.Generator) -> GroundStyle:
    """Ground materials of the configuration plus a random road and field-row direction."""
    mats = list(visual.ground_materials)[:4]
    rgb = [_GROUND_ALBEDO[m][0] for m in mats]
    tex = [_GROUND_ALBEDO[m][1] for m in mats]
    while len(rgb) < 4:
        rgb.append(rgb[-1])
        tex.append(tex[-1])
    road = (0.0, 0.0, 0.0, 0.0)
    if visual.road:
        off = rng.uniform(visual.clear_radius_m * 0.5, max(visual.clear_radius_m, 60.0))
        road = (float(rng.integers(2)), float(off % GROUND_PERIOD_M), float(rng.uniform(2.5, 4.0)), 0.0)
    rows_per_period = float(round(GROUND_PERIOD_M / rng.uniform(2.5, 5.0)))  # > 2 texels: no moire
    return GroundStyle(
        (rgb[0], rgb[1], rgb[2], rgb[3]),
        (tex[0], tex[1], tex[2], tex[3]),
        len(mats),
        road,
        (float(rng.integers(2)), rows_per_period),
    )


def _ring(radius: float, heights: F64, rgb: RGB, kind: float, b: MeshBuilder, *, segments: int = 48) -> None:
    """A vertical band around the origin facing inwards, top edge at the given heights (m, up).

    Added as ``segments`` meshes (world chunks), so that the renderer draws only those in view.
    """
    n = heights.size
    th = np.linspace(0.0, 2.0 * math.pi, n + 1)
    hh = np.append(heights, heights[0])
    x, y = radius * np.cos(th), radius * np.sin(th)
    quads = np.zeros((n, 4, 3))
    uv = np.zeros((n, 4, 2))
    for i in range(n):
        j = i + 1
        # Counter-clockwise seen from the centre (the inside): i bottom, i top, j top, j bottom.
        quads[i] = [[x[i], y[i], 2.0], [x[i], y[i], -hh[i]], [x[j], y[j], -hh[j]], [x[j], y[j], 2.0]]
        arc_i, arc_j = radius * th[i], radius * th[j]
        # v: fraction of the local column (0 foot, 1 top): the shader cuts crowns into the top part.
        uv[i] = [[arc_i, 0.0], [arc_i, 1.0], [arc_j, 1.0], [arc_j, 0.0]]
    m = quads_to_mesh(quads, uv)
    # Normals must point to the centre: flip any that do not.
    inward = -np.column_stack([m.pos[:, 0], m.pos[:, 1], np.zeros(len(m.pos))])
    if float(np.mean(np.sum(m.nrm * inward, axis=1))) < 0:
        idx = np.arange(m.n_vertices).reshape(-1, 3)[:, ::-1].reshape(-1)
        m = Mesh(m.pos[idx], -m.nrm[idx], m.uv[idx])
    per_quad = m.n_vertices // n
    for piece in np.array_split(np.arange(n), min(segments, n)):
        sl = slice(int(piece[0]) * per_quad, (int(piece[-1]) + 1) * per_quad)
        b.add(Mesh(m.pos[sl], m.nrm[sl], m.uv[sl]), rgb, kind)


def _smooth_profile(rng: np.random.Generator, n: int, octaves: int = 5) -> F64:
    """A periodic random profile in [0, 1] over n samples."""
    th = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    p = np.zeros(n)
    for o in range(octaves):
        f = 2**o * 2
        p += (0.6**o) * np.sin(f * th + rng.uniform(0, 2 * math.pi))
    out: F64 = (p - p.min()) / (p.max() - p.min() + 1e-9)
    return out


@dataclass(frozen=True, slots=True)
class Chunks:
    """The world's meshes as the renderer culls them: one per structure part or ring segment.

    Each is a contiguous vertex range of one shader group in ``World.vertices`` with a bounding sphere.
    """

    group: NDArray[np.int64]
    first: NDArray[np.int64]
    count: NDArray[np.int64]
    centre_ned_m: F64
    radius_m: F64


@dataclass(frozen=True, slots=True)
class World:
    """Static geometry (NED, m) and shading parameters of one visual configuration."""

    #: Sorted by shader group (see ``groups``).
    vertices: F32
    #: (first vertex, vertex count) of each of :data:`GROUPS`.
    groups: tuple[tuple[int, int], ...]
    chunks: Chunks
    lighting: Lighting
    ground: GroundStyle
    cloud_threshold: tuple[float, float]
    cloud_offset_texels: tuple[float, float]


#: Scene programs that draw the world, by group index (see :func:`shader_group`).
GROUPS = ("ground", "generic", "foliage", "band", "diffuse")


def shader_group(kind: NDArray[np.float32]) -> NDArray[np.int64]:
    """Which scene program draws each vertex kind: an index into :data:`GROUPS`.

    Plain, roof and bark surfaces need none of the generic program's windows and gloss (``diffuse``);
    the horizon forest band has its own cheap foliage program (``band``).
    """
    k = np.floor(kind).astype(np.int64)
    out = np.ones(k.shape, dtype=np.int64)
    out[k == Kind.GROUND] = 0
    out[k == Kind.FOLIAGE] = 2
    out[k == Kind.DISTANT] = 3
    out[(k == Kind.PLAIN) | (k == Kind.ROOF) | (k == Kind.BARK)] = 4
    return out


def chunk_table(vertices: F32, part_sizes: list[int]) -> Chunks:
    """Chunks of an unsorted vertex array of parts (one kind each), as :func:`sort_by_group` places them.

    The sort is stable, so a part stays contiguous and parts keep their order within a group.
    """
    sizes = np.asarray(part_sizes, dtype=np.int64)
    starts = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
    group = shader_group(vertices[starts, 11]) if sizes.size else np.zeros(0, dtype=np.int64)
    first = np.zeros(sizes.size, dtype=np.int64)
    base = 0
    for g in range(len(GROUPS)):
        idx = np.flatnonzero(group == g)
        first[idx] = base + np.concatenate([[0], np.cumsum(sizes[idx])[:-1]]).astype(np.int64)
        base += int(sizes[idx].sum())
    centre = np.zeros((sizes.size, 3))
    radius = np.zeros(sizes.size)
    for i, (s, n) in enumerate(zip(starts, sizes, strict=True)):
        pos = vertices[s : s + n, 0:3].astype(np.float64)
        lo, hi = pos.min(axis=0), pos.max(axis=0)
        centre[i] = (lo + hi) / 2.0
        radius[i] = float(np.max(np.linalg.norm(pos - centre[i], axis=1)))
    return Chunks(group, first, sizes, centre, radius)


def sort_by_group(vertices: F32) -> tuple[F32, tuple[tuple[int, int], ...]]:
    """Vertices reordered by shader group (whole triangles stay together) and each group's range."""
    group = shader_group(vertices[::3, 11])
    order = np.argsort(group, kind="stable")
    idx = (order[:, None] * 3 + np.arange(3)[None, :]).reshape(-1)
    counts = np.bincount(group, minlength=len(GROUPS)) * 3
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    ranges = tuple((int(s), int(c)) for s, c in zip(starts, counts, strict=True))
    return vertices[idx], ranges


def build_world(visual: VisualConfig, pattern_dens_quantile: F64) -> World:
    """Geometry and shading of a visual configuration (deterministic in ``visual.seed``).

    ``pattern_dens_quantile`` are the 0..100th percentiles of the cloud density the sky shader computes
    from the pattern texture; coverage thresholds are picked from them so ``cloud_cover`` is an area.
    """
    rng = np.random.default_rng(visual.seed)
    b = MeshBuilder()
    g = 2.0 * GROUND_HALF_M
    ground = quads_to_mesh(
        np.array(
            [
                [
                    [-GROUND_HALF_M, -GROUND_HALF_M, 0.0],
                    [-GROUND_HALF_M, GROUND_HALF_M, 0.0],
                    [GROUND_HALF_M, GROUND_HALF_M, 0.0],
                    [GROUND_HALF_M, -GROUND_HALF_M, 0.0],
                ]
            ]
        ),
        np.array([[[0.0, 0.0], [0.0, g], [g, g], [g, 0.0]]]),
    )
    if ground.nrm[0, 2] > 0:  # must face up (-z in NED)
        ground = Mesh(ground.pos[[0, 2, 1, 3, 5, 4]], -ground.nrm, ground.uv[[0, 2, 1, 3, 5, 4]])
    b.add(ground, (1.0, 1.0, 1.0), Kind.GROUND)
    # The first draws of rng: solid_structures() repeats them for the evaluation.
    for spec in (*random_structures(visual, rng), *visual.occluders):
        add_structure(b, spec, rng)
    if visual.tree_line:
        n = 720
        base = 8.0 + 14.0 * _smooth_profile(rng, n)
        bumps = rng.uniform(0.0, 4.0, n)
        gaps = _smooth_profile(rng, n, 4) < rng.uniform(0.1, 0.3)
        heights = np.where(gaps, 0.5, base + bumps)
        crown = CROWN_RGB[int(rng.integers(len(CROWN_RGB)))]
        _ring(
            visual.world_radius_m * rng.uniform(1.1, 1.6), heights, _scale(crown, 0.8), float(Kind.DISTANT), b
        )
    if visual.hills:
        n = 256
        heights = 30.0 + 160.0 * _smooth_profile(rng, n) ** 1.5
        _ring(2600.0, heights, (0.05, 0.08, 0.04), float(Kind.PLAIN), b)
    cover = visual.cloud_cover
    lo_q = float(
        np.interp(
            100.0 * (1.0 - cover), np.linspace(0, 100, pattern_dens_quantile.size), pattern_dens_quantile
        )
    )
    thr = (lo_q - 0.06, lo_q + 0.10) if cover < 0.999 else (-1.0, -0.9)
    unsorted = b.build()
    vertices, groups = sort_by_group(unsorted)
    return World(
        vertices=vertices,
        groups=groups,
        chunks=chunk_table(unsorted, b.part_sizes),
        lighting=lighting(visual),
        ground=ground_style(visual, rng),
        cloud_threshold=thr,
        cloud_offset_texels=(float(rng.uniform(0, 1024)), float(rng.uniform(0, 1024))),
    )
