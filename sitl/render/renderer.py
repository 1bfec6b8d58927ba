"""Offscreen RGB-D renderer of the follower's camera (moderngl through EGL; llvmpipe or a GPU).

``Renderer.render(follower_truth, leader_truth, t_s, others=()) -> RgbdFrame`` is the whole API a
lockstep harness needs; :meth:`Renderer.render_view` renders from an explicit camera pose (datasets).
``others`` are further vehicles with the leader's airframe (formations): solid in colour and depth, never
in the leader's mask or truth.

A frame is two passes (see :mod:`sitl.render.shaders`): the scene into RGBA8 colour + packed depth,
then the sensor model into RGB8 colour, float32 depth (m along the optical axis, 0 = invalid) and the
leader mask. The ground truth box comes from that mask: the leader's visible pixels, after occlusion
and clipping. A third, tiny pass draws the leader alone on a canvas with a shifted principal point to
count how many pixels it would cover unoccluded and unclipped (the visible fraction's denominator).

The pieces: :mod:`sitl.render.scene` (the context, its targets and the scene pass),
:mod:`sitl.render.backdrop` (the baked ground and sky), :mod:`sitl.render.view` (culling and the
regions where depth can be valid), :mod:`sitl.render.sensor` (exposure and the sensor model's
uniforms); this module renders a frame: the passes in turn, read-back, and the truth.

One ``Renderer`` owns one GL context: create it, render and close it on the same thread.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import cv2
import moderngl
import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import GroundTruth, RgbdFrame
from companion.kernel.frames import Mat3, R_from_quat, Vec3
from sitl.render import shaders
from sitl.render.geometry import (
    Box,
    CameraPose,
    LeaderPose,
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
from sitl.render.gl import mat_bytes, set_uniform
from sitl.render.meshes import F32
from sitl.render.scene import SceneRenderer
from sitl.render.sensor import (
    AE_TARGET,
    GAIN_AT_MAX_SHUTTER,
    metered_log2_gain,
    sensor_constants,
    sensor_uniforms,
)
from sitl.render.view import (
    FAR_M,
    NEAR_M,
    Blockers,
    chunks_in_view,
    ground_region,
    leader_span,
    may_hide_leader,
    near_region,
    shadow_search_px,
)

U8 = NDArray[np.uint8]


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


class Renderer(SceneRenderer):
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
        self._log2_gain = metered_log2_gain(self._log2_gain, rgb)

    # ---- rendering -------------------------------------------------------------------------------------

    def render(
        self,
        follower: PoseTruth,
        leader: PoseTruth | None,
        t_s: float,
        others: Sequence[PoseTruth] = (),
    ) -> RgbdFrame:
        """The follower's camera frame at sim time ``t_s`` with ground truth about the leader.

        ``follower`` may carry ``omega_body_rad_s`` (FRD body rate); it then drives motion blur.
        Without a leader the truth has no box, visible fraction 0 and NaN position and yaw.
        ``others``: poses (NED, m; body -> NED quaternion) of other vehicles drawn with the leader's
        airframe; they may hide the leader but are not in its truth.
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
        other_poses = [
            LeaderPose(R_from_quat(np.asarray(o.q_ned_body_wxyz, dtype=np.float64)), as_vec3(o.p_ned_m))
            for o in others
        ]
        view = self.render_view(cam, lp, t_s, omega_cam_rad_s=omega_cam, others=other_poses)
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
        others: Sequence[LeaderPose] = (),
    ) -> RenderedView:
        """Render from an explicit camera pose; ``extra_vertices`` are distractors (NED, never leader).

        ``others``: other vehicles with the leader's airframe (NED poses), never marked as leader.
        """
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
        in_view = chunks_in_view(chunk_cam, C.radius_m, self._frustum_n)
        standing = in_view & (C.group != 0)  # in view and not the ground
        near = standing & (chunk_cam[:, 2] - C.radius_m < self.camera.depth_max_m)
        near_cam, near_r = chunk_cam[near], C.radius_m[near]
        shadow_px = shadow_search_px(
            cam,
            leader,
            extra_vertices,
            camera=self.camera,
            intr=self.intrinsics,
            Kinv=self._Kinv,
            bound_radius_m=self.leader_model.bound_radius_m,
            near_cam=near_cam,
            near_r=near_r,
            others=others,
        )
        region = near_region(
            cam,
            leader,
            extra_vertices,
            intr=self.intrinsics,
            depth_max_m=self.camera.depth_max_m,
            bound_radius_m=self.leader_model.bound_radius_m,
            shadow_px=shadow_px,
            near_cam=near_cam,
            near_r=near_r,
            others=others,
        )
        sensor = sensor_uniforms(self._rng, self.camera, self.visual, self.intrinsics, analog)

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
            others=others,
        )

        # ---- pass 2: sensor, or (DIRECT) only edge and stereo-shadow holes near objects
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        self._noise.use(2)
        depth = np.empty((H, W), dtype=np.float32)
        if direct:
            ground = ground_region(
                cam, intr=self.intrinsics, Kinv=self._Kinv, depth_max_m=self.camera.depth_max_m
            )
            return self._finish_direct(
                cam,
                leader,
                boxes=[b for b in (region, ground) if b is not None],
                blockers=(chunk_cam[standing], C.radius_m[standing], extra_vertices, others),
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
        blockers: Blockers,
        shadow_px: int,
        sensor: dict[str, Any],
        depth: NDArray[np.float32],
        exposure_s: float,
        truth: bool,
    ) -> RenderedView:
        """After a DIRECT scene pass: the depth pass where depth can be valid, read-back, leader truth.

        ``boxes`` are scissor boxes (x, y, w, h) that hold every pixel whose true depth is in range
        (near objects, near ground); depth is 0 elsewhere. ``blockers``: what could hide the leader
        (bounding spheres of the world chunks in view, camera frame; distractor vertices; other vehicles).
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
        span, inside = (
            leader_span(cam, leader, intr=self.intrinsics, bound_radius_m=self.leader_model.bound_radius_m)
            if truth
            else (None, False)
        )
        if leader is not None and span is not None:
            x0, y0, x1, y1 = span
            # Colour alpha < 0.5 marks the leader (its opaque parts and rotor discs; see scene_shaders.emit).
            sub = rgba[y0:y1, x0:x1, 3] < 128
            sub_box, count = box_from_mask(sub)
            if sub_box is not None:
                mask[y0:y1, x0:x1] = sub.view(np.uint8) * np.uint8(255)
                box = (sub_box[0] + x0, sub_box[1] + y0, sub_box[2] + x0, sub_box[3] + y0)
                visible = float(count)
                # Wholly in the frame with nothing in front: every pixel it covers is visible (the
                # leader-alone pass would count the same pixels, up to its sampling offset).
                if inside and not may_hide_leader(
                    cam,
                    leader,
                    span,
                    blockers,
                    intr=self.intrinsics,
                    bound_radius_m=self.leader_model.bound_radius_m,
                ):
                    full = visible
                else:
                    full = max(self._full_leader_px(cam, leader), visible)
        return RenderedView(rgb, depth, mask, box, visible, full, exposure_s)

    # ---- the sensor passes -----------------------------------------------------------------------------

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
            set_uniform(prog, "u_z", 0.0)
            set_uniform(prog, "u_col", 0)
            set_uniform(prog, "u_aux", 1)
            set_uniform(prog, "u_zbuf", 3)
            set_uniform(prog, "u_disp_from_z", self._disp_from_window_z)
            set_uniform(prog, "u_size", (self.intrinsics.width_px, self.intrinsics.height_px))
            set_uniform(prog, "u_fB", self.camera.focal_baseline_px_m)
            sensor_constants(prog, self.camera)
            self._post_variants[key] = (prog, self._ctx.vertex_array(prog, [(self._tri, "2f", "in_xy")]))
        return self._post_variants[key]

    def _post_uniforms(
        self, prog: moderngl.Program, sensor: dict[str, Any], H0: Mat3, H1: Mat3, blur_n: int
    ) -> None:
        for name, value in sensor.items():
            set_uniform(prog, name, value)
        if blur_n:
            set_uniform(prog, "u_H0", mat_bytes(H0))
            set_uniform(prog, "u_H1", mat_bytes(H1))

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
        set_uniform(mp, "u_clip_from_ned", mat_bytes(P @ view_matrix(cam)))
        set_uniform(mp, "u_ned_from_model", mat_bytes(model_matrix(leader.R_ned_body, leader.p_ned_m)))
        for vao in self._mask_vaos:
            vao.render(moderngl.TRIANGLES)
        fbo.read_into(buf, components=1)
        return float(np.count_nonzero(buf)) / float(s * s)

    def _mask_fbo(self, size: int) -> tuple[moderngl.Framebuffer, U8]:
        if size not in self._mask_fbos:
            tex = self._ctx.texture((size, size), 1)
            self._mask_fbos[size] = (self._ctx.framebuffer([tex]), np.empty((size, size), dtype=np.uint8))
        return self._mask_fbos[size]
