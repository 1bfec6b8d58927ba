"""Domain randomisation for detector datasets: seeded samplers of short sequences. Pure numpy, no GL.

A sequence is a few frames of one scene (same world, light, leader look), with the camera and the
leader moving a little between frames: near-duplicates live inside one sequence, so splitting the
dataset by sequence keeps them out of different splits. What varies between sequences is chosen with
real photos of small drones in mind: mostly seen from below or level against bright, hazy or overcast
sky, tree lines and horizons; sizes from a few pixels to a third of the frame; dark silhouettes with
faint prop discs; varied exposure, white balance, noise, blur and JPEG compression.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from companion.kernel.camera import Intrinsics
from companion.kernel.frames import R_BODY_CAM_LEVEL, Mat3, R_from_euler, Vec3
from sitl.render.config import AIRFRAME_SPAN_M, RGB, LeaderLook, OccluderSpec, VisualConfig
from sitl.render.distractors import balloon_mesh, bird_mesh, debris_mesh, distractor_vertices, plane_mesh
from sitl.render.geometry import CameraPose, rotation_vector_matrix
from sitl.render.meshes import F32, Kind, Mesh

SPLITS = ("train", "val", "test")

#: ``wide``: every way a small drone shows up in a photo (below, level, above; 1-20 m; anywhere in the
#: frame). ``formation``: the follower's own view in flight (camera within about 15 deg of level, the leader
#: 2-15 m away near the middle of the image, usually the f450 the simulator flies), so the detector sees
#: the case the closed loop lives in (a dark airframe against ground, horizon and tree line) often enough.
#: ``clutter``: that view with a structure behind the leader. ``near``: the view of a formation slot, the
#: leader 5-12 m away (small at the whole-frame input: about 15-35 px of a 416 px letterbox for an f450),
#: with a tree, conifer, building or wall behind it in most sequences, where a detector loses it.
PROFILES = ("wide", "formation", "clutter", "near")
#: Leader range of the ``near`` profile, m.
NEAR_RANGE_M = (5.0, 12.0)


def split_of(seed: int, index: int) -> str:
    """Train, val or test for sequence ``index``: 8/1/1 in every block of ten, shuffled by the seed."""
    order = np.random.default_rng([seed, 7919]).permutation(10)
    slot = int(order[index % 10])
    return "train" if slot < 8 else ("val" if slot == 8 else "test")


#: Seconds between frames of a sequence (near-duplicates, but not identical).
FRAME_DT_S = 0.1

_AIRFRAMES = ("f450", "phantom", "racer", "heavy", "micro")
_AIRFRAME_P = (0.3, 0.25, 0.15, 0.15, 0.15)
_BODY_COLOURS: tuple[RGB, ...] = (
    (0.02, 0.02, 0.02),
    (0.05, 0.05, 0.055),
    (0.75, 0.75, 0.73),
    (0.35, 0.35, 0.36),
    (0.55, 0.04, 0.03),
    (0.04, 0.12, 0.45),
    (0.75, 0.45, 0.02),
    (0.12, 0.22, 0.05),
)


@dataclass(frozen=True, slots=True)
class Photometric:
    """Image-level augmentations applied after rendering (datasets only)."""

    gamma: float
    saturation: float
    blur_sigma_px: float
    jpeg_quality: int
    #: Downscale factor before scaling back (soft, video-like detail), 1 = none.
    resample: float


@dataclass(frozen=True, slots=True)
class DistractorTrack:
    """A non-leader flying thing (bird, balloon, plane, debris) moving at constant velocity."""

    kind: str
    mesh_size_m: float
    p0_ned_m: Vec3
    v_ned_m_s: Vec3
    yaw_rad: float
    rgb: RGB
    flap_hz: float


@dataclass(frozen=True, slots=True)
class SequenceSpec:
    """Everything needed to render one sequence, deterministic from the dataset seed and its index."""

    index: int
    split: str
    visual: VisualConfig
    cameras: list[CameraPose]
    #: Camera angular rate per frame (camera frame, rad/s): motion blur.
    omegas_cam_rad_s: list[Vec3]
    #: Leader (R_ned_body, p_ned_m) per frame, or None for a leader-free sequence.
    leaders: list[tuple[Mat3, Vec3]] | None
    distractors: list[DistractorTrack] = field(default_factory=list)
    photometric: list[Photometric] = field(default_factory=list)
    times_s: list[float] = field(default_factory=list)


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(math.exp(rng.uniform(math.log(lo), math.log(hi))))


def _colour(rng: np.random.Generator) -> RGB:
    base = _BODY_COLOURS[int(rng.integers(len(_BODY_COLOURS)))]
    k = float(rng.uniform(0.8, 1.2))
    return (min(base[0] * k, 0.9), min(base[1] * k, 0.9), min(base[2] * k, 0.9))


def sample_leader_look(rng: np.random.Generator) -> LeaderLook:
    """An airframe with its usual size +-25 % and, half the time, its own colours."""
    airframe = str(rng.choice(_AIRFRAMES, p=_AIRFRAME_P))
    span = AIRFRAME_SPAN_M[airframe] * float(rng.uniform(0.8, 1.25))
    if rng.random() < 0.5:
        return LeaderLook(airframe=airframe, span_m=span, rotor_rpm=float(rng.uniform(3000, 9000)))
    return LeaderLook(
        airframe=airframe,
        span_m=span,
        body_rgb=_colour(rng),
        arm_rgb=_colour(rng),
        accent_rgb=_colour(rng),
        prop_rgb=(0.02, 0.02, 0.02) if rng.random() < 0.6 else _colour(rng),
        rotor_rpm=float(rng.uniform(3000, 9000)),
    )


def sample_visual(rng: np.random.Generator) -> VisualConfig:
    """Light, weather, ground, structures and camera rendition of one sequence."""
    dusk = rng.random() < 0.2
    r = rng.random()
    cover = (
        rng.uniform(0.0, 0.15) if r < 0.3 else (rng.uniform(0.2, 0.7) if r < 0.7 else rng.uniform(0.8, 1.0))
    )
    f = rng.random()
    fog = (
        rng.uniform(0.0, 0.001)
        if f < 0.7
        else (rng.uniform(0.001, 0.005) if f < 0.95 else rng.uniform(0.005, 0.02))
    )
    mats = ["grass", "field", "dirt", "asphalt", "gravel", "snow"]
    p_mat = np.array([0.36, 0.3, 0.2, 0.04, 0.07, 0.03])
    chosen = tuple(str(m) for m in rng.choice(mats, size=int(rng.integers(2, 5)), replace=False, p=p_mat))
    clear = float(rng.uniform(20, 80))
    return VisualConfig(
        seed=int(rng.integers(0, 2**31 - 1)),
        time_of_day="dusk" if dusk else "day",
        sun_elevation_deg=float(rng.uniform(-2, 8) if dusk else rng.uniform(15, 75)),
        sun_azimuth_deg=float(rng.uniform(0, 360)),
        cloud_cover=float(cover),
        fog_density_per_m=float(fog),
        ground_materials=chosen,
        road=bool(rng.random() < 0.5),
        structures=int(rng.integers(10, 80)),
        clear_radius_m=clear,
        world_radius_m=float(rng.uniform(max(200.0, clear + 50.0), 450.0)),
        tree_line=bool(rng.random() < 0.85),
        hills=bool(rng.random() < 0.6),
        exposure_ev=float(np.clip(rng.normal(0.3, 0.5), -1.2, 1.5)),
        white_balance_k=float(rng.uniform(4800, 6500)),
        sensor_noise=_log_uniform(rng, 0.3, 1.5),
        vignetting=float(rng.uniform(0.0, 0.5)),
        contrast=float(rng.uniform(0.8, 1.25)),
        leader=sample_leader_look(rng),
    )


def _camera_rotation(rng: np.random.Generator, profile: str = "wide") -> Mat3:
    """A camera orientation biased to look up or level (sky backgrounds), sometimes down.

    For the ``formation`` profile, a follower's: mount tilt plus flight attitude, within 15 deg of level.
    """
    r = rng.random()
    if profile == "formation":
        pitch = float(np.clip(rng.normal(2.0, 6.0), -15.0, 15.0))
    else:
        pitch = rng.uniform(5, 40) if r < 0.45 else (rng.uniform(-8, 8) if r < 0.8 else rng.uniform(-40, -8))
    R_ned_body = R_from_euler(
        math.radians(float(np.clip(rng.normal(0, 5), -15, 15))),
        math.radians(pitch),
        rng.uniform(0, 2 * math.pi),
    )
    return R_ned_body @ R_BODY_CAM_LEVEL


def sample_photometric(rng: np.random.Generator) -> Photometric:
    """Gamma, saturation, defocus, JPEG and resampling of one frame."""
    return Photometric(
        gamma=float(rng.uniform(0.8, 1.25)),
        saturation=float(rng.uniform(0.6, 1.3)),
        blur_sigma_px=float(rng.uniform(0.3, 1.4)) if rng.random() < 0.3 else 0.0,
        jpeg_quality=int(rng.integers(35, 96)),
        resample=float(rng.uniform(0.5, 0.85)) if rng.random() < 0.2 else 1.0,
    )


def _sample_distractors(rng: np.random.Generator, cam: CameraPose, intr: Intrinsics) -> list[DistractorTrack]:
    """Birds most often; sometimes balloons, a distant aeroplane or wind-blown debris near the lens."""
    out: list[DistractorTrack] = []
    K_inv = np.linalg.inv(intr.K)

    def in_view(r_m: float) -> Vec3:
        u = rng.uniform(-0.1, 1.1) * intr.width_px
        v = rng.uniform(-0.1, 1.1) * intr.height_px
        d = K_inv @ np.array([u, v, 1.0])
        p: Vec3 = cam.p_ned_cam_m + cam.R_ned_cam @ (r_m * d / np.linalg.norm(d))
        p[2] = min(p[2], -0.5)
        return p

    if rng.random() < 0.4:
        for _ in range(int(rng.integers(1, 6))):
            dark = rng.random() < 0.75
            tone = rng.uniform(0.02, 0.1) if dark else rng.uniform(0.5, 0.8)
            speed = rng.uniform(3, 12)
            heading = rng.uniform(0, 2 * math.pi)
            out.append(
                DistractorTrack(
                    "bird",
                    float(rng.uniform(0.2, 1.3)),
                    in_view(_log_uniform(rng, 2.0, 80.0)),
                    np.array([speed * math.cos(heading), speed * math.sin(heading), rng.normal(0, 1)]),
                    heading,
                    (tone, tone * 0.95, tone * 0.9),
                    float(rng.uniform(2, 8)),
                )
            )
    if rng.random() < 0.1:
        out.append(
            DistractorTrack(
                "balloon",
                float(rng.uniform(0.12, 0.4)),
                in_view(rng.uniform(3.0, 40.0)),
                np.array([rng.normal(0, 1), rng.normal(0, 1), -rng.uniform(0, 1)]),
                0.0,
                _colour(rng),
                0.0,
            )
        )
    if rng.random() < 0.1:
        speed = rng.uniform(40, 80)
        heading = rng.uniform(0, 2 * math.pi)
        out.append(
            DistractorTrack(
                "plane",
                float(rng.uniform(10, 30)),
                in_view(rng.uniform(300.0, 2000.0)),
                np.array([speed * math.cos(heading), speed * math.sin(heading), 0.0]),
                heading,
                (0.7, 0.7, 0.72),
                0.0,
            )
        )
    if rng.random() < 0.1:
        for _ in range(int(rng.integers(1, 4))):
            out.append(
                DistractorTrack(
                    "debris",
                    float(rng.uniform(0.03, 0.1)),
                    in_view(rng.uniform(0.5, 3.0)),
                    rng.normal(0, 1.5, 3),
                    float(rng.uniform(0, 6.3)),
                    (0.1 + 0.3 * rng.random(), 0.08 + 0.2 * rng.random(), 0.03),
                    float(rng.uniform(1, 5)),
                )
            )
    return out


def distractor_frame_vertices(tracks: list[DistractorTrack], t_s: float) -> F32 | None:
    """Vertices (NED) of all distractors at time t (wings flapping, debris tumbling)."""
    if not tracks:
        return None
    items: list[tuple[Mesh, Mat3, Vec3, RGB, Kind]] = []
    for tr in tracks:
        p = tr.p0_ned_m + tr.v_ned_m_s * t_s
        R = R_from_euler(0.0, 0.0, tr.yaw_rad)
        if tr.kind == "bird":
            mesh = bird_mesh(tr.mesh_size_m, 0.7 * math.sin(2 * math.pi * tr.flap_hz * t_s + tr.yaw_rad))
        elif tr.kind == "balloon":
            mesh = balloon_mesh(tr.mesh_size_m)
        elif tr.kind == "plane":
            mesh = plane_mesh(tr.mesh_size_m)
        else:
            mesh = debris_mesh(tr.mesh_size_m)
            R = R_from_euler(tr.flap_hz * t_s, 0.7 * tr.flap_hz * t_s, tr.yaw_rad)
        items.append((mesh, R, p, tr.rgb, Kind.PLAIN if tr.kind != "balloon" else Kind.GLOSSY))
    return distractor_vertices(items)


def _occluder_between(
    rng: np.random.Generator, p_cam: Vec3, p_leader: Vec3, leader_radius_m: float
) -> OccluderSpec:
    """A tree, pole, wall or building corner whose edge crosses the leader's image: partial occlusion.

    The occluder stands part-way along the line of sight with its edge within the leader's apparent
    size of that line (a pole, thinner than most airframes, right across it).
    """
    frac = rng.uniform(0.3, 0.8)
    p = p_cam + frac * (p_leader - p_cam)
    alt = -float(p[2])
    r_app = leader_radius_m * frac  # the leader's half-size seen at the occluder's distance
    edge = rng.uniform(-0.8, 0.8) * r_app
    kind = str(rng.choice(["tree", "conifer", "pole", "wall", "building"], p=[0.3, 0.15, 0.25, 0.15, 0.15]))
    sgn = float(rng.choice([-1.0, 1.0]))
    if kind in ("tree", "conifer"):
        width = rng.uniform(2.0, 6.0)
        off = sgn * (edge + 0.45 * width)  # crown edge (slightly fuzzy) near the line of sight
        size = (width, 0.0, max(alt + 0.5 * width * rng.uniform(0.3, 1.0), 2.0))
    elif kind == "pole":
        off = rng.uniform(-1.0, 1.0) * r_app
        size = (rng.uniform(0.05, 0.2), 1.8, alt + rng.uniform(0.5, 4.0))
    else:
        w = rng.uniform(3.0, 12.0)
        off = sgn * (edge + 0.5 * w)
        size = (w, rng.uniform(0.3, 6.0), alt + rng.uniform(0.3, 3.0))
    return _across_los(kind, p, p_leader - p_cam, off, size)


def _across_los(
    kind: str, p_ned_m: Vec3, los: Vec3, off_m: float, size_m: tuple[float, float, float]
) -> OccluderSpec:
    """A structure on the ground below ``p_ned_m``, ``off_m`` sideways of the line of sight, facing it.

    ``los`` is the line of sight (NED, m); the structure's face is across it.
    """
    side = np.cross(los, np.array([0.0, 0.0, 1.0]))
    side /= max(float(np.linalg.norm(side)), 1e-9)
    base = p_ned_m + side * off_m
    yaw = math.degrees(math.atan2(side[1], side[0]))
    return OccluderSpec(kind=kind, p_ned_m=(float(base[0]), float(base[1]), 0.0), size_m=size_m, yaw_deg=yaw)


def _backdrop_behind(rng: np.random.Generator, p_cam: Vec3, p_leader: Vec3) -> OccluderSpec:
    """A tree, conifer, building or wall standing behind the leader, its face across the line of sight.

    The leader is then seen against foliage or a facade rather than the sky: the case where a detector
    trained mostly on open backgrounds loses it (a leader hovering in front of a tree).
    """
    los = p_leader - p_cam
    dist = float(np.linalg.norm(los))
    behind_m = _log_uniform(rng, 1.5, 25.0)
    p = p_leader + los * (behind_m / max(dist, 1e-9))
    alt = max(-float(p[2]), 0.5)
    kind = str(rng.choice(["tree", "conifer", "building", "wall"], p=[0.4, 0.2, 0.25, 0.15]))
    if kind in ("tree", "conifer"):
        width = rng.uniform(3.0, 8.0)
        off = rng.uniform(-0.3, 0.3) * width
        size = (width, 0.0, max(alt + 0.5 * width * rng.uniform(0.2, 1.0), 2.0))
    else:
        width = rng.uniform(6.0, 20.0)
        off = rng.uniform(-0.3, 0.3) * width
        size = (width, rng.uniform(0.3, 8.0), alt + rng.uniform(0.5, 6.0))
    return _across_los(kind, p, los, off, size)


def sample_sequence(
    seed: int, index: int, n_frames: int, intr: Intrinsics, profile: str = "wide"
) -> SequenceSpec:
    """Sequence ``index`` of a dataset with ``seed``: the same whatever the dataset's size.

    ``profile`` is one of :data:`PROFILES`; both draw light, weather, world, distractors and occluders
    the same way.
    """
    if profile not in PROFILES:
        raise ValueError(f"unknown dataset profile {profile!r} (one of {', '.join(PROFILES)})")
    # clutter and near: the formation view with a structure behind the leader in most sequences.
    formation = profile in ("formation", "clutter", "near")
    rng = np.random.default_rng([seed, index])
    split = split_of(seed, index)
    visual = sample_visual(rng)
    if formation and rng.random() < 0.5:
        visual = visual.model_copy(update={"leader": LeaderLook(rotor_rpm=float(rng.uniform(3000, 9000)))})
    a = rng.random()
    if formation:
        alt = rng.uniform(2.0, 8.0) if a < 0.6 else rng.uniform(8.0, 30.0)
    else:
        alt = rng.uniform(1.2, 2.5) if a < 0.25 else (rng.uniform(3, 30) if a < 0.75 else rng.uniform(30, 80))
    p_cam0 = np.array([rng.uniform(-10, 10), rng.uniform(-10, 10), -alt])
    R0 = _camera_rotation(rng, profile)
    # The view drifts slowly across the sequence (so the leader stays in it); motion blur comes from a
    # separate, sometimes fast, turn rate during each exposure (a shaking or turning follower).
    drift = rng.normal(0.0, math.radians(4.0), 3)
    fast = rng.random() < 0.3
    v_cam = rng.normal(0.0, 0.8, 3) * np.array([1.0, 1.0, 0.3])
    times = [i * FRAME_DT_S for i in range(n_frames)]
    cameras = []
    for t in times:
        p = p_cam0 + v_cam * t
        p[2] = min(p[2], -1.0)
        cameras.append(CameraPose(R0 @ rotation_vector_matrix(drift * t), p))
    omegas = [rng.normal(0.0, math.radians(60.0 if fast else 8.0), 3) for _ in times]

    leaders: list[tuple[Mat3, Vec3]] | None = None
    occluders: list[OccluderSpec] = []
    if rng.random() < 0.86:
        K_inv = np.linalg.inv(intr.K)
        p_leader0 = np.zeros(3)
        # 1-20 m, but never so far that the airframe spans fewer than ~8 px (a micro quad: 7 m).
        far_m = min(20.0, max(3.0, intr.fx_px * visual.leader.resolved_span_m / 8.0))
        near_m = 1.0
        if profile == "near":  # a formation slot's range; a small airframe only as far as it shows
            near_m, far_m = NEAR_RANGE_M[0], max(NEAR_RANGE_M[0] + 1.0, min(far_m, NEAR_RANGE_M[1]))
        elif formation:  # a follower flies 2-15 m behind; it keeps the leader near the image centre
            near_m, far_m = 2.0, min(far_m, 15.0)
        for _ in range(20):
            rng_m = _log_uniform(rng, near_m, far_m) if rng.random() < 0.5 else rng.uniform(near_m, far_m)
            edge = rng.random() < (0.05 if formation else 0.12)
            lo, hi = (-0.15, 1.15) if edge else ((0.2, 0.8) if formation else (0.02, 0.98))
            u, v = rng.uniform(lo, hi) * intr.width_px, rng.uniform(lo, hi) * intr.height_px
            d = K_inv @ np.array([u, v, 1.0])
            p_leader0 = cameras[0].p_ned_cam_m + cameras[0].R_ned_cam @ (rng_m * d / np.linalg.norm(d))
            if p_leader0[2] < -0.4:
                break
        else:
            p_leader0[2] = -0.4
        v_leader = rng.normal(0.0, 1.2, 3) * np.array([1.0, 1.0, 0.3])
        yaw0 = rng.uniform(0, 2 * math.pi)
        yaw_rate = rng.normal(0.0, 0.4)
        tilt = np.clip(rng.normal(0.0, math.radians(12.0), 2), -0.6, 0.6)
        leaders = []
        for t, cam in zip(times, cameras, strict=True):
            p = p_leader0 + v_leader * t
            p[2] = min(p[2], -0.4)
            # Both move during the sequence: keep the range within 1-20 m (near: its band) in every frame.
            rel = p - cam.p_ned_cam_m
            dist = float(np.linalg.norm(rel))
            closest_m = near_m if profile == "near" else 1.0
            p = cam.p_ned_cam_m + rel * (min(max(dist, closest_m), far_m) / max(dist, 1e-9))
            p[2] = min(p[2], -0.4)
            leaders.append((R_from_euler(float(tilt[0]), float(tilt[1]), yaw0 + yaw_rate * t), p))
        if rng.random() < 0.15:
            radius = 0.5 * visual.leader.resolved_span_m + 0.1
            occluders.append(_occluder_between(rng, cameras[0].p_ned_cam_m, p_leader0, radius))
        if profile in ("clutter", "near") and rng.random() < (0.75 if profile == "clutter" else 0.6):
            occluders.append(_backdrop_behind(rng, cameras[0].p_ned_cam_m, p_leader0))
    if occluders:
        visual = visual.model_copy(update={"occluders": tuple(occluders)})
    return SequenceSpec(
        index=index,
        split=split,
        visual=visual,
        cameras=cameras,
        omegas_cam_rad_s=omegas,
        leaders=leaders,
        distractors=_sample_distractors(rng, cameras[0], intr),
        photometric=[sample_photometric(rng) for _ in times],
        times_s=times,
    )
