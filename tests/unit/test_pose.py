from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.config import LeaderConfig, PoseConfig
from companion.kernel.camera import Intrinsics
from companion.perception.box_depth import box_bounds, depth_sigma_m, robust_depth
from companion.perception.pose import LeaderMeasurement, back_project, bearing, measure_leader, project
from companion.perception.size_range import SizeCalibrator, SizePrior, range_from_size
from companion.perception.types import Detection
from tests.synthetic import D435_COLOR, render

LEADER = LeaderConfig(box_centre_below_m=0.0)  # the synthetic quad's silhouette is centred
POSE = PoseConfig(depth_max_m=20.0)  # the synthetic camera has no range cut-off unless asked


@given(st.floats(0.0, 639.0), st.floats(0.0, 479.0), st.floats(0.3, 30.0), st.floats(300.0, 900.0))
def test_pinhole_round_trip(u: float, v: float, z: float, f: float) -> None:
    intr = Intrinsics(f, f * 1.01, 320.5, 240.2, 640, 480)
    p = back_project(u, v, z, intr)
    assert p[2] == pytest.approx(z)
    u2, v2 = project(p, intr)
    assert u2 == pytest.approx(u, abs=1e-9)
    assert v2 == pytest.approx(v, abs=1e-9)


def test_bearing_signs() -> None:
    az, el = bearing(np.array([1.0, -1.0, 1.0]))
    assert az == pytest.approx(math.pi / 4)  # right is positive
    assert el == pytest.approx(math.atan2(1.0, math.sqrt(2.0)))  # up (negative y) is positive


def test_depth_noise_model_is_the_d435_figure() -> None:
    # sigma_z = z^2 * 0.08 / (f * 0.05): at f = 450 px, 6 m gives 0.128 m (field survey: ~0.14 m).
    assert depth_sigma_m(6.0, 450.0, POSE) == pytest.approx(36 * 0.08 / (450 * 0.05))


def test_box_bounds_clip_to_the_image() -> None:
    assert box_bounds((-5.2, 3.7, 700.0, 479.9), 640, 480) == (0, 3, 640, 480)


def test_background_between_the_arms_is_not_the_leader() -> None:
    view = render((0.0, 0.0, 6.0), yaw_rad=math.pi / 4, background_m=9.0)
    bx0, by0, bx1, by1 = view.box_xyxy_px
    pad_x, pad_y = 0.3 * (bx1 - bx0), 0.6 * (by1 - by0)  # a loose box, as detectors give
    x0, y0, x1, y1 = int(bx0 - pad_x), int(by0 - pad_y), int(bx1 + pad_x), int(by1 + pad_y)
    roi = view.depth_m[y0:y1, x0:x1]
    # Most of the box is wall: a plain median reads the background.
    assert np.median(roi) == pytest.approx(9.0)
    c = robust_depth(view.depth_m, (x0, y0, x1, y1), focal_px=D435_COLOR.fx_px, body_depth_m=0.45, cfg=POSE)
    assert c is not None
    assert abs(c.z_m - 6.0) < 0.1


def test_isolated_near_speckles_do_not_pull_the_depth() -> None:
    rng = np.random.default_rng(3)
    view = render((0.3, 0.1, 8.0), rng=rng)
    depth = view.depth_m.copy()
    x0, y0, x1, y1 = (int(c) for c in view.box_xyxy_px)
    ys = rng.integers(y0, y1, 4)
    xs = rng.integers(x0, x1, 4)
    depth[ys, xs] = 1.5  # flying pixels / spurious matches in front of the leader
    det = Detection(view.box_xyxy_px, 0.9)
    clean = measure_leader(view.depth_m, D435_COLOR, det, 0.0, leader=LEADER, cfg=POSE)
    dirty = measure_leader(depth, D435_COLOR, det, 0.0, leader=LEADER, cfg=POSE)
    assert clean is not None
    assert dirty is not None
    assert abs(dirty.p_cam_leader_m[2] - clean.p_cam_leader_m[2]) < 0.05


def test_no_valid_depth_gives_no_measurement() -> None:
    depth = np.zeros((480, 640), np.float32)
    assert (
        measure_leader(depth, D435_COLOR, Detection((100, 100, 150, 120), 0.9), 0.0, leader=LEADER, cfg=POSE)
        is None
    )


@pytest.mark.parametrize(("z_m", "tol_m"), [(3.0, 0.05), (6.0, 0.06), (9.0, 0.12), (12.0, 0.2)])
def test_single_frame_error_within_noise_budget(z_m: float, tol_m: float) -> None:
    # Noisy D435-like depth, holes, a truthful box: per-frame RMS error of the centre (before any filter).
    rng = np.random.default_rng(int(z_m))
    errs = []
    nees = []
    for _ in range(15):
        p = np.array([rng.uniform(-0.2, 0.2) * z_m, rng.uniform(-0.1, 0.1) * z_m, z_m])
        view = render(p, rng=rng, yaw_rad=rng.uniform(0, math.pi), hole_fraction=0.05)
        m = measure_leader(
            view.depth_m, D435_COLOR, Detection(view.box_xyxy_px, 0.9), 0.0, leader=LEADER, cfg=POSE
        )
        assert m is not None
        e = m.p_cam_leader_m - p
        errs.append(float(e @ e))
        nees.append(float(e @ np.linalg.solve(m.cov_cam_m2, e)))
        assert 1 / 2.5 < m.size_ratio < 2.5
    assert math.sqrt(np.mean(errs)) < tol_m
    # The covariance is honest: not wildly optimistic (NEES mean for 3 dof is 3 when exact).
    assert np.mean(nees) < 6.0


@settings(max_examples=30, deadline=None)
@given(
    st.floats(1.0, 15.0),
    st.floats(-0.4, 0.4),
    st.floats(-0.3, 0.3),
    st.floats(4.0, 200.0),
    st.floats(4.0, 120.0),
)
def test_measurement_covariance_is_symmetric_psd(z: float, ax: float, ay: float, w: float, h: float) -> None:
    depth = np.full((480, 640), z, np.float32)
    u = D435_COLOR.cx_px + ax * D435_COLOR.fx_px
    v = D435_COLOR.cy_px + ay * D435_COLOR.fy_px
    box = (u - w / 2, v - h / 2, u + w / 2, v + h / 2)
    m = measure_leader(depth, D435_COLOR, Detection(box, 0.5), 0.0, leader=LEADER, cfg=POSE)
    assert m is not None
    C = m.cov_cam_m2
    assert np.allclose(C, C.T)
    assert np.linalg.eigvalsh(C).min() > 0.0
    # Depth uncertainty grows with range, as stereo noise does.
    assert C[2, 2] >= POSE.surface_model_std_m**2


def test_size_ratio_flags_a_box_that_does_not_fit_its_depth() -> None:
    view = render((0.0, 0.0, 5.0))
    x0, y0, x1, y1 = view.box_xyxy_px
    good = measure_leader(
        view.depth_m, D435_COLOR, Detection(view.box_xyxy_px, 0.9), 0.0, leader=LEADER, cfg=POSE
    )
    cx, cy = (x0 + x1) / 2, (y0 + y1) / 2
    huge = measure_leader(
        view.depth_m,
        D435_COLOR,
        Detection((cx - 200, cy - 100, cx + 200, cy + 100), 0.9),
        0.0,
        leader=LEADER,
        cfg=POSE,
    )
    assert good is not None
    assert huge is not None
    assert 0.6 < good.size_ratio < 1.8
    assert huge.size_ratio > 2.5


def test_a_loose_box_on_a_leader_in_front_of_a_wall_is_ranged_where_its_size_says() -> None:
    """A thin quad fills under 10 % of a loose box in front of a wall: the nearest dense cluster is the wall.

    The box is then ~2.8x the size a leader would have at the wall's range, so it is searched again for a
    sparser cluster in front, near the range its size gives (leader-occluded seed 7 re-acquired a leader
    4.4 m away at the tree's 7.2 m and flew at it).
    """
    view = render((0.0, 0.0, 4.4), background_m=7.2, rng=np.random.default_rng(5))
    bx0, by0, bx1, by1 = view.box_xyxy_px
    w, h = bx1 - bx0, by1 - by0
    loose = Detection((bx0 - 0.15 * w, by0 - 2.5 * h, bx1 + 0.15 * w, by1 + 2.5 * h), 0.9)
    off = measure_leader(
        view.depth_m,
        D435_COLOR,
        loose,
        0.0,
        leader=LEADER,
        cfg=POSE.model_copy(update={"size_suspect_ratio": 0.0}),
    )
    on = measure_leader(view.depth_m, D435_COLOR, loose, 0.0, leader=LEADER, cfg=POSE)
    assert off is not None
    assert on is not None
    assert off.p_cam_leader_m[2] == pytest.approx(7.25, abs=0.1)
    assert off.size_ratio > 2.5
    assert on.p_cam_leader_m[2] == pytest.approx(4.4, abs=0.1)
    assert on.size_ratio < 2.0
    # A tight box on the same scene was right before and is untouched.
    tight = Detection(view.box_xyxy_px, 0.9)
    cfg_off = POSE.model_copy(update={"size_suspect_ratio": 0.0})
    m_on = measure_leader(view.depth_m, D435_COLOR, tight, 0.0, leader=LEADER, cfg=POSE)
    m_off = measure_leader(view.depth_m, D435_COLOR, tight, 0.0, leader=LEADER, cfg=cfg_off)
    assert m_on is not None
    assert m_off is not None
    assert np.array_equal(m_on.p_cam_leader_m, m_off.p_cam_leader_m)


def test_range_limit_truncation_is_undone() -> None:
    # At 9.7 m with a 10 m cut-off a third of the leader's noisy pixels are dropped (all of them far):
    # a plain mean of the rest reads ~0.2 m short; the truncated-normal correction removes that.
    rng = np.random.default_rng(11)
    cfg = PoseConfig(depth_max_m=10.0)
    errs, naive = [], []
    for _ in range(40):
        p = np.array([0.0, 0.0, 9.7])
        view = render(p, rng=rng, yaw_rad=rng.uniform(0, math.pi), depth_max_m=10.0, background_m=None)
        m = measure_leader(
            view.depth_m, D435_COLOR, Detection(view.box_xyxy_px, 0.9), 0.0, leader=LEADER, cfg=cfg
        )
        assert m is not None
        errs.append(m.p_cam_leader_m[2] - 9.7)
        vals = view.depth_m[view.leader_mask]
        naive.append(vals[vals > 0].mean() + LEADER.surface_to_centre_m - 9.7)
    assert np.mean(naive) < -0.12
    assert abs(np.mean(errs)) < 0.06


def test_size_fallback_ranges_beyond_the_stereo_range_after_learning_the_size() -> None:
    rng = np.random.default_rng(12)
    cfg = PoseConfig(depth_max_m=10.0)
    calib = SizeCalibrator(LEADER.span_m, max_depth_m=9.5)
    yaw = 0.4
    for k in range(40):  # the track receding from 6 to 9.5 m teaches the leader's apparent size
        p = np.array([0.3, 0.0, 6.0 + 3.5 * k / 40])
        view = render(p, rng=rng, yaw_rad=yaw + 0.01 * k)
        m = measure_leader(
            view.depth_m, D435_COLOR, Detection(view.box_xyxy_px, 0.9), 0.0, leader=LEADER, cfg=cfg
        )
        assert m is not None
        assert m.range_source == "depth"
        calib.update(m)
    prior = calib.prior()
    assert prior.height_rel_std < 0.2  # box size jitters a lot at 10-40 px; depth does far better
    view = render((0.5, 0.1, 11.5), rng=rng, yaw_rad=yaw + 0.4, depth_max_m=10.0)
    det = Detection(view.box_xyxy_px, 0.9)
    assert measure_leader(view.depth_m, D435_COLOR, det, 0.0, leader=LEADER, cfg=cfg) is None  # no depth
    m = measure_leader(view.depth_m, D435_COLOR, det, 0.0, leader=LEADER, cfg=cfg, size_prior=prior)
    assert m is not None
    assert m.range_source == "size"
    # Coarse (box size at ~20 px, thin props vanish with range) but honest about it: within 25 %, and
    # within 3 sigma of its own covariance, so the tracker weighs it accordingly.
    err_z = m.p_cam_leader_m[2] - 11.5
    assert abs(err_z) < 0.25 * 11.5
    assert abs(err_z) < 3.0 * math.sqrt(m.cov_cam_m2[2, 2])


def test_a_box_without_depth_is_not_size_ranged_where_the_leader_would_have_depth() -> None:
    """A box with no stereo return where the track puts the leader at 5 m is something beyond the
    cut-off (a tree seen past the leader): it is dropped, not size-ranged and pulled to the track."""
    rng = np.random.default_rng(3)
    cfg = PoseConfig(depth_max_m=10.0, size_fallback_min_frac=0.8)
    prior = SizePrior(0.55, 0.1, 1.0, 0.30, 0.05, 1.0)
    far = render((0.2, 0.0, 12.0), rng=rng, depth_max_m=10.0)  # no depth in its box
    det = Detection(far.box_xyxy_px, 0.9)
    kw = {"leader": LEADER, "size_prior": prior}
    on = measure_leader(far.depth_m, D435_COLOR, det, 0.0, cfg=cfg, z_hint_m=5.0, z_hint_std_m=0.2, **kw)
    assert on is None
    off = PoseConfig(depth_max_m=10.0, size_fallback_min_frac=0.0)
    m = measure_leader(far.depth_m, D435_COLOR, det, 0.0, cfg=off, z_hint_m=5.0, z_hint_std_m=0.2, **kw)
    assert m is not None
    assert m.range_source == "size"
    # Beyond the cut-off, where the track expects it, size ranging still works...
    m = measure_leader(far.depth_m, D435_COLOR, det, 0.0, cfg=cfg, z_hint_m=11.5, z_hint_std_m=0.5, **kw)
    assert m is not None
    assert m.range_source == "size"
    # ...and without a track the box's own size decides.
    m = measure_leader(far.depth_m, D435_COLOR, det, 0.0, cfg=cfg, **kw)
    assert m is not None
    assert m.p_cam_leader_m[2] > 8.0


def test_tracker_prediction_picks_the_leader_behind_a_nearer_occluder() -> None:
    # A branch 3 m nearer covers the left 60 % of the leader's box: the nearest dense cluster is the
    # branch; the tracker's predicted depth picks the leader's cluster instead.
    rng = np.random.default_rng(13)
    view = render((0.2, 0.0, 8.0), rng=rng, yaw_rad=0.5, background_m=20.0)
    depth = view.depth_m.copy()
    x0, y0, x1, y1 = (int(c) for c in view.box_xyxy_px)
    depth[y0:y1, x0 : x0 + int(0.6 * (x1 - x0))] = 5.0
    det = Detection(view.box_xyxy_px, 0.9)
    blind = measure_leader(depth, D435_COLOR, det, 0.0, leader=LEADER, cfg=POSE)
    hinted = measure_leader(
        depth, D435_COLOR, det, 0.0, leader=LEADER, cfg=POSE, z_hint_m=8.1, z_hint_std_m=0.3
    )
    assert blind is not None
    assert hinted is not None
    assert abs(blind.p_cam_leader_m[2] - 5.0) < 0.2
    assert abs(hinted.p_cam_leader_m[2] - 8.0) < 0.15
    # A hint that fits no cluster changes nothing.
    lost = measure_leader(
        depth, D435_COLOR, det, 0.0, leader=LEADER, cfg=POSE, z_hint_m=13.0, z_hint_std_m=0.3
    )
    assert lost is not None
    assert lost.p_cam_leader_m[2] == blind.p_cam_leader_m[2]


def _depth_meas(
    z_m: float, w_px: float, h_px: float, f_px: float = 465.6, box_scale: float = 1.0
) -> LeaderMeasurement:
    return LeaderMeasurement(
        stamp_s=0.0,
        p_cam_leader_m=np.array([0.0, 0.0, z_m]),
        cov_cam_m2=np.eye(3) * 1e-4,
        depth_surface_m=z_m,
        n_depth_px=50,
        size_ratio=1.0,
        azimuth_rad=0.0,
        elevation_rad=0.0,
        score=0.9,
        box_xyxy_px=(300.0, 200.0, 300.0 + w_px, 200.0 + h_px),
        truncated=False,
        width_m=w_px * z_m / f_px,
        height_m=h_px * z_m / f_px,
        box_scale=box_scale,
    )


def test_size_calibration_learns_near_the_cut_off_and_the_box_noise_in_px() -> None:
    # Close up the leader looks 10 % taller (thin parts still show); near the cut-off its box height
    # scatters by 1.5 px. The calibration takes the band's size and learns that scatter.
    rng = np.random.default_rng(3)
    f = 465.6
    calib = SizeCalibrator(0.45, min_depth_m=7.5, max_depth_m=9.5)
    for z in np.linspace(3.0, 7.4, 60):
        calib.update(_depth_meas(z, f * 0.6 / z, f * 0.33 / z))
    assert calib.prior().height_m == pytest.approx(0.33, rel=0.01)  # closer range stands in
    for z in np.linspace(7.5, 9.5, 200):
        calib.update(_depth_meas(z, f * 0.55 / z + rng.normal(0, 3.0), f * 0.30 / z + rng.normal(0, 1.5)))
    prior = calib.prior()
    assert prior.height_m == pytest.approx(0.30, rel=0.02)
    assert prior.height_noise_px == pytest.approx(1.5, rel=0.25)
    assert prior.width_noise_px == pytest.approx(3.0, rel=0.25)
    calib.update(_depth_meas(12.0, 10.0, 5.0))  # beyond the band: ignored
    assert calib.prior().height_m == pytest.approx(prior.height_m)


def test_size_calibration_is_per_box_scale() -> None:
    """Boxes found magnified (the window, 1.5x) are tighter than boxes found 1:1: each scale learns its own
    size, and a scale never seen keeps the configured prior rather than borrowing another's."""
    f = 465.6
    calib = SizeCalibrator(0.45, min_depth_m=7.5, max_depth_m=9.5)
    for z in np.linspace(7.5, 9.5, 100):
        calib.update(_depth_meas(z, f * 0.55 / z, f * 0.30 / z, box_scale=1.6))  # the window
        calib.update(_depth_meas(z, f * 0.60 / z, f * 0.36 / z, box_scale=1.0))  # the 1:1 search
    assert calib.prior(1.5).height_m == pytest.approx(0.30, rel=0.01)  # 1.5 and 1.6: one half-octave
    assert calib.prior(1.0).height_m == pytest.approx(0.36, rel=0.01)
    unseen = calib.prior(0.5)
    assert unseen.height_m == pytest.approx(0.65 * 0.45)  # the configured prior, loose
    assert unseen.height_rel_std == pytest.approx(0.25)


def test_range_from_size_averages_without_bias_under_box_noise() -> None:
    # 12 px high at 11.5 m with 2.9 px noise per frame (2 px per edge): the tracker averages the ranges
    # linearly, so their mean must be right; weights at the predicted range keep long and short alike.
    rng = np.random.default_rng(4)
    f, z_true = 465.6, 11.5
    prior = SizePrior(0.55, 1.0, 4.0, 0.30, 0.03, 2.9)
    h0, w0 = f * 0.30 / z_true, f * 0.55 / z_true
    zs, ws = [], []
    for _ in range(20000):
        ranged = range_from_size(w0 + rng.normal(0, 4.0), h0 + rng.normal(0, 2.9), f, prior, z_true * 1.05)
        if ranged is not None:
            zs.append(ranged[0])
            ws.append(1.0 / ranged[1])
    assert np.mean(zs) == pytest.approx(z_true, rel=0.01)
    assert np.average(zs, weights=ws) == pytest.approx(z_true, rel=0.01)
    # Per-frame relative error as stated (height noise over the expected height, plus the floor).
    assert math.sqrt(1.0 / np.mean(ws)) == pytest.approx(np.std(zs) / z_true, rel=0.2)
