"""The renderer against independent geometry: depth vs the noise model, boxes vs silhouettes, occlusion.

Every check here renders real frames through EGL (llvmpipe on CI).
"""

from __future__ import annotations

import math
from collections.abc import Iterator

import numpy as np
import pytest

from companion.kernel.camera import MountConfig
from companion.kernel.frames import R_from_euler, R_from_quat, quat_from_euler, quat_from_R
from sitl.render.airframes import leader_triangles_m
from sitl.render.config import CameraModel, LeaderLook, OccluderSpec, VisualConfig
from sitl.render.geometry import VehiclePose, camera_pose
from sitl.render.noise import depth_sigma_m
from sitl.render.renderer import Renderer

pytestmark = pytest.mark.render

LEVEL_MOUNT = MountConfig(pitch_deg=0.0, x_m=0.0)
#: A plain world: nothing but ground and sky, so the leader is never occluded by accident.
PLAIN = VisualConfig(structures=0, tree_line=False, hills=False, road=False, cloud_cover=0.4)


@pytest.fixture(scope="module")
def renderer() -> Iterator[Renderer]:
    with Renderer(CameraModel(), PLAIN, LEVEL_MOUNT, seed=7) as r:
        yield r


def _follower(yaw_rad: float = 0.0, alt_m: float = 30.0) -> VehiclePose:
    return VehiclePose(np.array([0.0, 0.0, -alt_m]), quat_from_euler(0.0, 0.0, yaw_rad))


def _ray_box_t(origin: np.ndarray, d: np.ndarray, half: np.ndarray) -> float:
    """Distance along a ray (box frame) to an axis-aligned box centred at the origin (slab method)."""
    with np.errstate(divide="ignore"):
        t1 = (-half - origin) / d
        t2 = (half - origin) / d
    t_near = float(np.max(np.minimum(t1, t2)))
    t_far = float(np.min(np.maximum(t1, t2)))
    assert t_near <= t_far, "ray misses the hub"
    return t_near


@pytest.mark.parametrize("range_m", [2.0, 5.0, 10.0])
def test_depth_at_leader_centre_within_noise_model(renderer: Renderer, range_m: float) -> None:
    # Leader straight ahead on the optical axis, nose towards the camera: the axis meets the hub's face.
    renderer.set_visual(PLAIN)
    follower = _follower(alt_m=30.0)
    cam = camera_pose(follower, LEVEL_MOUNT)
    p_leader = cam.p_ned_cam_m + cam.R_ned_cam @ np.array([0.0, 0.0, range_m])
    R_ned_leader = R_from_euler(0.0, 0.0, math.pi)
    leader = VehiclePose(p_leader, quat_from_R(R_ned_leader))
    # Independent truth: where the optical axis enters the hub box, as a depth along the axis.
    hub = np.asarray(renderer.leader_model.hub_half_m)
    axis_ned = cam.R_ned_cam[:, 2]
    t_hit = _ray_box_t(R_ned_leader.T @ (cam.p_ned_cam_m - p_leader), R_ned_leader.T @ axis_ned, hub)
    z_true = t_hit  # the ray is the optical axis: distance along it is depth
    sigma = float(depth_sigma_m(z_true, renderer.intrinsics.fx_px, 0.05, 0.08))
    samples = []
    for i in range(30):
        frame = renderer.render(follower, leader, t_s=i / 30.0)
        patch = frame.depth_m[239:241, 319:321]  # the four pixels around the principal point (319.5, 239.5)
        if i == 0:
            assert frame.truth is not None
            assert abs(float(frame.truth.p_cam_leader_m[2]) - range_m) < 1e-6
            valid0 = patch[patch > 0]
            assert valid0.size > 0
            assert np.all(np.abs(valid0 - z_true) < 3.0 * sigma), (valid0, z_true, sigma)
        samples.extend(patch[patch > 0].tolist())
    s = np.asarray(samples)
    assert s.size >= 0.6 * 120  # holes must not eat the leader's centre
    # Mean: within 3 standard errors (four pixels of one frame share correlated noise: count frames).
    assert abs(float(s.mean()) - z_true) < 3.0 * sigma / math.sqrt(30)
    # Spread: the noise model's sigma, neither switched off nor inflated.
    assert 0.7 * sigma < float(s.std()) < 1.4 * sigma


def _silhouette_box(
    renderer: Renderer, follower: VehiclePose, leader: VehiclePose, pad: int = 0
) -> tuple[np.ndarray, tuple[int, int]]:
    """Leader silhouette by projecting its triangles with numpy and rasterising them on the CPU.

    ``pad`` enlarges the canvas on every side so the unclipped silhouette fits. Returns the mask and
    the pixel offset of the image origin in it.
    """
    intr = renderer.intrinsics
    cam = camera_pose(follower, LEVEL_MOUNT)
    R_ned_body = R_from_quat(leader.q_ned_body_wxyz)
    tris = leader_triangles_m(renderer.leader_model)  # (T, 3, 3) body frame
    p_ned = tris @ R_ned_body.T + leader.p_ned_m
    p_cam = (p_ned - cam.p_ned_cam_m) @ cam.R_ned_cam
    assert np.all(p_cam[..., 2] > 0.05)
    u = intr.fx_px * p_cam[..., 0] / p_cam[..., 2] + intr.cx_px + pad
    v = intr.fy_px * p_cam[..., 1] / p_cam[..., 2] + intr.cy_px + pad
    mask = np.zeros((intr.height_px + 2 * pad, intr.width_px + 2 * pad), dtype=np.uint8)
    _raster_centres(np.stack([u, v], axis=-1), mask)
    return mask, (pad, pad)


def _raster_centres(tris_uv: np.ndarray, mask: np.ndarray) -> None:
    """Mark pixels whose centre (integer coordinates) lies inside a triangle: a plain edge-function
    rasteriser, sampling like GL does (an edge-on triangle covers nothing)."""
    H, W = mask.shape
    for tri in tris_uv:
        (x0, y0), (x1, y1), (x2, y2) = tri
        area = (x1 - x0) * (y2 - y0) - (x2 - x0) * (y1 - y0)
        if abs(area) < 1e-9:
            continue
        c0, c1 = max(int(np.ceil(min(x0, x1, x2))), 0), min(int(np.floor(max(x0, x1, x2))), W - 1)
        r0, r1 = max(int(np.ceil(min(y0, y1, y2))), 0), min(int(np.floor(max(y0, y1, y2))), H - 1)
        if c1 < c0 or r1 < r0:
            continue
        X, Y = np.meshgrid(np.arange(c0, c1 + 1), np.arange(r0, r1 + 1))
        w0 = (x2 - x1) * (Y - y1) - (y2 - y1) * (X - x1)
        w1 = (x0 - x2) * (Y - y2) - (y0 - y2) * (X - x2)
        w2 = (x1 - x0) * (Y - y0) - (y1 - y0) * (X - x0)
        s = np.sign(area)
        inside = (s * w0 >= 0) & (s * w1 >= 0) & (s * w2 >= 0)
        mask[r0 : r1 + 1, c0 : c1 + 1] |= inside.astype(np.uint8)


def _box_of(mask: np.ndarray) -> tuple[float, float, float, float]:
    rows = np.flatnonzero(mask.any(axis=1))
    cols = np.flatnonzero(mask.any(axis=0))
    return float(cols[0]), float(rows[0]), float(cols[-1] + 1), float(rows[-1] + 1)


def _iou(a: tuple[float, ...], b: tuple[float, ...]) -> float:
    ix = max(0.0, min(a[2], b[2]) - max(a[0], b[0]))
    iy = max(0.0, min(a[3], b[3]) - max(a[1], b[1]))
    inter = ix * iy
    return inter / ((a[2] - a[0]) * (a[3] - a[1]) + (b[2] - b[0]) * (b[3] - b[1]) - inter)


CASES = [
    # airframe, range m, pixel (u, v) of the leader centre, leader roll/pitch/yaw deg
    ("f450", 3.0, (320.0, 240.0), (0.0, 0.0, 30.0)),
    ("phantom", 6.0, (150.0, 330.0), (10.0, -5.0, 120.0)),
    ("racer", 2.5, (500.0, 120.0), (-20.0, 15.0, 250.0)),
    ("heavy", 12.0, (420.0, 300.0), (5.0, 5.0, 75.0)),
    ("micro", 1.5, (260.0, 200.0), (0.0, 25.0, 10.0)),
    ("f450", 8.0, (15.0, 240.0), (0.0, 0.0, 200.0)),  # straddles the left image border
]


@pytest.mark.parametrize(("airframe", "range_m", "pixel", "rpy_deg"), CASES)
def test_label_box_matches_projected_silhouette(
    renderer: Renderer,
    airframe: str,
    range_m: float,
    pixel: tuple[float, float],
    rpy_deg: tuple[float, float, float],
) -> None:
    renderer.set_visual(PLAIN.model_copy(update={"leader": LeaderLook(airframe=airframe)}))  # type: ignore[arg-type]
    follower = _follower(yaw_rad=0.4)
    cam = camera_pose(follower, LEVEL_MOUNT)
    ray = np.linalg.inv(renderer.intrinsics.K) @ np.array([pixel[0], pixel[1], 1.0])
    p_leader = cam.p_ned_cam_m + cam.R_ned_cam @ (range_m * ray / np.linalg.norm(ray))
    q = quat_from_euler(*(math.radians(a) for a in rpy_deg))
    leader = VehiclePose(p_leader, q)
    frame = renderer.render(follower, leader, t_s=0.0)
    assert frame.truth is not None
    assert frame.truth.box_xyxy_px is not None
    pad = 400
    mask, (ox, oy) = _silhouette_box(renderer, follower, leader, pad=pad)
    in_frame = mask[oy : oy + 480, ox : ox + 640]
    expected = _box_of(in_frame)
    iou = _iou(frame.truth.box_xyxy_px, expected)
    assert iou >= 0.9, (frame.truth.box_xyxy_px, expected, iou)
    # Visible fraction: pixels inside the frame over the whole silhouette (nothing occludes here).
    fraction = float(in_frame.sum()) / float(mask.sum())
    assert abs(frame.truth.visible_fraction - fraction) < 0.06, (frame.truth.visible_fraction, fraction)


def test_occluder_hides_part_of_the_leader(renderer: Renderer) -> None:
    # Camera looks north; a wall 3 m ahead covers everything west of east = 0: the leader's left half.
    wall = OccluderSpec(kind="wall", p_ned_m=(3.0, -3.0, 0.0), size_m=(0.2, 6.0, 40.0))
    leader = VehiclePose(np.array([6.0, 0.0, -30.0]), quat_from_euler(0.0, 0.0, 0.3))
    follower = _follower(alt_m=30.0)
    renderer.set_visual(PLAIN)
    clear = renderer.render(follower, leader, 0.0)
    renderer.set_visual(PLAIN.model_copy(update={"occluders": (wall,)}))
    hidden = renderer.render(follower, leader, 0.0)
    assert clear.truth is not None
    assert hidden.truth is not None
    assert clear.truth.box_xyxy_px is not None
    assert hidden.truth.box_xyxy_px is not None
    assert clear.truth.visible_fraction > 0.97
    assert 0.3 < hidden.truth.visible_fraction < 0.7
    # The box shrinks from the left to the wall's edge at the principal point's column.
    assert hidden.truth.box_xyxy_px[0] > clear.truth.box_xyxy_px[0] + 10
    assert abs(hidden.truth.box_xyxy_px[0] - 320.0) <= 2.0
    assert hidden.truth.box_xyxy_px[2] == clear.truth.box_xyxy_px[2]
    # Depth at the wall is the wall's (3 m minus half its thickness), with noise.
    wall_depth = hidden.depth_m[200:280, 100:300]
    valid = wall_depth[wall_depth > 0]
    assert valid.size > 0.8 * wall_depth.size
    assert abs(float(np.median(valid)) - 2.9) < 0.02


def test_stereo_shadow_left_of_a_near_leader(renderer: Renderer) -> None:
    # A near leader in front of a far wall: the right imager cannot see the wall just left of the
    # leader (a band as wide as the disparity difference), while just right of it the wall is seen.
    wall = OccluderSpec(kind="wall", p_ned_m=(7.0, 0.0, 0.0), size_m=(0.2, 30.0, 60.0))
    renderer.set_visual(
        PLAIN.model_copy(update={"occluders": (wall,), "leader": LeaderLook(airframe="heavy")})
    )
    follower = _follower(alt_m=30.0)
    leader = VehiclePose(np.array([2.0, 0.0, -30.0]), quat_from_euler(0.0, 0.0, 0.0))
    frame = renderer.render(follower, leader, 0.0)
    fB = renderer.camera.focal_baseline_px_m
    band = int(fB / 1.85 - fB / 6.9) - 2  # disparity of the hub's face minus the wall's, px, less a margin
    # Per row through the hub, the leader's opaque extent (props are translucent to the stereo pair).
    left, right, far_left = [], [], []
    for row in frame.depth_m[232:248]:
        cols = np.flatnonzero((row > 0) & (row < 3.0))
        if cols.size < 10:
            continue
        x_l, x_r = int(cols[0]), int(cols[-1])
        left.append(row[x_l - band : x_l - 1])
        right.append(row[x_r + 2 : x_r + band])
        far_left.append(row[x_l - band - 40 : x_l - band - 10])
    assert len(left) >= 8
    assert np.mean(np.concatenate(left) == 0) > 0.9
    assert np.mean(np.concatenate(right) > 0) > 0.75
    assert np.mean(np.concatenate(far_left) > 0) > 0.75


def _projected_box(renderer: Renderer, follower: VehiclePose, p_ned_m: np.ndarray) -> tuple[int, ...]:
    """Pixel box (x0, y0, x1, y1) of a vehicle's bounding cube, clipped to the image."""
    cam = camera_pose(follower, LEVEL_MOUNT)
    intr = renderer.intrinsics
    R = renderer.leader_model.bound_radius_m
    cube = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    corners = cam.to_cam(p_ned_m) + R * cube
    u = intr.fx_px * corners[:, 0] / corners[:, 2] + intr.cx_px
    v = intr.fy_px * corners[:, 1] / corners[:, 2] + intr.cy_px
    x0, y0 = max(int(u.min()), 0), max(int(v.min()), 0)
    x1, y1 = min(int(u.max()) + 1, intr.width_px), min(int(v.max()) + 1, intr.height_px)
    return x0, y0, x1, y1


def test_other_vehicle_is_solid_but_not_the_leader(renderer: Renderer) -> None:
    # The leader right of centre, another vehicle of the same airframe left of it, apart in the image.
    renderer.set_visual(PLAIN)
    follower = _follower(alt_m=30.0)
    leader = VehiclePose(np.array([6.0, 1.0, -30.0]), quat_from_euler(0.0, 0.0, 0.4))
    other = VehiclePose(np.array([5.0, -1.2, -30.0]), quat_from_euler(0.0, 0.0, 2.0))
    alone = renderer.render(follower, leader, 0.0)
    both = renderer.render(follower, leader, 0.0, others=[other])
    assert alone.truth is not None
    assert both.truth is not None
    # The truth stays the leader's alone.
    assert alone.truth.box_xyxy_px is not None
    assert both.truth.box_xyxy_px == alone.truth.box_xyxy_px
    assert both.truth.visible_fraction == alone.truth.visible_fraction
    assert np.array_equal(both.truth.p_cam_leader_m, alone.truth.p_cam_leader_m)
    x0, y0, x1, y1 = _projected_box(renderer, follower, other.p_ned_m)
    assert x1 <= alone.truth.box_xyxy_px[0]  # apart from the leader in the image
    # The other vehicle has depth at its range (nothing else in its box is within the depth range).
    z_true = float(camera_pose(follower, LEVEL_MOUNT).to_cam(other.p_ned_m)[2])
    patch = both.depth_m[y0:y1, x0:x1]
    valid = patch[patch > 0]
    assert valid.size > 50
    assert abs(float(np.median(valid)) - z_true) < 0.1 * z_true, (float(np.median(valid)), z_true)
    empty = alone.depth_m[y0:y1, x0:x1]
    assert np.count_nonzero(empty) < 5
    assert not np.array_equal(both.rgb[y0:y1, x0:x1], alone.rgb[y0:y1, x0:x1])


def test_other_vehicle_in_front_hides_the_leader(renderer: Renderer) -> None:
    renderer.set_visual(PLAIN)
    follower = _follower(alt_m=30.0)
    leader = VehiclePose(np.array([8.0, 0.0, -30.0]), quat_from_euler(0.0, 0.0, 0.4))
    front = VehiclePose(np.array([4.0, 0.25, -30.0]), quat_from_euler(0.0, 0.0, 1.0))  # half across it
    clear = renderer.render(follower, leader, 0.0)
    hidden = renderer.render(follower, leader, 0.0, others=[front])
    assert clear.truth is not None
    assert hidden.truth is not None
    assert clear.truth.visible_fraction > 0.97
    assert hidden.truth.box_xyxy_px is not None
    assert hidden.truth.visible_fraction < clear.truth.visible_fraction - 0.2


def test_no_leader_frame(renderer: Renderer) -> None:
    renderer.set_visual(PLAIN)
    frame = renderer.render(_follower(), None, 1.0)
    assert frame.truth is not None
    assert frame.truth.box_xyxy_px is None
    assert frame.truth.visible_fraction == 0.0
    assert np.all(np.isnan(frame.truth.p_cam_leader_m))
    assert frame.rgb.shape == (480, 640, 3)
    assert frame.rgb.dtype == np.uint8
    assert frame.depth_m.dtype == np.float32
    assert frame.stamp_s == 1.0


def test_frames_repeat_for_a_seed() -> None:
    follower = _follower(alt_m=3.0)
    leader = VehiclePose(np.array([5.0, 0.5, -3.5]), quat_from_euler(0.1, 0.0, 1.0))
    frames = []
    visual = PLAIN.model_copy(update={"seed": 3, "structures": 5})
    for _ in range(2):
        with Renderer(CameraModel(), visual, seed=11) as r:
            frames.append([r.render(follower, leader, 0.1 * i) for i in range(2)])
    for a, b in zip(*frames, strict=True):
        assert np.array_equal(a.rgb, b.rgb)
        assert np.array_equal(a.depth_m, b.depth_m)
    # Consecutive frames differ (fresh sensor noise every frame).
    assert not np.array_equal(frames[0][0].depth_m, frames[0][1].depth_m)
