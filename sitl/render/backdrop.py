"""The world's backdrop, baked on the GPU once per world: the periodic ground texture and the sky.

The ground's materials are rendered into a mipmapped texture that tiles every ``GROUND_PERIOD_M``; the
sky (gradient, sun, glow, clouds, fog) into six cube faces: at output resolution one atlas that a skybox
samples with ``texelFetch``, supersampled a cube map sampled with linear filtering.
"""

from __future__ import annotations

import math

import moderngl
import numpy as np
from numpy.typing import NDArray

from sitl.render import scene_shaders, shaders
from sitl.render.config import VisualConfig
from sitl.render.gl import mat_bytes, set_uniform
from sitl.render.surroundings import CLOUD_ALTITUDE_M, CLOUD_TEXEL_M, GROUND_PERIOD_M, World

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


def skybox_vertices(face_px: int) -> NDArray[np.float32]:
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


class Backdrop:
    """The baked ground texture and sky of one GL context, and the programs that bake them.

    Args:
        ctx: the renderer's context.
        supersample: the renderer's (1: the sky as an atlas sampled texel by texel; 2: a filtered cube map).
        tri: the full-screen triangle's vertex buffer.
    """

    def __init__(self, ctx: moderngl.Context, supersample: int, tri: moderngl.Buffer) -> None:
        self._ctx = ctx
        self.supersample = s = supersample
        mag = moderngl.LINEAR if s > 1 else moderngl.NEAREST
        self._bake_filter = (
            moderngl.LINEAR_MIPMAP_NEAREST if s > 1 else moderngl.NEAREST_MIPMAP_NEAREST,
            mag,
        )
        self.ground_tex = ctx.texture((GROUND_TEX_PX, GROUND_TEX_PX), 4)
        self._ground_fbo = ctx.framebuffer([self.ground_tex])
        # The sky: at output resolution six faces in one atlas (a skybox samples it with texelFetch);
        # supersampled, a cube map sampled with linear filtering.
        face = self._sky_face_px = SKY_FACE_PX if s == 1 else SKY_FACE_PX_SUPERSAMPLED
        self._face_tex = ctx.texture((face, face * (6 if s == 1 else 1)), 4)
        self._face_tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self._face_fbo = ctx.framebuffer([self._face_tex])
        self._sky_cube: moderngl.TextureCube | None = None
        #: The skybox's triangles (output resolution), see :func:`skybox_vertices`.
        self.skybox = ctx.buffer(skybox_vertices(face).tobytes())
        self._sky_bake_prog = ctx.program(
            vertex_shader=shaders.FULLSCREEN_VS, fragment_shader=scene_shaders.SKY_BAKE_FS
        )
        self._ground_bake_prog = ctx.program(
            vertex_shader=shaders.FULLSCREEN_VS, fragment_shader=scene_shaders.GROUND_BAKE_FS
        )
        self._sky_bake_vao = ctx.vertex_array(self._sky_bake_prog, [(tri, "2f", "in_xy")])
        self._ground_bake_vao = ctx.vertex_array(self._ground_bake_prog, [(tri, "2f", "in_xy")])
        for prog in (self._sky_bake_prog, self._ground_bake_prog):
            set_uniform(prog, "u_tex", 4)
            set_uniform(prog, "u_z", 0.0)

    def bake(self, world: World, visual: VisualConfig, pattern: moderngl.Texture) -> None:
        """Bake a world's ground and sky (``pattern``: the detail pattern texture, bound to unit 4)."""
        self._bake_ground(world, pattern)
        self._bake_sky(world, visual, pattern)

    def _bake_ground(self, world: World, pattern: moderngl.Texture) -> None:
        """Render the world's ground materials into the periodic ground texture (+ mipmaps)."""
        G = world.ground
        bp = self._ground_bake_prog
        set_uniform(bp, "u_ground_rgb", np.asarray(G.rgb, dtype=np.float32).tobytes())
        set_uniform(bp, "u_ground_texture", G.texturedness)
        set_uniform(bp, "u_ground_n", G.n_materials)
        set_uniform(bp, "u_road", G.road)
        set_uniform(bp, "u_rows", G.rows)
        set_uniform(bp, "u_texel_m", GROUND_PERIOD_M / GROUND_TEX_PX)
        self._ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        pattern.use(4)
        self._ground_fbo.use()
        self._ground_bake_vao.render(moderngl.TRIANGLES)
        self.ground_tex.build_mipmaps()
        self.ground_tex.filter = self._bake_filter
        self.ground_tex.repeat_x = self.ground_tex.repeat_y = True

    def _bake_sky(self, world: World, visual: VisualConfig, pattern: moderngl.Texture) -> None:
        """Render the six faces of the world's sky cube map (gradient, sun, glow, clouds, fog)."""
        L = world.lighting
        kp = self._sky_bake_prog
        set_uniform(kp, "u_sun_dir", L.sun_dir_ned)
        set_uniform(kp, "u_sun_rgb", L.sun_rgb)
        set_uniform(kp, "u_sun_cos", math.cos(math.radians(0.35)))
        for name in ("zenith", "horizon", "glow", "haze", "cloud_lit", "cloud_dark"):
            set_uniform(kp, f"u_{name}_rgb", getattr(L, f"{name}_rgb"))
        set_uniform(kp, "u_cloud", (CLOUD_ALTITUDE_M, CLOUD_TEXEL_M, *world.cloud_threshold))
        set_uniform(kp, "u_cloud_off", world.cloud_offset_texels)
        face = self._sky_face_px
        set_uniform(kp, "u_face_px", float(face))
        set_uniform(kp, "u_sky_scale", SKY_SCALE)
        set_uniform(kp, "u_fog_rgb", L.fog_rgb)
        set_uniform(kp, "u_fog_density", visual.fog_density_per_m)
        self._ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        pattern.use(4)
        fbo = self._face_fbo
        fbo.use()
        atlas = self.supersample == 1
        faces = np.empty((6, face, face, 4), dtype=np.uint8)
        for i, rows in enumerate(_CUBE_FACES):
            org_y = face * i if atlas else 0
            fbo.viewport = (0, org_y, face, face)
            set_uniform(kp, "u_face_org", (0.0, float(org_y)))
            set_uniform(kp, "u_dir_from_st", mat_bytes(np.array(rows, dtype=np.float64)))
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

    def sky_tex(self) -> moderngl.Texture | moderngl.TextureCube:
        """The baked sky: the face atlas (output resolution) or the cube map (supersampled)."""
        if self.supersample == 1:
            return self._face_tex
        assert self._sky_cube is not None  # noqa: S101  (baked)
        return self._sky_cube
