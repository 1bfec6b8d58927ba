"""The renderer's GL context, its render targets and the scene pass (see :mod:`sitl.render.renderer`).

:class:`SceneRenderer` owns the context: the targets of every pass, the scene programs (for the post
pass, and DIRECT: with the sensor model inside), the world and the leader on the GPU, and draws pass 1,
the scene: world chunks in view, distractors, the leader and the other vehicles (the leader's airframe,
not marked as leader), the sky where nothing was drawn, and the rotor discs blended.
:class:`~sitl.render.renderer.Renderer` adds the sensor passes, exposure and the truth.

One context per renderer: create it, render and close it on the same thread.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from types import TracebackType
from typing import Any, Self

import moderngl
import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import Intrinsics, MountConfig
from companion.kernel.errors import CameraError
from companion.kernel.frames import R_body_cam_from_mount
from sitl.render import scene_shaders, shaders
from sitl.render.airframes import LeaderModel, build_leader
from sitl.render.backdrop import GROUND_TEX_PX, SKY_SCALE, Backdrop
from sitl.render.config import CameraModel, VisualConfig
from sitl.render.geometry import CameraPose, LeaderPose, model_matrix, projection_matrix, view_matrix
from sitl.render.gl import IDENTITY4, ScenePrograms, color_mask, mat_bytes, set_uniform
from sitl.render.meshes import F32, VERTEX_ATTRIBUTES, VERTEX_FLOATS, VERTEX_FORMAT
from sitl.render.noise import FIELD_PX, pattern_texture, sensor_noise_field
from sitl.render.sensor import sensor_constants, white_balance_gains
from sitl.render.surroundings import GROUND_PERIOD_M, GROUPS, World, build_world
from sitl.render.view import FAR_M, NEAR_M, frustum_normals

U8 = NDArray[np.uint8]
#: Indices into ``world.GROUPS``: crowns, generic, diffuse, band, ground.
_WORLD_DRAW_ORDER = (2, 1, 4, 3, 0)
#: Bytes of one indirect draw record (moderngl's stride for glMultiDrawArraysIndirect).
INDIRECT_BYTES = 20


class SceneRenderer:
    """The GL context of a :class:`~sitl.render.renderer.Renderer`, its targets, and the scene pass.

    Takes the renderer's arguments (see there); not used on its own.
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
        self._tri = ctx.buffer(np.array([-1.0, -1.0, 3.0, -1.0, -1.0, 3.0], dtype=np.float32).tobytes())
        # Baked once per world (set_visual): the ground's materials and the sky.
        self._backdrop = Backdrop(ctx, s, self._tri)
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
        self._indirect = ctx.buffer(reserve=INDIRECT_BYTES * 1024, dynamic=True)
        self._Kinv = np.linalg.inv(self.intrinsics.K)
        # A turn by a small angle moves no pixel further than this many px per rad (pitch or yaw:
        # f (1 + r^2 / f^2) at the corner radius r; roll: r), so slower turns skip the blur maths.
        r_px = math.hypot(self.intrinsics.width_px, self.intrinsics.height_px) / 2.0 + 1.0
        f_px = max(self.intrinsics.fx_px, self.intrinsics.fy_px)
        self._streak_px_per_rad = f_px + r_px * r_px / f_px + r_px
        self._frustum_n = frustum_normals(self.intrinsics, margin_px=2.0)
        # Post: final colour, depth and leader coverage.
        self._p_rgb = ctx.texture((W, H), 4)
        self._p_depth = ctx.texture((W, H), 1, dtype="f4")
        self._p_mask = ctx.texture((W, H), 1)
        self._post_fbo = ctx.framebuffer([self._p_rgb, self._p_depth, self._p_mask])

        self._programs = self._scene_programs(direct=False)
        self._programs_direct = self._scene_programs(direct=True) if s == 1 else None
        self._mask_prog = ctx.program(vertex_shader=scene_shaders.SCENE_VS, fragment_shader=shaders.MASK_FS)
        self._post_variants: dict[
            tuple[int, int, int, int], tuple[moderngl.Program, moderngl.VertexArray]
        ] = {}
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
    def _program_sets(self) -> tuple[ScenePrograms, ...]:
        return (self._programs,) if self._programs_direct is None else (self._programs, self._programs_direct)

    def _scene_programs(self, direct: bool) -> ScenePrograms:
        ctx = self._ctx
        d = int(direct)

        filtered = int(self.supersample > 1)

        def mesh(fs: str, *, band: int = 0, diffuse: int = 0) -> moderngl.Program:
            return ctx.program(
                vertex_shader=scene_shaders.SCENE_VS,
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
                vertex_shader=scene_shaders.SKYBOX_VS,
                fragment_shader=shaders.with_defines(scene_shaders.SKYBOX_FS, DIRECT=d),
            )
            sky_vao = ctx.vertex_array(sky, [(self._backdrop.skybox, "3f 2f", "in_dir", "in_uv")])
        else:
            sky = ctx.program(vertex_shader=shaders.FULLSCREEN_VS, fragment_shader=scene_shaders.SKY_FS)
            sky_vao = ctx.vertex_array(sky, [(self._tri, "2f", "in_xy")])
        progs = ScenePrograms(
            ground=mesh(scene_shaders.SCENE_GROUND_FS),
            generic=mesh(scene_shaders.SCENE_GENERIC_FS),
            foliage=mesh(scene_shaders.SCENE_FOLIAGE_FS),
            band=mesh(scene_shaders.SCENE_FOLIAGE_FS, band=1),
            diffuse=mesh(scene_shaders.SCENE_GENERIC_FS, diffuse=1),
            rotor=mesh(scene_shaders.SCENE_ROTOR_FS),
            sky=sky,
            sky_vao=sky_vao,
        )
        cam = self.camera
        for prog in progs.all:
            set_uniform(prog, "u_tex", 4)
            set_uniform(prog, "u_fB", cam.focal_baseline_px_m)
            if direct:
                sensor_constants(prog, cam)
        set_uniform(progs.ground, "u_ground", 5)
        set_uniform(progs.sky, "u_sky", 6)
        set_uniform(progs.sky, "u_sky_atlas", 6)
        set_uniform(progs.sky, "u_z", 1.0)
        return progs

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
                set_uniform(prog, "u_sun_dir", L.sun_dir_ned)
                set_uniform(prog, "u_sun_rgb", L.sun_rgb)
                set_uniform(prog, "u_sky_rgb", L.sky_rgb)
                set_uniform(prog, "u_bounce_rgb", L.bounce_rgb)
                set_uniform(prog, "u_fog_rgb", L.fog_rgb)
                set_uniform(prog, "u_fog_density", visual.fog_density_per_m)
            set_uniform(progs.ground, "u_ground_light", tuple(float(c) for c in ground_light))
        self._backdrop.bake(self.world, visual, self._pattern)
        self._wb = white_balance_gains(visual.white_balance_k)
        self._log2_gain = None
        chunks = self.world.chunks
        self._chunk_order = np.argsort(chunks.first, kind="stable")
        self._chunk_group_sorted = chunks.group[self._chunk_order]
        self._records_key = b""
        self._records_offsets: list[int] = []

    # ---- the scene pass --------------------------------------------------------------------------------

    def _scene_pass(
        self,
        progs: ScenePrograms,
        cam: CameraPose,
        leader: LeaderPose | None,
        t_s: float,
        *,
        gain: float,
        exposure_s: float,
        extra_vertices: F32 | None,
        sensor: dict[str, Any] | None,
        in_view: NDArray[np.bool_],
        others: Sequence[LeaderPose] = (),
    ) -> None:
        """Draw the world chunks in view, distractors, leader, other vehicles, sky and rotor discs.

        ``others`` have the leader's airframe but leave the leader mask alone (``u_leader`` = 0).
        """
        ctx = self._ctx
        gain_rgb = (gain * self._wb[0], gain * self._wb[1], gain * self._wb[2])
        clip_from_ned = mat_bytes(self._P @ view_matrix(cam))
        cam_ned = tuple(float(c) for c in cam.p_ned_cam_m)
        glare = self._glare_rgb(cam)
        direct = sensor is not None and self._direct_fbo is not None
        fbo = self._direct_fbo if direct and self._direct_fbo is not None else self._scene_fbo
        fbo.use()
        on, off = (True, True, True, True), (False, False, False, False)
        if self.supersample == 1:
            # The skybox covers every pixel nothing else drew: only depth needs clearing.
            color_mask(fbo, [off, off])
        fbo.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        color_mask(fbo, [on, on])
        fbo.use()  # moderngl applies a restored single-attachment mask only on use() after a clear
        ctx.enable(moderngl.DEPTH_TEST | moderngl.CULL_FACE)
        ctx.disable(moderngl.BLEND)
        ctx.front_face = "cw"  # the y-down projection mirrors the image (see projection_matrix)
        ctx.depth_func = "<"
        self._pattern.use(4)
        self._backdrop.ground_tex.use(5)
        self._noise.use(2)
        identity = IDENTITY4
        # Ground mip levels: footprint at 1 m = 1 / (f h) metres per pixel (see the ground shader).
        f_px = self.intrinsics.fx_px * self.supersample
        base = -math.log2(f_px * max(-float(cam.p_ned_cam_m[2]), 0.05))
        lod = (base - math.log2(GROUND_PERIOD_M / GROUND_TEX_PX), base - math.log2(0.04))
        set_uniform(progs.ground, "u_ground_lod", lod)
        set_uniform(progs.ground, "u_ground_lod_k", (2.0 ** (lod[0] + 0.5), 2.0 ** (lod[1] + 0.5)))
        glare_gain = (glare[0] * gain_rgb[0], glare[1] * gain_rgb[1], glare[2] * gain_rgb[2])
        for prog in progs.all:
            set_uniform(prog, "u_glare_rgb", glare_gain)
            set_uniform(prog, "u_clip_from_ned", clip_from_ned)
            set_uniform(prog, "u_ned_from_model", identity)
            set_uniform(prog, "u_cam_ned", cam_ned)
            set_uniform(prog, "u_gain_rgb", gain_rgb)
            set_uniform(prog, "u_leader", 0.0)
            set_uniform(prog, "u_blend_alpha", 0.0)
            if sensor is not None:
                for name, value in sensor.items():
                    set_uniform(prog, name, value)
        # Near things first so that early depth testing spares the far ones.
        model = mat_bytes(model_matrix(leader.R_ned_body, leader.p_ned_m)) if leader is not None else identity
        # Vehicles as (model matrix, leader flag, distance from the camera, m).
        vehicles = [(model, 1.0, 0.0)] if leader is not None else []
        vehicles += [
            (
                mat_bytes(model_matrix(o.R_ned_body, o.p_ned_m)),
                0.0,
                float(np.linalg.norm(o.p_ned_m - cam.p_ned_cam_m)),
            )
            for o in others
        ]
        for m, is_leader, _ in vehicles:
            set_uniform(progs.generic, "u_ned_from_model", m)
            set_uniform(progs.generic, "u_leader", is_leader)
            progs.leader_vaos[0].render(moderngl.TRIANGLES)
        if vehicles:
            set_uniform(progs.generic, "u_ned_from_model", identity)
            set_uniform(progs.generic, "u_leader", 0.0)
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
        self._backdrop.sky_tex().use(6)
        set_uniform(progs.sky, "u_ned_from_pix", mat_bytes(cam.R_ned_cam @ self._Kinv_fb))
        set_uniform(progs.sky, "u_gain_rgb", tuple(g * SKY_SCALE for g in gain_rgb))
        progs.sky_vao.render(moderngl.TRIANGLES)
        if vehicles:
            # Rotor discs: blend colour, mark the mask (aux alpha), leave depth and texturedness alone.
            # Far to near (the discs write no depth): a nearer disc covers a farther one.
            rotor_phase, blade_vis = self._rotor_state(t_s, exposure_s)
            rp = progs.rotor
            set_uniform(rp, "u_blade_vis", blade_vis)
            ctx.depth_func = "<"
            for k in sorted(range(len(vehicles)), key=lambda i: -vehicles[i][2]):
                m, is_leader, _ = vehicles[k]
                set_uniform(rp, "u_ned_from_model", m)
                set_uniform(rp, "u_leader", is_leader)
                # Each other vehicle's blades turn at their own phase.
                set_uniform(rp, "u_rotor_phase", math.fmod(rotor_phase + 1.1 * k, math.pi))
                ctx.enable(moderngl.BLEND)
                # Blend the colour by the disc's opacity. The aux alpha (leader + texturedness) takes the
                # disc's value; DIRECT writes that into colour alpha in a second, unblended pass.
                ctx.blend_func = (  # type: ignore[assignment]  # moderngl takes 2 or 4 factors
                    moderngl.SRC_ALPHA,
                    moderngl.ONE_MINUS_SRC_ALPHA,
                    moderngl.ONE,
                    moderngl.ZERO,
                )
                set_uniform(rp, "u_blend_alpha", 1.0)
                color_mask(fbo, [(True, True, True, False), (False, False, False, True)])
                progs.leader_vaos[1].render(moderngl.TRIANGLES)
                ctx.disable(moderngl.BLEND)
                if direct:
                    set_uniform(rp, "u_blend_alpha", 0.0)
                    color_mask(fbo, [(False, False, False, True)])
                    progs.leader_vaos[1].render(moderngl.TRIANGLES)
                color_mask(fbo, [on, on])
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
        rec = np.zeros((starts.size, INDIRECT_BYTES // 4), dtype=np.uint32)
        rec[:, 0], rec[:, 1], rec[:, 2] = count, 1, first
        if rec.nbytes > self._indirect.size:
            self._indirect.orphan(rec.nbytes * 2)
        if rec.size:
            self._indirect.write(rec.tobytes())
        run_group = group[starts]
        self._records_key = key
        self._records_offsets = [int(np.searchsorted(run_group, g)) for g in range(len(GROUPS) + 1)]
        return self._records_offsets
