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

import moderngl
import numpy as np
from numpy.typing import NDArray

from companion.config import MountConfig
from companion.errors import CameraError
from companion.frames import Mat3, R_body_cam_from_mount, R_from_quat, Vec3
from companion.perception.types import GroundTruth, Intrinsics, RgbdFrame
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
from sitl.render.noise import FIELD_PX, pattern_texture, sensor_noise_field
from sitl.render.shaders import SHADOW_OFFSETS_PX
from sitl.render.world import (
    CLOUD_ALTITUDE_M,
    CLOUD_TEXEL_M,
    GROUND_HALF_M,
    GROUND_PERIOD_M,
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


def _mat_bytes(M: NDArray[np.float64]) -> bytes:
    """A numpy matrix as GLSL expects it (column-major float32)."""
    return np.ascontiguousarray(M.T, dtype=np.float32).tobytes()


def _set(prog: moderngl.Program, name: str, value: Any) -> None:
    """Set a uniform if the linker kept it (unused uniforms are optimised away)."""
    try:
        member = prog[name]
    except KeyError:
        return
    if isinstance(value, bytes):
        member.write(value)  # type: ignore[union-attr]
    else:
        member.value = value  # type: ignore[union-attr]


@dataclass(slots=True)
class _ScenePrograms:
    """The scene pass's programs, compiled either for the post pass or DIRECT (sensor in the scene)."""

    ground: moderngl.Program
    generic: moderngl.Program
    foliage: moderngl.Program
    rotor: moderngl.Program
    sky: moderngl.Program
    sky_vao: moderngl.VertexArray
    world_vaos: tuple[moderngl.VertexArray, ...] = ()
    leader_vaos: tuple[moderngl.VertexArray, ...] = ()
    dyn_vao: moderngl.VertexArray | None = None

    @property
    def all(self) -> tuple[moderngl.Program, ...]:
        return (self.ground, self.generic, self.foliage, self.rotor, self.sky)

    @property
    def meshes(self) -> tuple[moderngl.Program, ...]:
        return (self.ground, self.generic, self.foliage, self.rotor)


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
        noise = sensor_noise_field(seed + 1, self.camera.depth_noise_corr_px)
        self._noise = ctx.texture((FIELD_PX, FIELD_PX), 4, noise.tobytes())
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
        self._sky_face_px = SKY_FACE_PX if s == 1 else SKY_FACE_PX_SUPERSAMPLED
        self._face_tex = ctx.texture((self._sky_face_px, self._sky_face_px), 4)
        self._face_fbo = ctx.framebuffer([self._face_tex])
        self._sky_cube: moderngl.TextureCube | None = None
        # Scene: S0 colour, S1 aux (packed disparity, leader + texturedness); DIRECT adds final depth.
        self._sdepth = ctx.depth_renderbuffer((W * s, H * s))
        self._scene_fbo = ctx.framebuffer([self._s0, self._s1], self._sdepth)
        self._d_depth = ctx.texture((W, H), 1, dtype="f4")
        # DIRECT (real time, no supersampling) writes final depth in the scene pass.
        self._direct_fbo = (
            ctx.framebuffer([self._s0, self._s1, self._d_depth], self._sdepth) if s == 1 else None
        )
        self._edges_fbo = ctx.framebuffer([self._d_depth])
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

        def mesh(fs: str) -> moderngl.Program:
            return ctx.program(
                vertex_shader=shaders.SCENE_VS, fragment_shader=shaders.with_defines(fs, DIRECT=d)
            )

        sky = ctx.program(
            vertex_shader=shaders.FULLSCREEN_VS,
            fragment_shader=shaders.with_defines(shaders.SKY_FS, DIRECT=d),
        )
        progs = _ScenePrograms(
            ground=mesh(shaders.SCENE_GROUND_FS),
            generic=mesh(shaders.SCENE_GENERIC_FS),
            foliage=mesh(shaders.SCENE_FOLIAGE_FS),
            rotor=mesh(shaders.SCENE_ROTOR_FS),
            sky=sky,
            sky_vao=ctx.vertex_array(sky, [(self._tri, "2f", "in_xy")]),
        )
        cam = self.camera
        for prog in progs.all:
            _set(prog, "u_tex", 4)
            _set(prog, "u_fB", cam.focal_baseline_px_m)
            if direct:
                self._sensor_constants(prog)
        _set(progs.ground, "u_ground", 5)
        _set(progs.sky, "u_sky", 6)
        _set(progs.sky, "u_z", 1.0)
        return progs

    def _sensor_constants(self, prog: moderngl.Program) -> None:
        """Uniforms of the sensor model that never change for a camera (see shaders._SENSOR)."""
        cam = self.camera
        _set(prog, "u_noise", 2)
        _set(prog, "u_half_size", (self.intrinsics.width_px / 2.0, self.intrinsics.height_px / 2.0))
        _set(prog, "u_subpix", cam.subpixel_px if cam.depth_noise else 0.0)
        _set(prog, "u_zrange", (cam.depth_min_m, cam.depth_max_m))
        _set(prog, "u_hole_p", (0.004, 0.10) if cam.depth_holes else (0.0, 0.0))

    def _post_variant(
        self, edges: bool, shadow_px: int, blur_n: int, depth_only: bool = False
    ) -> tuple[moderngl.Program, moderngl.VertexArray]:
        """The post program for one combination of switches, compiled on first use."""
        key = (int(edges), shadow_px if edges else 0, blur_n, int(depth_only))
        if key not in self._post_variants:
            prog = self._ctx.program(
                vertex_shader=shaders.FULLSCREEN_VS,
                fragment_shader=shaders.post_fs(self.supersample, edges, key[1], blur_n, depth_only),
            )
            _set(prog, "u_z", 0.0)
            _set(prog, "u_col", 0)
            _set(prog, "u_aux", 1)
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
            progs.world_vaos = tuple(
                self._vao(p, world_buf) for p in (progs.ground, progs.generic, progs.foliage)
            )
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
        self._near_occluders = np.array(
            [[*o.p_ned_m, max(o.resolved_size_m[0], o.resolved_size_m[1])] for o in visual.occluders],
            dtype=np.float64,
        ).reshape(-1, 4)

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
        faces = np.empty((6, face, face, 4), dtype=np.uint8)
        self._face_fbo.use()
        for i, rows in enumerate(_CUBE_FACES):
            _set(kp, "u_dir_from_st", _mat_bytes(np.array(rows, dtype=np.float64)))
            self._sky_bake_vao.render(moderngl.TRIANGLES)
            self._face_fbo.read_into(faces[i], components=4)
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
        if omega_cam_rad_s is not None and self.camera.motion_blur:
            H0, H1, streak = blur_homographies(self.intrinsics, omega_cam_rad_s, exposure_s)
            if streak > 0.75:
                blur_n = 4 if streak <= 4.0 else (8 if streak <= 8.0 else 16)
        # Real time: the sensor model runs inside the scene pass (no full-screen post pass).
        direct = self._programs_direct is not None and blur_n == 0
        progs = self._programs_direct if direct and self._programs_direct is not None else self._programs
        holes = self.camera.depth_holes
        shadow_px = self._shadow_search_px(cam, leader, extra_vertices)
        region = self._near_region(cam, leader, extra_vertices, shadow_px) if holes else None
        offs = self._rng.integers(0, FIELD_PX, 2)
        k = self.visual.sensor_noise if self.camera.colour_noise else 0.0
        a, b = 0.0008 * analog * k, (0.002 * analog * k) ** 2
        sensor = {
            "u_off": (int(offs[0]), int(offs[1])),
            "u_noise_sd": (0.5 * math.sqrt(a), 0.5 * math.sqrt(b), max(b**0.25, 1e-3)),
            "u_vignette": self.visual.vignetting,
            "u_contrast": self.visual.contrast,
        }

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
        )

        # ---- pass 2: sensor, or (DIRECT) only edge and stereo-shadow holes near objects
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        self._s0.use(0)
        self._s1.use(1)
        self._noise.use(2)
        rgb = np.empty((H, W, 3), dtype=np.uint8)
        depth = np.empty((H, W), dtype=np.float32)
        if direct:
            if region is not None:
                pp, vao = self._post_variant(True, shadow_px, 0, depth_only=True)
                self._post_uniforms(pp, sensor, H0, H1, 0)
                self._edges_fbo.use()
                self._edges_fbo.scissor = region
                vao.render(moderngl.TRIANGLES)
                self._edges_fbo.scissor = None  # type: ignore[assignment]
            aux = np.empty((H, W, 4), dtype=np.uint8)
            dfbo = self._direct_fbo
            assert dfbo is not None  # noqa: S101  (direct implies supersample == 1)
            dfbo.read_into(rgb, components=3, attachment=0)
            dfbo.read_into(aux, components=4, attachment=1)
            dfbo.read_into(depth, components=1, attachment=2, dtype="f4")
            mask = aux[..., 3] >= 128
        else:
            # Whole frame when near things fill much of it (and always for supersampled datasets).
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
            if direct:
                box, count = box_from_mask(mask)
                visible = float(count)
                mask_out = mask.view(np.uint8) * np.uint8(255)
            else:
                box, count = box_from_mask(mask_u8)
                visible = (
                    float(count) if self.supersample == 1 else float(mask_u8.sum(dtype=np.int64)) / 255.0
                )
                mask_out = mask_u8
            if box is not None:
                full = max(self._full_leader_px(cam, leader), visible)
        else:
            mask_out = np.zeros((H, W), dtype=np.uint8) if direct else mask_u8
        return RenderedView(rgb, depth, mask_out, box, visible, full, exposure_s)

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
    ) -> None:
        """Draw the world, distractors, leader, sky and rotor discs into the scene framebuffer."""
        ctx = self._ctx
        gain_rgb = (gain * self._wb[0], gain * self._wb[1], gain * self._wb[2])
        clip_from_ned = _mat_bytes(self._P @ view_matrix(cam))
        cam_ned = tuple(float(c) for c in cam.p_ned_cam_m)
        glare = self._glare_rgb(cam)
        fbo = self._direct_fbo if sensor is not None and self._direct_fbo is not None else self._scene_fbo
        fbo.use()
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        ctx.enable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.disable(moderngl.BLEND)
        ctx.front_face = "cw"  # the y-down projection mirrors the image (see projection_matrix)
        ctx.depth_func = "<"
        self._pattern.use(4)
        self._ground_tex.use(5)
        assert self._sky_cube is not None  # noqa: S101  (baked in set_visual)
        self._sky_cube.use(6)
        self._noise.use(2)
        identity = _mat_bytes(np.eye(4))
        # Ground mip levels: footprint at 1 m = 1 / (f h) metres per pixel (see the ground shader).
        f_px = self.intrinsics.fx_px * self.supersample
        base = -math.log2(f_px * max(-float(cam.p_ned_cam_m[2]), 0.05))
        _set(
            progs.ground,
            "u_ground_lod",
            (base - math.log2(GROUND_PERIOD_M / GROUND_TEX_PX), base - math.log2(0.04)),
        )
        for prog in progs.all:
            _set(prog, "u_glare_rgb", glare)
            _set(prog, "u_clip_from_ned", clip_from_ned)
            _set(prog, "u_ned_from_model", identity)
            _set(prog, "u_cam_ned", cam_ned)
            _set(prog, "u_gain_rgb", gain_rgb)
            _set(prog, "u_leader", 0.0)
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
        for vao, (first, count) in zip(progs.world_vaos[::-1], self.world.groups[::-1], strict=True):
            if count:
                vao.render(moderngl.TRIANGLES, vertices=count, first=first)
        # Sky where nothing was drawn: depth is still 1.0 there.
        ctx.disable(moderngl.CULL_FACE)
        ctx.depth_func = "<="
        fbo.depth_mask = False
        _set(progs.sky, "u_ned_from_pix", _mat_bytes(cam.R_ned_cam @ self._Kinv_fb))
        _set(progs.sky, "u_gain_rgb", tuple(g * SKY_SCALE for g in gain_rgb))
        _set(progs.sky, "u_glare_rgb", tuple(g / SKY_SCALE for g in glare))
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
            ctx.blend_func = (  # type: ignore[assignment]  # moderngl takes 2 or 4 factors
                moderngl.SRC_ALPHA,
                moderngl.ONE_MINUS_SRC_ALPHA,
                moderngl.ONE,
                moderngl.ZERO,
            )
            masks = [(True, True, True, False), (False, False, False, True), (False, False, False, False)]
            fbo.color_mask = masks[: len(fbo.color_attachments)]  # type: ignore[assignment]
            progs.leader_vaos[1].render(moderngl.TRIANGLES)
            fbo.color_mask = [(True, True, True, True)] * len(fbo.color_attachments)  # type: ignore[assignment]
            ctx.disable(moderngl.BLEND)
        fbo.depth_mask = True

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

    def _shadow_search_px(self, cam: CameraPose, leader: LeaderPose | None, extra: F32 | None) -> int:
        """Widest stereo shadow worth searching: disparity of the nearest thing in view, px."""
        z_near = 1e9
        if leader is not None:
            z = float(cam.to_cam(leader.p_ned_m)[2]) - self.leader_model.bound_radius_m
            if z > 0.0:
                z_near = min(z_near, z)
        # Ground seen along the image's bottom corners.
        h = -float(cam.p_ned_cam_m[2])
        if h > 0.0:
            W, H = self.intrinsics.width_px, self.intrinsics.height_px
            rays = (
                cam.R_ned_cam
                @ np.linalg.inv(self.intrinsics.K)
                @ np.array([[0.0, W - 1.0], [H - 1.0, H - 1.0], [1.0, 1.0]])
            )
            down = rays[2]
            if np.any(down > 1e-6):
                z_near = min(z_near, float(np.min(h / down[down > 1e-6])))
        if self._near_occluders.size:
            d = (
                np.linalg.norm(self._near_occluders[:, :2] - cam.p_ned_cam_m[:2], axis=1)
                - self._near_occluders[:, 3]
            )
            z_near = min(z_near, float(max(np.min(d), 0.3)))
        if extra is not None and len(extra):
            zs = (extra[:, :3].astype(np.float64) - cam.p_ned_cam_m) @ cam.R_ned_cam[:, 2]
            zs = zs[zs > NEAR_M]
            if zs.size:
                z_near = min(z_near, float(zs.min()))
        z_near = max(z_near, self.camera.depth_min_m)
        widest = math.ceil(self.camera.focal_baseline_px_m / z_near)
        return min((k for k in SHADOW_OFFSETS_PX if k >= widest), default=max(SHADOW_OFFSETS_PX))

    def _near_region(
        self, cam: CameraPose, leader: LeaderPose | None, extra: F32 | None, shadow_px: int
    ) -> tuple[int, int, int, int] | None:
        """Scissor box (x, y, w, h) around things near enough to have valid depth, or None.

        The leader (its bounding cube), scenario occluders (their footprint cylinders) and distractors
        within the depth range; widened to the left by the stereo shadow. The whole frame if any of
        them straddles the image plane.
        """
        intr = self.intrinsics
        W, H = intr.width_px, intr.height_px
        z_max = self.camera.depth_max_m
        pts: list[NDArray[np.float64]] = []
        if leader is not None:
            R = self.leader_model.bound_radius_m
            c = cam.to_cam(leader.p_ned_m)
            if c[2] - R < z_max:
                cube = np.array(
                    [[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64
                )
                pts.append(c + R * cube)
        for x, y, _, size in self._near_occluders:
            if float(np.hypot(x - cam.p_ned_cam_m[0], y - cam.p_ned_cam_m[1])) - size < z_max:
                return (0, 0, W, H)
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
