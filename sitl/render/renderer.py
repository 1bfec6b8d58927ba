"""Offscreen RGB-D renderer of the follower's camera (moderngl through EGL; llvmpipe or a GPU).

``Renderer.render(follower_truth, leader_truth, t_s) -> RgbdFrame`` is the whole API a lockstep
harness needs; :meth:`Renderer.render_view` renders from an explicit camera pose (datasets).

A frame is two passes (see :mod:`sitl.render.shaders`): the scene into RGBA8 colour + packed depth,
then the sensor model into RGB8 colour, float32 depth (m along the optical axis, 0 = invalid) and the
leader mask. The ground truth box comes from that mask: the leader's visible pixels, after occlusion
and clipping. A third, tiny pass draws the leader alone on a canvas with a shifted principal point to
count how many pixels it would cover unoccluded and unclipped (the visible fraction's denominator).

One ``Renderer`` owns one GL context: create it, render and close it on the same thread.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Self

import cv2
import moderngl
import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import GroundTruth, Intrinsics, MountConfig, RgbdFrame
from companion.kernel.errors import CameraError
from companion.kernel.frames import Mat3, R_body_cam_from_mount, R_from_quat, Vec3
from sitl.render import shaders
from sitl.render.airframes import LeaderModel, build_leader
from sitl.render.config import CameraModel, VisualConfig
from sitl.render.geometry import (
    Box,
    CameraPose,
    PoseTruth,
    as_vec3,
    blur_homographies,
    box_from_mask,
    camera_pose,
    model_matrix,
    projection_matrix,
    shifted_intrinsics,
    view_matrix,
    yaw_rel_rad,
)
from sitl.render.meshes import F32, VERTEX_ATTRIBUTES, VERTEX_FLOATS, VERTEX_FORMAT
from sitl.render.noise import FIELD_PX, NORMAL_RANGE, pattern_texture, sensor_noise_field
from sitl.render.shaders import SHADOW_OFFSETS_PX
from sitl.render.world import (
    CLOUD_ALTITUDE_M,
    CLOUD_TEXEL_M,
    GROUND_HALF_M,
    GROUND_PERIOD_M,
    GROUPS,
    World,
    build_world,
)

NEAR_M = 0.05
FAR_M = 2.0 * GROUND_HALF_M
#: Auto exposure aims the frame's mean linear luminance at this (18 % grey).
AE_TARGET = 0.18
#: Exposure gain at which the shutter is fully open; above it, analog gain (and noise) rises.
GAIN_AT_MAX_SHUTTER = 2.0
#: The sky cube stores sqrt(radiance / SKY_SCALE).
SKY_SCALE = 8.0
#: Sky cube face size: texels about a pixel wide at 640 px (nearest); datasets supersample and filter.
SKY_FACE_PX = 1024
SKY_FACE_PX_SUPERSAMPLED = 512
#: Ground texture size (a power of two: the real-time ground shader wraps texel indices with a mask).
GROUND_TEX_PX = 2048
#: Cube-map face (s, t, 1) -> direction, GL's convention, faces +X -X +Y -Y +Z -Z.
_CUBE_FACES = (
    ((0, 0, 1), (0, -1, 0), (-1, 0, 0)),
    ((0, 0, -1), (0, -1, 0), (1, 0, 0)),
    ((1, 0, 0), (0, 0, 1), (0, 1, 0)),
    ((1, 0, 0), (0, 0, -1), (0, -1, 0)),
    ((1, 0, 0), (0, -1, 0), (0, 0, 1)),
    ((-1, 0, 0), (0, -1, 0), (0, 0, -1)),
)

U8 = NDArray[np.uint8]
_IDENTITY4 = np.eye(4, dtype=np.float32).tobytes()
#: Indices into ``world.GROUPS``: crowns, generic, diffuse, band, ground.
_WORLD_DRAW_ORDER = (2, 1, 4, 3, 0)
#: Bytes of one indirect draw record (moderngl's stride for glMultiDrawArraysIndirect).
_INDIRECT_BYTES = 20
#: Sd of the sum of two uniform bytes, the shaders' colour-noise unit (see ``shaders.colour_noise``).
NOISE_SUM_SD = math.sqrt(2.0 * (256.0**2 - 1.0) / 12.0)
_UNIT_CUBE = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)


@dataclass(frozen=True, slots=True)
class LeaderPose:
    """The leader's attitude (body -> NED) and centre position in NED, m."""

    R_ned_body: Mat3
    p_ned_m: Vec3


@dataclass(frozen=True, slots=True)
class RenderedView:
    """One rendered camera view with the leader's mask-derived truth."""

    rgb: U8
    depth_m: NDArray[np.float32]
    #: Leader coverage per pixel, 0..255 (binary without supersampling).
    mask: U8
    box_xyxy_px: Box | None
    #: Leader pixels visible in the frame and pixels it would cover unoccluded and unclipped.
    visible_px: float
    full_px: float
    exposure_s: float

    @property
    def visible_fraction(self) -> float:
        if self.full_px <= 0.0:
            return 0.0
        return float(min(1.0, self.visible_px / self.full_px))


def kelvin_rgb(kelvin: float) -> tuple[float, float, float]:
    """Approximate linear RGB of a black body (Tanner Helland's fit), green normalised to 1."""
    t = kelvin / 100.0
    r = 255.0 if t <= 66 else 329.698727446 * (t - 60) ** -0.1332047592
    g = (
        99.4708025861 * math.log(t) - 161.1195681661
        if t <= 66
        else 288.1221695283 * (t - 60) ** -0.0755148492
    )
    b = 255.0 if t >= 66 else (0.0 if t <= 19 else 138.5177312231 * math.log(t - 10) - 305.0447927307)
    lin = [(min(max(c, 1.0), 255.0) / 255.0) ** 2.2 for c in (r, g, b)]
    return lin[0] / lin[1], 1.0, lin[2] / lin[1]


def white_balance_gains(camera_k: float) -> tuple[float, float, float]:
    """Per-channel gains of a camera white-balanced for ``camera_k`` kelvin under daylight (5500 K).

    A camera set for warmer light than there is boosts blue: the picture turns cold, and vice versa.
    """
    cam, ref = kelvin_rgb(camera_k), kelvin_rgb(5500.0)
    return ref[0] / cam[0], 1.0, ref[2] / cam[2]


def _skybox_vertices(face_px: int) -> NDArray[np.float32]:
    """The sky cube's triangles: per vertex a corner direction (NED) and its sky-atlas texel coordinates.

    Face ``i`` of the atlas holds rows ``[i face_px, (i + 1) face_px)``; a face's (s, t) in [-1, 1] maps
    to texels [0.5, face_px - 0.5], so that the interpolated coordinate never leaves the face.
    """
    out = []
    for i, rows in enumerate(_CUBE_FACES):
        M = np.array(rows, dtype=np.float64)
        corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)]
        for s_, t_ in corners:
            d = M @ np.array([s_, t_, 1.0])
            u = 0.5 + 0.5 * (s_ + 1.0) * (face_px - 1)
            v = 0.5 + 0.5 * (t_ + 1.0) * (face_px - 1) + i * face_px
            out.append([*d, u, v])
    return np.array(out, dtype=np.float32)


def _color_mask(fbo: moderngl.Framebuffer, masks: list[tuple[bool, bool, bool, bool]]) -> None:
    """Per-attachment colour write masks (the first ``len(attachments)`` of ``masks``)."""
    n = len(fbo.color_attachments)
    fbo.color_mask = masks[0] if n == 1 else masks[:n]  # type: ignore[assignment]


def _frustum_normals(intr: Intrinsics, margin_px: float) -> NDArray[np.float64]:
    """Inward unit normals (camera frame) of the view frustum's four side planes, widened by a margin."""
    W, H = intr.width_px, intr.height_px
    xl, xr = (-0.5 - margin_px - intr.cx_px) / intr.fx_px, (W - 0.5 + margin_px - intr.cx_px) / intr.fx_px
    yt, yb = (-0.5 - margin_px - intr.cy_px) / intr.fy_px, (H - 0.5 + margin_px - intr.cy_px) / intr.fy_px
    n = np.array([[1.0, 0.0, -xl], [-1.0, 0.0, xr], [0.0, 1.0, -yt], [0.0, -1.0, yb]])
    out: NDArray[np.float64] = n / np.linalg.norm(n, axis=1, keepdims=True)
    return out


def _clip_half_plane(
    poly: list[tuple[float, float]], a: float, b: float, c: float
) -> list[tuple[float, float]]:
    """The part of a convex polygon where ``a x + b y + c >= 0`` (one Sutherland-Hodgman step)."""
    out: list[tuple[float, float]] = []
    for i, p in enumerate(poly):
        q = poly[(i + 1) % len(poly)]
        fp, fq = a * p[0] + b * p[1] + c, a * q[0] + b * q[1] + c
        if fp >= 0.0:
            out.append(p)
        if (fp >= 0.0) != (fq >= 0.0):
            t = fp / (fp - fq)
            out.append((p[0] + t * (q[0] - p[0]), p[1] + t * (q[1] - p[1])))
    return out


def _mat_bytes(M: NDArray[np.float64]) -> bytes:
    """A numpy matrix as GLSL expects it (column-major float32)."""
    return np.ascontiguousarray(M.T, dtype=np.float32).tobytes()


def _set(prog: moderngl.Program, name: str, value: Any) -> None:
    """Set a uniform if the linker kept it (unused uniforms are optimised away) and it changed.

    The program's ``extra`` caches each name's uniform (or None) and last value: setting one costs
    microseconds in moderngl, and a frame sets dozens, most of them unchanged.
    """
    cache: dict[str, list[Any]] | None = prog.extra
    if cache is None:
        cache = prog.extra = {}
    entry = cache.get(name)
    if entry is None:
        try:
            member: Any = prog[name]
        except KeyError:
            member = None
        entry = cache[name] = [member, None]
    if entry[0] is None or entry[1] == value:
        return
    entry[1] = value
    if isinstance(value, bytes):
        entry[0].write(value)
    else:
        entry[0].value = value


@dataclass(slots=True)
class _ScenePrograms:
    """The scene pass's programs, compiled either for the post pass or DIRECT (sensor in the scene)."""

    ground: moderngl.Program
    generic: moderngl.Program
    foliage: moderngl.Program
    band: moderngl.Program
    diffuse: moderngl.Program
    rotor: moderngl.Program
    sky: moderngl.Program
    sky_vao: moderngl.VertexArray
    world_vaos: tuple[moderngl.VertexArray, ...] = ()
    leader_vaos: tuple[moderngl.VertexArray, ...] = ()
    dyn_vao: moderngl.VertexArray | None = None

    @property
    def all(self) -> tuple[moderngl.Program, ...]:
        return (*self.meshes, self.sky)

    @property
    def meshes(self) -> tuple[moderngl.Program, ...]:
        return (*self.world, self.rotor)

    @property
    def world(self) -> tuple[moderngl.Program, ...]:
        """The world's programs in the order of ``world.GROUPS``."""
        return (self.ground, self.generic, self.foliage, self.band, self.diffuse)


class Renderer:
    """Renders the follower's RGB-D camera with the leader, the world and a D435i-like sensor model.

    Args:
        camera: the sensor (resolution, FOV, depth range and noise).
        visual: the scene; change it later with :meth:`set_visual`.
        mount: camera extrinsics on the follower's body.
        supersample: 1 (real time) or 2 (datasets: 4 samples per pixel, smoother edges of small leaders).
        seed: seeds the noise fields and the per-frame noise offsets (frames repeat exactly).
        backend: moderngl context backend ("egl" for headless; None lets moderngl choose).
        auto_exposure: meter each frame to expose the next; off keeps the first frame's estimate.
    """

    def __init__(
        self,
        camera: CameraModel | None = None,
        visual: VisualConfig | None = None,
        mount: MountConfig | None = None,
        *,
        supersample: int = 1,
        seed: int = 0,
        backend: str | None = "egl",
        auto_exposure: bool = True,
    ) -> None:
        if supersample not in (1, 2):
            raise ValueError("supersample must be 1 or 2")
        self.camera = camera or CameraModel()
        self.mount = mount or MountConfig()
        self.intrinsics: Intrinsics = self.camera.intrinsics
        self.supersample = supersample
        self.auto_exposure = auto_exposure
        self._rng = np.random.default_rng(seed)
        self._R_body_cam = R_body_cam_from_mount(
            self.mount.roll_deg, self.mount.pitch_deg, self.mount.yaw_deg
        )
        try:
            kwargs: dict[str, Any] = {"require": 330}
            if backend is not None:
                kwargs["backend"] = backend
            self._ctx = moderngl.create_standalone_context(**kwargs)
        except Exception as exc:  # moderngl raises bare Exceptions from EGL
            raise CameraError(
                f"cannot create an offscreen OpenGL context ({backend or 'default'} backend): {exc}; "
                "install Mesa's EGL (libegl1 libgl1-mesa-dri libegl-mesa0)"
            ) from exc
        self._seq = 0
        self._log2_gain: float | None = None
        try:
            self._init_gl(seed)
            self.set_visual(visual or VisualConfig())
        except BaseException:
            self._ctx.release()
            raise

    # ---- lifecycle -------------------------------------------------------------------------------------

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def close(self) -> None:
        """Release the GL context and everything on it (idempotent)."""
        ctx = getattr(self, "_ctx", None)
        if ctx is not None:
            ctx.release()
            self._ctx = None  # type: ignore[assignment]

    @property
    def gl_renderer(self) -> str:
        """The OpenGL renderer string (llvmpipe on CPU machines, the GPU's name otherwise)."""
        return str(self._ctx.info.get("GL_RENDERER", "?"))

    # ---- set-up ----------------------------------------------------------------------------------------

    def _init_gl(self, seed: int) -> None:
        ctx = self._ctx
        W, H = self.intrinsics.width_px, self.intrinsics.height_px
        s = self.supersample
        pattern = pattern_texture(seed)
        self._pattern = ctx.texture((FIELD_PX, FIELD_PX), 4, pattern.tobytes())
        self._pattern.build_mipmaps()
        self._pattern.filter = (moderngl.NEAREST_MIPMAP_NEAREST, moderngl.NEAREST)
        p = pattern[::4, ::4].astype(np.float32) / 255.0
        dens = 0.8 * p[..., 0] + 0.12 * p[..., 1] + 0.08 * p[..., 1]
        self._cloud_quantiles = np.percentile(dens, np.linspace(0, 100, 101))
        # The periodic field padded by a frame, so that every offset in [0, FIELD_PX)^2 reads a frame
        # without wrapping (a wrap costs more per pixel than the fetch's address on llvmpipe).
        noise = np.pad(
            sensor_noise_field(seed + 1, self.camera.depth_noise_corr_px),
            ((0, H - 1), (0, W - 1), (0, 0)),
            mode="wrap",
        )
        self._noise = ctx.texture((noise.shape[1], noise.shape[0]), 4, noise.tobytes())
        self._s0 = ctx.texture((W * s, H * s), 4)
        self._s1 = ctx.texture((W * s, H * s), 4)
        for t in (self._noise, self._s0, self._s1):
            t.filter = (moderngl.NEAREST, moderngl.NEAREST)
        # Baked once per world (set_visual): the ground's materials and the sky cube map.
        mag = moderngl.LINEAR if s > 1 else moderngl.NEAREST
        self._bake_filter = (
            moderngl.LINEAR_MIPMAP_NEAREST if s > 1 else moderngl.NEAREST_MIPMAP_NEAREST,
            mag,
        )
        self._ground_tex = ctx.texture((GROUND_TEX_PX, GROUND_TEX_PX), 4)
        self._ground_fbo = ctx.framebuffer([self._ground_tex])
        # The sky: at output resolution six faces in one atlas (a skybox samples it with texelFetch);
        # supersampled, a cube map sampled with linear filtering.
        face = self._sky_face_px = SKY_FACE_PX if s == 1 else SKY_FACE_PX_SUPERSAMPLED
        self._face_tex = ctx.texture((face, face * (6 if s == 1 else 1)), 4)
        self._face_tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._face_fbo = ctx.framebuffer([self._face_tex])
        self._sky_cube: moderngl.TextureCube | None = None
        self._skybox = ctx.buffer(_skybox_vertices(face).tobytes())
        # Scene: S0 colour (alpha < 0.5: leader), S1 aux (packed disparity, leader + texturedness), or,
        # DIRECT (real time, no supersampling), S0 and the final depth; the depth buffer is a texture
        # that the holes pass reads disparity from.
        self._sdepth = ctx.depth_texture((W * s, H * s))
        self._sdepth.compare_func = ""
        self._sdepth.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._scene_fbo = ctx.framebuffer([self._s0, self._s1], self._sdepth)
        self._d_depth = ctx.texture((W, H), 1, dtype="f4")
        self._direct_fbo = ctx.framebuffer([self._s0], self._sdepth) if s == 1 else None
        self._depth_fbo = ctx.framebuffer([self._d_depth])
        self._rgba = np.empty((H, W, 4), dtype=np.uint8)
        # Draw records of the world chunks in view (glMultiDrawArraysIndirect: count, 1, first, 0, pad).
        self._indirect = ctx.buffer(reserve=_INDIRECT_BYTES * 1024, dynamic=True)
        self._Kinv = np.linalg.inv(self.intrinsics.K)
        # A turn by a small angle moves no pixel further than this many px per rad (pitch or yaw:
        # f (1 + r^2 / f^2) at the corner radius r; roll: r), so slower turns skip the blur maths.
        r_px = math.hypot(self.intrinsics.width_px, self.intrinsics.height_px) / 2.0 + 1.0
        f_px = max(self.intrinsics.fx_px, self.intrinsics.fy_px)
        self._streak_px_per_rad = f_px + r_px * r_px / f_px + r_px
        self._frustum_n = _frustum_normals(self.intrinsics, margin_px=2.0)
        # Post: final colour, depth and leader coverage.
        self._p_rgb = ctx.texture((W, H), 4)
        self._p_depth = ctx.texture((W, H), 1, dtype="f4")
        self._p_mask = ctx.texture((W, H), 1)
        self._post_fbo = ctx.framebuffer([self._p_rgb, self._p_depth, self._p_mask])

        self._tri = ctx.buffer(np.array([-1.0, -1.0, 3.0, -1.0, -1.0, 3.0], dtype=np.float32).tobytes())
        self._programs = self._scene_programs(direct=False)
        self._programs_direct = self._scene_programs(direct=True) if s == 1 else None
        vs = shaders.SCENE_VS
        self._sky_bake_prog = ctx.program(
            vertex_shader=shaders.FULLSCREEN_VS, fragment_shader=shaders.SKY_BAKE_FS
        )
        self._ground_bake_prog = ctx.program(
            vertex_shader=shaders.FULLSCREEN_VS, fragment_shader=shaders.GROUND_BAKE_FS
        )
        self._mask_prog = ctx.program(vertex_shader=vs, fragment_shader=shaders.MASK_FS)
        self._sky_bake_vao = ctx.vertex_array(self._sky_bake_prog, [(self._tri, "2f", "in_xy")])
        self._ground_bake_vao = ctx.vertex_array(self._ground_bake_prog, [(self._tri, "2f", "in_xy")])
        self._post_variants: dict[
            tuple[int, int, int, int], tuple[moderngl.Program, moderngl.VertexArray]
        ] = {}
        for prog in (self._sky_bake_prog, self._ground_bake_prog):
            _set(prog, "u_tex", 4)
            _set(prog, "u_z", 0.0)
        self._P = projection_matrix(self.intrinsics, NEAR_M, FAR_M, s)
        # Window depth zw -> disparity: 1 / z = (2 zw - 1 - P22) / P23, so disparity = fB / z is affine.
        fB, P22, P23 = self.camera.focal_baseline_px_m, self._P[2, 2], self._P[2, 3]
        self._disp_from_window_z = (2.0 * fB / P23, -fB * (1.0 + P22) / P23)
        # Framebuffer pixel (x, y) at scale s is intrinsics pixel ((x + 0.5) / s - 0.5, ...).
        S = np.array([[1.0 / s, 0.0, 0.5 / s - 0.5], [0.0, 1.0 / s, 0.5 / s - 0.5], [0.0, 0.0, 1.0]])
        self._Kinv_fb = np.linalg.inv(self.intrinsics.K) @ S
        self._mask_vaos: tuple[moderngl.VertexArray, ...] = ()
        self._dyn_buf = ctx.buffer(reserve=VERTEX_FLOATS * 4 * 3 * 2048, dynamic=True)
        for progs in self._program_sets:
            progs.dyn_vao = self._vao(progs.generic, self._dyn_buf)
        self._mask_fbos: dict[int, tuple[moderngl.Framebuffer, U8]] = {}
        self._resources: list[Any] = []

    @property
    def _program_sets(self) -> tuple[_ScenePrograms, ...]:
        return (self._programs,) if self._programs_direct is None else (self._programs, self._programs_direct)

    def _scene_programs(self, direct: bool) -> _ScenePrograms:
        ctx = self._ctx
        d = int(direct)

        filtered = int(self.supersample > 1)

        def mesh(fs: str, *, band: int = 0, diffuse: int = 0) -> moderngl.Program:
            return ctx.program(
                vertex_shader=shaders.SCENE_VS,
                fragment_shader=shaders.with_defines(
                    fs,
                    DIRECT=d,
                    FILTERED=filtered,
                    BAND=band,
                    DIFFUSE=diffuse,
                    GROUND_LEVELS=GROUND_TEX_PX.bit_length() - 1,
                    GROUND_PERIOD_M=f"{GROUND_PERIOD_M:.1f}",
                ),
            )

        if self.supersample == 1:
            sky = ctx.program(
                vertex_shader=shaders.SKYBOX_VS,
                fragment_shader=shaders.with_defines(shaders.SKYBOX_FS, DIRECT=d),
            )
            sky_vao = ctx.vertex_array(sky, [(self._skybox, "3f 2f", "in_dir", "in_uv")])
        else:
            sky = ctx.program(vertex_shader=shaders.FULLSCREEN_VS, fragment_shader=shaders.SKY_FS)
            sky_vao = ctx.vertex_array(sky, [(self._tri, "2f", "in_xy")])
        progs = _ScenePrograms(
            ground=mesh(shaders.SCENE_GROUND_FS),
            generic=mesh(shaders.SCENE_GENERIC_FS),
            foliage=mesh(shaders.SCENE_FOLIAGE_FS),
            band=mesh(shaders.SCENE_FOLIAGE_FS, band=1),
            diffuse=mesh(shaders.SCENE_GENERIC_FS, diffuse=1),
            rotor=mesh(shaders.SCENE_ROTOR_FS),
            sky=sky,
            sky_vao=sky_vao,
        )
        cam = self.camera
        for prog in progs.all:
            _set(prog, "u_tex", 4)
            _set(prog, "u_fB", cam.focal_baseline_px_m)
            if direct:
                self._sensor_constants(prog)
        _set(progs.ground, "u_ground", 5)
        _set(progs.sky, "u_sky", 6)
        _set(progs.sky, "u_sky_atlas", 6)
        _set(progs.sky, "u_z", 1.0)
        return progs

    def _sensor_constants(self, prog: moderngl.Program) -> None:
        """Uniforms of the sensor model that never change for a camera (see shaders._SENSOR)."""
        cam = self.camera
        fB = cam.focal_baseline_px_m
        sigma_px = cam.subpixel_px if cam.depth_noise else 0.0
        floor, low_texture = (0.004, 0.10) if cam.depth_holes else (0.0, 0.0)
        _set(prog, "u_noise", 2)
        _set(prog, "u_disp_noise", (NORMAL_RANGE * sigma_px, -0.5 * NORMAL_RANGE * sigma_px))
        _set(prog, "u_drange", (fB / cam.depth_max_m, fB / cam.depth_min_m))
        _set(prog, "u_hole_p", (floor + low_texture, low_texture))

    def _post_variant(
        self, edges: bool, shadow_px: int, blur_n: int, depth_pass: bool = False
    ) -> tuple[moderngl.Program, moderngl.VertexArray]:
        """The post program for one combination of switches, compiled on first use."""
        key = (int(edges), shadow_px if edges else 0, blur_n, int(depth_pass))
        if key not in self._post_variants:
            prog = self._ctx.program(
                vertex_shader=shaders.FULLSCREEN_VS,
                fragment_shader=shaders.post_fs(self.supersample, edges, key[1], blur_n, depth_pass),
            )
            _set(prog, "u_z", 0.0)
            _set(prog, "u_col", 0)
            _set(prog, "u_aux", 1)
            _set(prog, "u_zbuf", 3)
            _set(prog, "u_disp_from_z", self._disp_from_window_z)
            _set(prog, "u_size", (self.intrinsics.width_px, self.intrinsics.height_px))
            _set(prog, "u_fB", self.camera.focal_baseline_px_m)
            self._sensor_constants(prog)
            self._post_variants[key] = (prog, self._ctx.vertex_array(prog, [(self._tri, "2f", "in_xy")]))
        return self._post_variants[key]

    def _vao(self, prog: moderngl.Program, buf: moderngl.Buffer) -> moderngl.VertexArray:
        return self._ctx.vertex_array(prog, [(buf, VERTEX_FORMAT, *VERTEX_ATTRIBUTES)], skip_errors=True)

    def set_visual(self, visual: VisualConfig) -> None:
        """Rebuild the world and the leader for a new visual configuration (about half a second)."""
        self.visual = visual
        self.world: World = build_world(visual, self._cloud_quantiles)
        self.leader_model: LeaderModel = build_leader(visual.leader)
        for res in self._resources:
            res.release()
        ctx = self._ctx
        world_buf = ctx.buffer(self.world.vertices.tobytes())
        opaque = ctx.buffer(self.leader_model.opaque.tobytes())
        rotors = ctx.buffer(self.leader_model.rotors.tobytes())
        self._resources = [world_buf, opaque, rotors]
        for progs in self._program_sets:
            progs.world_vaos = tuple(self._vao(p, world_buf) for p in progs.world)
            progs.leader_vaos = (self._vao(progs.generic, opaque), self._vao(progs.rotor, rotors))
            self._resources += [*progs.world_vaos, *progs.leader_vaos]
        self._mask_vaos = (self._vao(self._mask_prog, opaque), self._vao(self._mask_prog, rotors))
        self._resources += list(self._mask_vaos)
        L = self.world.lighting
        ground_light = np.asarray(L.sun_rgb) * max(-L.sun_dir_ned[2], 0.0) + np.asarray(L.sky_rgb)
        for progs in self._program_sets:
            for prog in progs.meshes:
                _set(prog, "u_sun_dir", L.sun_dir_ned)
                _set(prog, "u_sun_rgb", L.sun_rgb)
                _set(prog, "u_sky_rgb", L.sky_rgb)
                _set(prog, "u_bounce_rgb", L.bounce_rgb)
                _set(prog, "u_fog_rgb", L.fog_rgb)
                _set(prog, "u_fog_density", visual.fog_density_per_m)
            _set(progs.ground, "u_ground_light", tuple(float(c) for c in ground_light))
        self._bake_ground()
        self._bake_sky()
        self._wb = white_balance_gains(visual.white_balance_k)
        self._log2_gain = None
        chunks = self.world.chunks
        self._chunk_order = np.argsort(chunks.first, kind="stable")
        self._chunk_group_sorted = chunks.group[self._chunk_order]
        self._records_key = b""
        self._records_offsets: list[int] = []

    def _bake_ground(self) -> None:
        """Render the world's ground materials into the periodic ground texture (+ mipmaps)."""
        G = self.world.ground
        bp = self._ground_bake_prog
        _set(bp, "u_ground_rgb", np.asarray(G.rgb, dtype=np.float32).tobytes())
        _set(bp, "u_ground_texture", G.texturedness)
        _set(bp, "u_ground_n", G.n_materials)
        _set(bp, "u_road", G.road)
        _set(bp, "u_rows", G.rows)
        _set(bp, "u_texel_m", GROUND_PERIOD_M / GROUND_TEX_PX)
        self._ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        self._pattern.use(4)
        self._ground_fbo.use()
        self._ground_bake_vao.render(moderngl.TRIANGLES)
        self._ground_tex.build_mipmaps()
        self._ground_tex.filter = self._bake_filter
        self._ground_tex.repeat_x = self._ground_tex.repeat_y = True

    def _bake_sky(self) -> None:
        """Render the six faces of the world's sky cube map (gradient, sun, glow, clouds, fog)."""
        L = self.world.lighting
        kp = self._sky_bake_prog
        _set(kp, "u_sun_dir", L.sun_dir_ned)
        _set(kp, "u_sun_rgb", L.sun_rgb)
        _set(kp, "u_sun_cos", math.cos(math.radians(0.35)))
        for name in ("zenith", "horizon", "glow", "haze", "cloud_lit", "cloud_dark"):
            _set(kp, f"u_{name}_rgb", getattr(L, f"{name}_rgb"))
        _set(kp, "u_cloud", (CLOUD_ALTITUDE_M, CLOUD_TEXEL_M, *self.world.cloud_threshold))
        _set(kp, "u_cloud_off", self.world.cloud_offset_texels)
        face = self._sky_face_px
        _set(kp, "u_face_px", float(face))
        _set(kp, "u_sky_scale", SKY_SCALE)
        _set(kp, "u_fog_rgb", L.fog_rgb)
        _set(kp, "u_fog_density", self.visual.fog_density_per_m)
        self._ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        self._pattern.use(4)
        fbo = self._face_fbo
        fbo.use()
        atlas = self.supersample == 1
        faces = np.empty((6, face, face, 4), dtype=np.uint8)
        for i, rows in enumerate(_CUBE_FACES):
            org_y = face * i if atlas else 0
            fbo.viewport = (0, org_y, face, face)
            _set(kp, "u_face_org", (0.0, float(org_y)))
            _set(kp, "u_dir_from_st", _mat_bytes(np.array(rows, dtype=np.float64)))
            self._sky_bake_vao.render(moderngl.TRIANGLES)
            if not atlas:
                fbo.read_into(faces[i], components=4)
        fbo.viewport = (0, 0, *fbo.size)
        if atlas:
            return
        if self._sky_cube is None:
            self._sky_cube = self._ctx.texture_cube((face, face), 4)
        for i in range(6):
            self._sky_cube.write(i, faces[i].tobytes())
        linear = self.supersample > 1
        self._sky_cube.filter = (
            (moderngl.LINEAR, moderngl.LINEAR) if linear else (moderngl.NEAREST, moderngl.NEAREST)
        )

    # ---- exposure --------------------------------------------------------------------------------------

    @property
    def exposure_gain(self) -> float:
        """The current linear exposure gain (auto exposure state times the EV bias)."""
        if self._log2_gain is None:
            self._log2_gain = math.log2(AE_TARGET / self.world.lighting.typical_radiance)
        return float(2.0 ** (self._log2_gain + self.visual.exposure_ev))

    def _meter(self, rgb: U8) -> None:
        if not self.auto_exposure or self._log2_gain is None:
            return
        sample = rgb[::12, ::12].astype(np.float32) * np.float32(1.0 / 255.0)
        lin = float(np.mean(sample * sample))  # the sensor encodes with gamma 2
        self._log2_gain = min(8.0, max(-8.0, self._log2_gain + 0.8 * math.log2(AE_TARGET / max(lin, 1e-4))))

    # ---- rendering -------------------------------------------------------------------------------------

    def render(self, follower: PoseTruth, leader: PoseTruth | None, t_s: float) -> RgbdFrame:
        """The follower's camera frame at sim time ``t_s`` with ground truth about the leader.

        ``follower`` may carry ``omega_body_rad_s`` (FRD body rate); it then drives motion blur.
        Without a leader the truth has no box, visible fraction 0 and NaN position and yaw.
        """
        cam = camera_pose(follower, self.mount)
        q_follower = np.asarray(follower.q_ned_body_wxyz, dtype=np.float64)
        R_ned_follower = R_from_quat(q_follower)
        omega_body = getattr(follower, "omega_body_rad_s", None)
        omega_cam = None if omega_body is None else self._R_body_cam.T @ as_vec3(omega_body)
        lp = None
        if leader is not None:
            R_ned_leader = R_from_quat(np.asarray(leader.q_ned_body_wxyz, dtype=np.float64))
            lp = LeaderPose(R_ned_leader, as_vec3(leader.p_ned_m))
        view = self.render_view(cam, lp, t_s, omega_cam_rad_s=omega_cam)
        p_follower = as_vec3(follower.p_ned_m)
        if lp is None:
            truth = GroundTruth(None, 0.0, np.full(3, np.nan), math.nan, p_follower, None, q_follower)
        else:
            truth = GroundTruth(
                view.box_xyxy_px,
                view.visible_fraction,
                cam.to_cam(lp.p_ned_m),
                yaw_rel_rad(lp.R_ned_body, R_ned_follower),
                p_follower,
                lp.p_ned_m,
                q_follower,
            )
        self._seq += 1
        return RgbdFrame(view.rgb, view.depth_m, self.intrinsics, float(t_s), self._seq, truth)

    def render_view(
        self,
        cam: CameraPose,
        leader: LeaderPose | None,
        t_s: float,
        *,
        omega_cam_rad_s: Vec3 | None = None,
        extra_vertices: F32 | None = None,
        truth: bool = True,
    ) -> RenderedView:
        """Render from an explicit camera pose; ``extra_vertices`` are distractors (NED, never leader)."""
        ctx = self._ctx
        W, H = self.intrinsics.width_px, self.intrinsics.height_px
        gain = self.exposure_gain
        exposure_s = max(self.camera.exposure_max_s * min(gain / GAIN_AT_MAX_SHUTTER, 1.0), 1.0 / 8000.0)
        analog = max(1.0, gain / GAIN_AT_MAX_SHUTTER)
        blur_n, H0, H1 = 0, np.eye(3), np.eye(3)
        if (
            omega_cam_rad_s is not None
            and self.camera.motion_blur
            and float(np.linalg.norm(omega_cam_rad_s)) * exposure_s * self._streak_px_per_rad > 0.75
        ):
            H0, H1, streak = blur_homographies(self.intrinsics, omega_cam_rad_s, exposure_s)
            if streak > 0.75:
                blur_n = 4 if streak <= 4.0 else (8 if streak <= 8.0 else 16)
        # Real time: the sensor model runs inside the scene pass (no full-screen post pass).
        direct = self._programs_direct is not None and blur_n == 0
        progs = self._programs_direct if direct and self._programs_direct is not None else self._programs
        holes = self.camera.depth_holes
        C = self.world.chunks
        chunk_cam = (C.centre_ned_m - cam.p_ned_cam_m) @ cam.R_ned_cam
        in_view = self._chunks_in_view(chunk_cam)
        standing = in_view & (C.group != 0)  # in view and not the ground
        near = standing & (chunk_cam[:, 2] - C.radius_m < self.camera.depth_max_m)
        near_cam, near_r = chunk_cam[near], C.radius_m[near]
        shadow_px = self._shadow_search_px(cam, leader, extra_vertices, near_cam, near_r)
        region = self._near_region(
            cam, leader, extra_vertices, shadow_px=shadow_px, near_cam=near_cam, near_r=near_r
        )
        sensor = self._sensor_uniforms(analog)

        # ---- pass 1: scene (and, DIRECT, the sensor)
        self._scene_pass(
            progs,
            cam,
            leader,
            t_s,
            gain=gain,
            exposure_s=exposure_s,
            extra_vertices=extra_vertices,
            sensor=sensor if direct else None,
            in_view=in_view,
        )

        # ---- pass 2: sensor, or (DIRECT) only edge and stereo-shadow holes near objects
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        self._noise.use(2)
        depth = np.empty((H, W), dtype=np.float32)
        if direct:
            return self._finish_direct(
                cam,
                leader,
                boxes=[b for b in (region, self._ground_region(cam)) if b is not None],
                blockers=(chunk_cam[standing], C.radius_m[standing], extra_vertices),
                shadow_px=shadow_px,
                sensor=sensor,
                depth=depth,
                exposure_s=exposure_s,
                truth=truth,
            )
        self._s0.use(0)
        self._s1.use(1)
        rgb = np.empty((H, W, 3), dtype=np.uint8)
        # Whole frame when near things fill much of it (and always for supersampled datasets).
        if not holes:
            region = None
        whole = holes and (
            self.supersample > 1 or (region is not None and region[2] * region[3] > 0.4 * W * H)
        )
        passes = [(whole, None)] if whole or region is None else [(False, None), (True, region)]
        self._post_fbo.use()
        for edges, scissor in passes:
            pp, vao = self._post_variant(edges, shadow_px, blur_n)
            self._post_uniforms(pp, sensor, H0, H1, blur_n)
            self._post_fbo.scissor = scissor  # type: ignore[assignment]
            vao.render(moderngl.TRIANGLES)
        self._post_fbo.scissor = None  # type: ignore[assignment]
        mask_u8 = np.empty((H, W), dtype=np.uint8)
        self._post_fbo.read_into(rgb, components=3, attachment=0)
        self._post_fbo.read_into(depth, components=1, attachment=1, dtype="f4")
        self._post_fbo.read_into(mask_u8, components=1, attachment=2)
        self._meter(rgb)

        box, visible, full = None, 0.0, 0.0
        if leader is not None and truth:
            box, count = box_from_mask(mask_u8)
            visible = float(count) if self.supersample == 1 else float(mask_u8.sum(dtype=np.int64)) / 255.0
            if box is not None:
                full = max(self._full_leader_px(cam, leader), visible)
        return RenderedView(rgb, depth, mask_u8, box, visible, full, exposure_s)

    def _finish_direct(
        self,
        cam: CameraPose,
        leader: LeaderPose | None,
        *,
        boxes: list[tuple[int, int, int, int]],
        blockers: tuple[NDArray[np.float64], NDArray[np.float64], F32 | None],
        shadow_px: int,
        sensor: dict[str, Any],
        depth: NDArray[np.float32],
        exposure_s: float,
        truth: bool,
    ) -> RenderedView:
        """After a DIRECT scene pass: the depth pass where depth can be valid, read-back, leader truth.

        ``boxes`` are scissor boxes (x, y, w, h) that hold every pixel whose true depth is in range
        (near objects, near ground); depth is 0 elsewhere. ``blockers``: what could hide the leader
        (bounding spheres of the world chunks in view, camera frame; distractor vertices).
        """
        W, H = self.intrinsics.width_px, self.intrinsics.height_px
        dfbo = self._depth_fbo
        dfbo.use()
        dfbo.clear(0.0)
        if boxes:
            pp, vao = self._post_variant(self.camera.depth_holes, shadow_px, 0, depth_pass=True)
            self._post_uniforms(pp, sensor, np.eye(3), np.eye(3), 0)
            self._s0.use(0)
            self._sdepth.use(3)
            x0, y0 = min(b[0] for b in boxes), min(b[1] for b in boxes)
            x1, y1 = max(b[0] + b[2] for b in boxes), max(b[1] + b[3] for b in boxes)
            union = (x0, y0, x1 - x0, y1 - y0)
            # One draw over the union unless the boxes leave much of it out (an object high, the
            # near ground low); overlapping boxes only compute the same depth twice.
            if union[2] * union[3] <= 1.2 * sum(b[2] * b[3] for b in boxes):
                boxes = [union]
            for box_ in boxes:
                dfbo.scissor = box_
                vao.render(moderngl.TRIANGLES)
            dfbo.scissor = None  # type: ignore[assignment]
        scene = self._direct_fbo
        assert scene is not None  # noqa: S101  (direct implies supersample == 1)
        rgba = self._rgba
        # RGBA reads as a copy; llvmpipe converts to RGB byte by byte (10x slower than OpenCV's swizzle).
        scene.read_into(rgba, components=4, attachment=0)
        dfbo.read_into(depth, components=1, attachment=0, dtype="f4")
        rgb = np.empty((H, W, 3), dtype=np.uint8)
        cv2.cvtColor(rgba, cv2.COLOR_RGBA2RGB, dst=rgb)
        self._meter(rgb)
        mask = np.zeros((H, W), dtype=np.uint8)
        box, visible, full = None, 0.0, 0.0
        span, inside = self._leader_span(cam, leader) if truth else (None, False)
        if leader is not None and span is not None:
            x0, y0, x1, y1 = span
            # Colour alpha < 0.5 marks the leader (its opaque parts and rotor discs; see shaders.emit).
            sub = rgba[y0:y1, x0:x1, 3] < 128
            sub_box, count = box_from_mask(sub)
            if sub_box is not None:
                mask[y0:y1, x0:x1] = sub.view(np.uint8) * np.uint8(255)
                box = (sub_box[0] + x0, sub_box[1] + y0, sub_box[2] + x0, sub_box[3] + y0)
                visible = float(count)
                # Wholly in the frame with nothing in front: every pixel it covers is visible (the
                # leader-alone pass would count the same pixels, up to its sampling offset).
                if inside and not self._may_hide_leader(cam, leader, span, blockers):
                    full = visible
                else:
                    full = max(self._full_leader_px(cam, leader), visible)
        return RenderedView(rgb, depth, mask, box, visible, full, exposure_s)

    def _may_hide_leader(
        self,
        cam: CameraPose,
        leader: LeaderPose,
        span: tuple[int, int, int, int],
        blockers: tuple[NDArray[np.float64], NDArray[np.float64], F32 | None],
    ) -> bool:
        """Whether anything could stand between the camera and the leader's pixels (conservative).

        A world chunk whose bounding sphere starts nearer than the leader's far side and whose
        projected bounding cube overlaps the leader's pixel span; any distractor; the ground unless the
        camera and the whole leader are above it (then no line of sight between them crosses it).
        """
        chunk_cam, radius, extra = blockers
        if extra is not None and len(extra):
            return True
        R = self.leader_model.bound_radius_m
        if cam.p_ned_cam_m[2] >= 0.0 or leader.p_ned_m[2] + R >= 0.0:
            return True
        z_far = float(cam.to_cam(leader.p_ned_m)[2]) + R
        front = chunk_cam[:, 2] - radius < z_far
        if not np.any(front):
            return False
        corners = chunk_cam[front][:, None, :] + radius[front][:, None, None] * _UNIT_CUBE[None]
        if np.any(corners[..., 2] <= NEAR_M):
            return True
        intr = self.intrinsics
        u = intr.fx_px * corners[..., 0] / corners[..., 2] + intr.cx_px
        v = intr.fy_px * corners[..., 1] / corners[..., 2] + intr.cy_px
        x0, y0, x1, y1 = span
        overlap = (u.max(axis=1) >= x0 - 1) & (u.min(axis=1) <= x1 + 1)
        overlap &= (v.max(axis=1) >= y0 - 1) & (v.min(axis=1) <= y1 + 1)
        return bool(np.any(overlap))

    def _leader_span(
        self, cam: CameraPose, leader: LeaderPose | None
    ) -> tuple[tuple[int, int, int, int] | None, bool]:
        """Pixel rectangle (x0, y0, x1, y1) holding the leader (None: off screen); is it wholly in frame?

        The projection of the leader's bounding cube, a pixel wider on each side; the whole frame if the
        cube reaches behind the camera.
        """
        if leader is None:
            return None, False
        intr = self.intrinsics
        W, H = intr.width_px, intr.height_px
        R = self.leader_model.bound_radius_m
        corners = cam.to_cam(leader.p_ned_m) + R * _UNIT_CUBE
        if np.any(corners[:, 2] <= NEAR_M):
            return (0, 0, W, H), False
        u = intr.fx_px * corners[:, 0] / corners[:, 2] + intr.cx_px
        v = intr.fy_px * corners[:, 1] / corners[:, 2] + intr.cy_px
        ux0, ux1 = math.floor(u.min()) - 1, math.ceil(u.max()) + 2
        vy0, vy1 = math.floor(v.min()) - 1, math.ceil(v.max()) + 2
        x0, x1, y0, y1 = max(ux0, 0), min(ux1, W), max(vy0, 0), min(vy1, H)
        if x1 <= x0 or y1 <= y0:
            return None, False
        return (x0, y0, x1, y1), (x0, x1, y0, y1) == (ux0, ux1, vy0, vy1)

    def _sensor_uniforms(self, analog_gain: float) -> dict[str, Any]:
        """Per-frame sensor-model uniforms (see ``shaders._SENSOR``), constants folded for the shader.

        A fresh noise offset each frame. Colour noise: shot variance ``a`` and read variance ``b`` grow with
        analog gain; in the sqrt domain their sd is about ``0.5 sqrt(a) + 0.5 sqrt(b) / (v + b^0.25)``.
        Vignetting darkens by ``vignetting / 4 * (radius / half width)^2``; contrast pivots on 0.45.
        """
        W, H = self.intrinsics.width_px, self.intrinsics.height_px
        offs = self._rng.integers(0, FIELD_PX, 2)
        seed = int(self._rng.integers(0, 2**32, dtype=np.uint64))
        k = self.visual.sensor_noise if self.camera.colour_noise else 0.0
        a, b = 0.0008 * analog_gain * k, (0.002 * analog_gain * k) ** 2
        c = self.visual.contrast
        x, y, z = 0.5 * math.sqrt(a), 0.5 * math.sqrt(b), max(b**0.25, 1e-3)
        # The shader's noise is the hash's byte sums (sd NOISE_SUM_SD) and its read-noise term sees v g k / c.
        sd = (c * x / NOISE_SUM_SD, c * c * y / NOISE_SUM_SD, c * z)
        r_scale = math.sqrt(c * self.visual.vignetting / 4.0) / (W / 2.0)
        return {
            "u_off": (int(offs[0]), int(offs[1])),
            "u_seed": seed,
            "u_noise_sd": sd,
            "u_vig": (r_scale, r_scale, -r_scale * W / 2.0, -r_scale * H / 2.0),
            "u_tone": (c, 0.45 * (1.0 - c)),
        }

    def _post_uniforms(
        self, prog: moderngl.Program, sensor: dict[str, Any], H0: Mat3, H1: Mat3, blur_n: int
    ) -> None:
        for name, value in sensor.items():
            _set(prog, name, value)
        if blur_n:
            _set(prog, "u_H0", _mat_bytes(H0))
            _set(prog, "u_H1", _mat_bytes(H1))

    def _scene_pass(
        self,
        progs: _ScenePrograms,
        cam: CameraPose,
        leader: LeaderPose | None,
        t_s: float,
        *,
        gain: float,
        exposure_s: float,
        extra_vertices: F32 | None,
        sensor: dict[str, Any] | None,
        in_view: NDArray[np.bool_],
    ) -> None:
        """Draw the world chunks in view, distractors, leader, sky and rotor discs into the scene."""
        ctx = self._ctx
        gain_rgb = (gain * self._wb[0], gain * self._wb[1], gain * self._wb[2])
        clip_from_ned = _mat_bytes(self._P @ view_matrix(cam))
        cam_ned = tuple(float(c) for c in cam.p_ned_cam_m)
        glare = self._glare_rgb(cam)
        direct = sensor is not None and self._direct_fbo is not None
        fbo = self._direct_fbo if direct and self._direct_fbo is not None else self._scene_fbo
        fbo.use()
        on, off = (True, True, True, True), (False, False, False, False)
        if self.supersample == 1:
            # The skybox covers every pixel nothing else drew: only depth needs clearing.
            _color_mask(fbo, [off, off])
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        _color_mask(fbo, [on, on])
        fbo.use()  # moderngl applies a restored single-attachment mask only on use() after a clear
        ctx.enable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.disable(moderngl.BLEND)
        ctx.front_face = "cw"  # the y-down projection mirrors the image (see projection_matrix)
        ctx.depth_func = "<"
        self._pattern.use(4)
        self._ground_tex.use(5)
        self._noise.use(2)
        identity = _IDENTITY4
        # Ground mip levels: footprint at 1 m = 1 / (f h) metres per pixel (see the ground shader).
        f_px = self.intrinsics.fx_px * self.supersample
        base = -math.log2(f_px * max(-float(cam.p_ned_cam_m[2]), 0.05))
        lod = (base - math.log2(GROUND_PERIOD_M / GROUND_TEX_PX), base - math.log2(0.04))
        _set(progs.ground, "u_ground_lod", lod)
        _set(progs.ground, "u_ground_lod_k", (2.0 ** (lod[0] + 0.5), 2.0 ** (lod[1] + 0.5)))
        glare_gain = (glare[0] * gain_rgb[0], glare[1] * gain_rgb[1], glare[2] * gain_rgb[2])
        for prog in progs.all:
            _set(prog, "u_glare_rgb", glare_gain)
            _set(prog, "u_clip_from_ned", clip_from_ned)
            _set(prog, "u_ned_from_model", identity)
            _set(prog, "u_cam_ned", cam_ned)
            _set(prog, "u_gain_rgb", gain_rgb)
            _set(prog, "u_leader", 0.0)
            _set(prog, "u_blend_alpha", 0.0)
            if sensor is not None:
                for name, value in sensor.items():
                    _set(prog, name, value)
        # Near things first so that early depth testing spares the far ones.
        model = (
            _mat_bytes(model_matrix(leader.R_ned_body, leader.p_ned_m)) if leader is not None else identity
        )
        if leader is not None:
            _set(progs.generic, "u_ned_from_model", model)
            _set(progs.generic, "u_leader", 1.0)
            progs.leader_vaos[0].render(moderngl.TRIANGLES)
            _set(progs.generic, "u_ned_from_model", identity)
            _set(progs.generic, "u_leader", 0.0)
        if extra_vertices is not None and len(extra_vertices) and progs.dyn_vao is not None:
            data = np.ascontiguousarray(extra_vertices, dtype=np.float32)
            if data.nbytes > self._dyn_buf.size:
                self._dyn_buf.orphan(data.nbytes * 2)
            self._dyn_buf.write(data.tobytes())
            progs.dyn_vao.render(moderngl.TRIANGLES, vertices=len(data))
        offsets = self._write_draw_records(in_view)
        # Near-ish things first (crowns, buildings, trunks), then the horizon band, the ground last.
        for g in _WORLD_DRAW_ORDER:
            n = offsets[g + 1] - offsets[g]
            if n:
                progs.world_vaos[g].render_indirect(
                    self._indirect, moderngl.TRIANGLES, count=n, first=offsets[g]
                )
        # Sky where nothing was drawn: depth is still 1.0 there.
        ctx.disable(moderngl.CULL_FACE)
        ctx.depth_func = "<="
        fbo.depth_mask = False
        self._sky_tex().use(6)
        _set(progs.sky, "u_ned_from_pix", _mat_bytes(cam.R_ned_cam @ self._Kinv_fb))
        _set(progs.sky, "u_gain_rgb", tuple(g * SKY_SCALE for g in gain_rgb))
        progs.sky_vao.render(moderngl.TRIANGLES)
        if leader is not None:
            # Rotor discs: blend colour, mark the mask (aux alpha), leave depth and texturedness alone.
            rotor_phase, blade_vis = self._rotor_state(t_s, exposure_s)
            rp = progs.rotor
            _set(rp, "u_ned_from_model", model)
            _set(rp, "u_leader", 1.0)
            _set(rp, "u_rotor_phase", rotor_phase)
            _set(rp, "u_blade_vis", blade_vis)
            ctx.depth_func = "<"
            ctx.enable(moderngl.BLEND)
            # Blend the colour by the disc's opacity. The aux alpha (leader + texturedness) takes the
            # disc's value; DIRECT writes that into colour alpha in a second, unblended pass.
            ctx.blend_func = (  # type: ignore[assignment]  # moderngl takes 2 or 4 factors
                moderngl.SRC_ALPHA,
                moderngl.ONE_MINUS_SRC_ALPHA,
                moderngl.ONE,
                moderngl.ZERO,
            )
            _set(rp, "u_blend_alpha", 1.0)
            _color_mask(fbo, [(True, True, True, False), (False, False, False, True)])
            progs.leader_vaos[1].render(moderngl.TRIANGLES)
            ctx.disable(moderngl.BLEND)
            if direct:
                _set(rp, "u_blend_alpha", 0.0)
                _color_mask(fbo, [(False, False, False, True)])
                progs.leader_vaos[1].render(moderngl.TRIANGLES)
            _color_mask(fbo, [on, on])
        fbo.depth_mask = True

    def _sky_tex(self) -> moderngl.Texture | moderngl.TextureCube:
        """The baked sky: the face atlas (output resolution) or the cube map (supersampled)."""
        if self.supersample == 1:
            return self._face_tex
        assert self._sky_cube is not None  # noqa: S101  (baked in set_visual)
        return self._sky_cube

    def _glare_rgb(self, cam: CameraPose) -> tuple[float, float, float]:
        """Veiling glare: light a sun in or near the view scatters over the whole image (linear)."""
        L = self.world.lighting
        c = float(np.dot(cam.R_ned_cam[:, 2], np.asarray(L.sun_dir_ned)))
        k = 0.06 * max(c, 0.0) ** 6
        return (L.sun_rgb[0] * k, L.sun_rgb[1] * k, L.sun_rgb[2] * k)

    def _rotor_state(self, t_s: float, exposure_s: float) -> tuple[float, float]:
        """Blade angle (two-blade pattern, period pi) and how visible blades are through the smear."""
        omega = self.visual.leader.rotor_rpm * 2.0 * math.pi / 60.0
        phase = math.fmod(omega * t_s, math.pi)
        return phase, float(min(max(1.0 - omega * exposure_s / math.pi, 0.0), 1.0))

    def _chunks_in_view(self, chunk_cam: NDArray[np.float64]) -> NDArray[np.bool_]:
        """Which world chunks' bounding spheres (centres in the camera frame) touch the view frustum."""
        r = self.world.chunks.radius_m
        inside: NDArray[np.bool_] = np.all(chunk_cam @ self._frustum_n.T >= -r[:, None], axis=1) & (
            chunk_cam[:, 2] > NEAR_M - r
        )
        return inside

    def _write_draw_records(self, in_view: NDArray[np.bool_]) -> list[int]:
        """Indirect draw records of the chunks in view, consecutive ones merged; per-group offsets.

        Returns ``o``: group ``g``'s records are ``o[g]`` up to ``o[g + 1]`` (groups of ``world.GROUPS``).
        """
        key = in_view.tobytes()
        if key == self._records_key:
            return self._records_offsets
        C = self.world.chunks
        order = self._chunk_order
        vis = in_view[order].astype(np.int8)
        group = self._chunk_group_sorted
        # A run starts at a visible chunk whose predecessor is hidden or in another group.
        prev_vis = np.concatenate([[0], vis[:-1]])
        new_group = np.concatenate([[True], group[1:] != group[:-1]])
        starts = np.flatnonzero((vis == 1) & ((prev_vis == 0) | new_group))
        next_vis = np.concatenate([vis[1:], [0]])
        next_new = np.concatenate([new_group[1:], [True]])
        ends = np.flatnonzero((vis == 1) & ((next_vis == 0) | next_new))
        first = C.first[order][starts]
        count = C.first[order][ends] + C.count[order][ends] - first
        rec = np.zeros((starts.size, _INDIRECT_BYTES // 4), dtype=np.uint32)
        rec[:, 0], rec[:, 1], rec[:, 2] = count, 1, first
        if rec.nbytes > self._indirect.size:
            self._indirect.orphan(rec.nbytes * 2)
        if rec.size:
            self._indirect.write(rec.tobytes())
        run_group = group[starts]
        self._records_key = key
        self._records_offsets = [int(np.searchsorted(run_group, g)) for g in range(len(GROUPS) + 1)]
        return self._records_offsets

    def _shadow_search_px(
        self,
        cam: CameraPose,
        leader: LeaderPose | None,
        extra: F32 | None,
        near_cam: NDArray[np.float64],
        near_r: NDArray[np.float64],
    ) -> int:
        """Widest stereo shadow worth searching: disparity of the nearest thing in view, px.

        ``near_cam``, ``near_r``: bounding spheres (camera frame) of the world chunks within range.
        """
        z_near = 1e9
        if leader is not None:
            z = float(cam.to_cam(leader.p_ned_m)[2]) - self.leader_model.bound_radius_m
            if z > 0.0:
                z_near = min(z_near, z)
        # Ground seen along the image's bottom corners.
        h = -float(cam.p_ned_cam_m[2])
        if h > 0.0:
            W, H = self.intrinsics.width_px, self.intrinsics.height_px
            rays = cam.R_ned_cam @ self._Kinv @ np.array([[0.0, W - 1.0], [H - 1.0, H - 1.0], [1.0, 1.0]])
            down = rays[2]
            if np.any(down > 1e-6):
                z_near = min(z_near, float(np.min(h / down[down > 1e-6])))
        if near_r.size:
            z_near = min(z_near, float(max(np.min(near_cam[:, 2] - near_r), 0.3)))
        if extra is not None and len(extra):
            zs = (extra[:, :3].astype(np.float64) - cam.p_ned_cam_m) @ cam.R_ned_cam[:, 2]
            zs = zs[zs > NEAR_M]
            if zs.size:
                z_near = min(z_near, float(zs.min()))
        z_near = max(z_near, self.camera.depth_min_m)
        widest = math.ceil(self.camera.focal_baseline_px_m / z_near)
        return min((k for k in SHADOW_OFFSETS_PX if k >= widest), default=max(SHADOW_OFFSETS_PX))

    def _near_region(
        self,
        cam: CameraPose,
        leader: LeaderPose | None,
        extra: F32 | None,
        *,
        shadow_px: int,
        near_cam: NDArray[np.float64],
        near_r: NDArray[np.float64],
    ) -> tuple[int, int, int, int] | None:
        """Scissor box (x, y, w, h) around things near enough to have valid depth, or None.

        The leader (its bounding cube), world chunks within range (their bounding spheres' cubes) and
        distractors; widened to the left by the stereo shadow. The whole frame if any of them straddles
        the image plane. The ground is :meth:`_ground_region`.
        """
        intr = self.intrinsics
        W, H = intr.width_px, intr.height_px
        z_max = self.camera.depth_max_m
        pts: list[NDArray[np.float64]] = []
        if leader is not None:
            R = self.leader_model.bound_radius_m
            c = cam.to_cam(leader.p_ned_m)
            if c[2] - R < z_max:
                pts.append(c + R * _UNIT_CUBE)
        if near_r.size:
            pts.append((near_cam[:, None, :] + near_r[:, None, None] * _UNIT_CUBE[None]).reshape(-1, 3))
        if extra is not None and len(extra):
            pc = (extra[:, :3].astype(np.float64) - cam.p_ned_cam_m) @ cam.R_ned_cam
            pts.append(pc[pc[:, 2] < z_max + 1.0])
        if not pts:
            return None
        allp = np.concatenate(pts)
        if allp.size == 0:
            return None
        if np.any(allp[:, 2] <= NEAR_M):
            return (0, 0, W, H)
        u = intr.fx_px * allp[:, 0] / allp[:, 2] + intr.cx_px
        v = intr.fy_px * allp[:, 1] / allp[:, 2] + intr.cy_px
        x0 = max(math.floor(u.min()) - shadow_px - 3, 0)
        x1 = min(math.ceil(u.max()) + 3, W)
        y0 = max(math.floor(v.min()) - 3, 0)
        y1 = min(math.ceil(v.max()) + 3, H)
        if x1 <= x0 or y1 <= y0:
            return None
        return (x0, y0, x1 - x0, y1 - y0)

    def _ground_region(self, cam: CameraPose) -> tuple[int, int, int, int] | None:
        """Scissor box (x, y, w, h) of the ground nearer than the depth range, or None.

        The ground (NED down = 0) at pixel (u, v) lies at depth ``h / g(u, v)``, with ``g`` the down
        component of the pixel's ray at unit depth, affine in (u, v): in range where
        ``g >= h / depth_max``, a half-plane of the image.
        """
        h = -float(cam.p_ned_cam_m[2])
        if h <= 0.0:
            return None  # at or below ground level: the ground is seen edge-on or from below (culled)
        intr = self.intrinsics
        W, H = intr.width_px, intr.height_px
        g = (cam.R_ned_cam @ self._Kinv)[2]
        frame = [(-0.5, -0.5), (W - 0.5, -0.5), (W - 0.5, H - 0.5), (-0.5, H - 0.5)]
        poly = _clip_half_plane(frame, float(g[0]), float(g[1]), float(g[2]) - h / self.camera.depth_max_m)
        if not poly:
            return None
        us, vs = [q[0] for q in poly], [q[1] for q in poly]
        x0, x1 = max(math.floor(min(us) + 0.5) - 1, 0), min(math.ceil(max(us) + 0.5) + 1, W)
        y0, y1 = max(math.floor(min(vs) + 0.5) - 1, 0), min(math.ceil(max(vs) + 0.5) + 1, H)
        if x1 <= x0 or y1 <= y0:
            return None
        return (x0, y0, x1 - x0, y1 - y0)

    def _full_leader_px(self, cam: CameraPose, leader: LeaderPose) -> float:
        """Pixels the leader would cover with nothing in front and no image border (0 if unknown)."""
        p_cam = cam.to_cam(leader.p_ned_m)
        R = self.leader_model.bound_radius_m
        if p_cam[2] - R <= NEAR_M * 2.0:
            return 0.0
        intr = self.intrinsics
        corners = p_cam + R * np.array(
            [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64
        )
        u = intr.fx_px * corners[:, 0] / corners[:, 2] + intr.cx_px
        v = intr.fy_px * corners[:, 1] / corners[:, 2] + intr.cy_px
        s = self.supersample
        extent = max(float(u.max() - u.min()), float(v.max() - v.min())) * s + 4
        size = 32
        while size < extent:
            size *= 2
        if size > 4096:
            return 0.0
        uc, vc = float((u.max() + u.min()) / 2.0), float((v.max() + v.min()) / 2.0)
        shifted = shifted_intrinsics(intr, uc, vc, size // s)
        P = projection_matrix(shifted, NEAR_M, FAR_M, s)
        fbo, buf = self._mask_fbo(size)
        fbo.use()
        fbo.clear(0.0)
        ctx = self._ctx
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        mp = self._mask_prog
        _set(mp, "u_clip_from_ned", _mat_bytes(P @ view_matrix(cam)))
        _set(mp, "u_ned_from_model", _mat_bytes(model_matrix(leader.R_ned_body, leader.p_ned_m)))
        for vao in self._mask_vaos:
            vao.render(moderngl.TRIANGLES)
        fbo.read_into(buf, components=1)
        return float(np.count_nonzero(buf)) / float(s * s)

    def _mask_fbo(self, size: int) -> tuple[moderngl.Framebuffer, U8]:
        if size not in self._mask_fbos:
            tex = self._ctx.texture((size, size), 1)
            self._mask_fbos[size] = (self._ctx.framebuffer([tex]), np.empty((size, size), dtype=np.uint8))
        return self._mask_fbos[size]
