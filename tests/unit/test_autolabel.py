"""Auto-labels from the leader's expected position and the depth image (pure logic, synthetic depth)."""

from __future__ import annotations

import csv
import time
from pathlib import Path

import numpy as np
import pytest

from companion.kernel.camera import Intrinsics, RgbdFrame
from companion.lab.evaluation.autolabel_check import LeaderShare
from companion.lab.evaluation.scoring import iou
from companion.perception.autolabel import AutoLabel, AutoLabelConfig, Verdict, auto_label
from companion.perception.autolabel_writer import AutoLabelWriter
from companion.perception.detector.dataset import find_samples, read_labels

INTR = Intrinsics(460.0, 460.0, 319.5, 239.5, 640, 480)
CFG = AutoLabelConfig(leader_span_m=0.45, side_pad_fraction=0.0)


def _project(p_cam: tuple[float, float, float]) -> tuple[float, float]:
    x, y, z = p_cam
    return INTR.fx_px * x / z + INTR.cx_px, INTR.fy_px * y / z + INTR.cy_px


def _scene(
    p_cam: tuple[float, float, float], size_m: tuple[float, float] = (0.45, 0.15)
) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """Sky (no depth) with one box-shaped leader at ``p_cam``; returns the depth and its pixel box."""
    depth = np.zeros((480, 640), np.float32)
    u, v = _project(p_cam)
    hw = INTR.fx_px * size_m[0] / 2 / p_cam[2]
    hh = INTR.fy_px * size_m[1] / 2 / p_cam[2]
    box = (round(u - hw), round(v - hh), round(u + hw), round(v + hh))
    depth[box[1] : box[3], box[0] : box[2]] = p_cam[2]
    return depth, box


def test_a_leader_where_expected_is_labelled_with_its_depth_box() -> None:
    depth, box = _scene((0.3, 0.2, 6.0))
    label = auto_label(depth, INTR, np.array([0.3, 0.2, 6.0]), CFG)
    assert label.verdict is Verdict.LABEL
    assert label.box_xyxy_px == tuple(float(v) for v in box)
    assert label.quality > 0.9


def test_the_guess_may_be_off_by_the_gps_errors() -> None:
    # The depth blob is 0.6 m to the side of where the shared position puts it: the box is the blob's.
    depth, box = _scene((0.9, 0.2, 6.0))
    label = auto_label(depth, INTR, np.array([0.3, 0.2, 6.0]), CFG)
    assert label.verdict is Verdict.LABEL
    assert iou(label.box_xyxy_px, box) == 1.0  # type: ignore[arg-type]
    assert 0.35 < label.quality < 0.6  # 1.2 sigma off: a middling score
    # 0.8 m off (1.6 sigma): too doubtful to keep.
    depth, _ = _scene((1.1, 0.2, 6.0))
    far = auto_label(depth, INTR, np.array([0.3, 0.2, 6.0]), CFG)
    assert (far.verdict, far.reason) == (Verdict.REJECTED, "low quality")


def test_propellers_widen_the_box() -> None:
    depth, box = _scene((0.0, 0.0, 5.0))
    cfg = AutoLabelConfig(leader_span_m=0.45, side_pad_fraction=0.2)
    label = auto_label(depth, INTR, np.array([0.0, 0.0, 5.0]), cfg)
    assert label.box_xyxy_px is not None
    pad = 460.0 * 0.2 * 0.45 / 5.0
    assert label.box_xyxy_px[0] == pytest.approx(box[0] - pad)
    assert label.box_xyxy_px[2] == pytest.approx(box[2] + pad)
    assert label.box_xyxy_px[1] == box[1]


def test_thin_parts_cut_off_by_depth_holes_join_the_body() -> None:
    depth, box = _scene((0.0, 0.0, 5.0))
    depth[box[3] + 4 : box[3] + 7, box[0] + 3] = 5.0  # a landing leg below a gap of invalid depth
    label = auto_label(depth, INTR, np.array([0.0, 0.0, 5.0]), CFG)
    assert label.box_xyxy_px is not None
    assert label.box_xyxy_px[3] == box[3] + 7


def test_outside_the_field_of_view_is_a_negative_and_behind_too() -> None:
    depth = np.zeros((480, 640), np.float32)
    assert auto_label(depth, INTR, np.array([20.0, 0.0, 6.0]), CFG).verdict is Verdict.NEGATIVE
    assert auto_label(depth, INTR, np.array([0.0, 0.0, -3.0]), CFG).verdict is Verdict.NEGATIVE


@pytest.mark.parametrize(
    ("case", "reason"),
    [
        ("nothing", "no depth at the expected range"),
        ("wall", "the blob runs into the background"),
        ("two", "two objects at the expected range"),
        ("edge", "leader at the image edge"),
    ],
)
def test_doubtful_frames_are_rejected(case: str, reason: str) -> None:
    p = np.array([0.0, 0.0, 6.0])
    depth = np.zeros((480, 640), np.float32)
    if case == "wall":  # a building at the leader's range fills the search window
        depth[:, :] = 6.2
    elif case == "two":  # two drones side by side at the same range
        depth, _ = _scene((-0.5, 0.0, 6.0))
        depth2, _ = _scene((0.5, 0.0, 6.0))
        depth = np.maximum(depth, depth2)
    elif case == "edge":
        p = np.array([4.3, 0.0, 6.0])  # the projection falls just outside the image's right edge
    label = auto_label(depth, INTR, p, CFG)
    assert label.verdict is Verdict.REJECTED
    assert label.reason == reason


def test_a_leader_at_another_range_is_not_labelled() -> None:
    depth, _ = _scene((0.0, 0.0, 12.0))  # something at 12 m where the leader should be at 6 m
    assert auto_label(depth, INTR, np.array([0.0, 0.0, 6.0]), CFG).verdict is Verdict.REJECTED


def test_the_share_arrives_late_and_is_extrapolated_to_the_frame() -> None:
    from companion.service.autolabel_tap import SharedLeaderTrack

    share = LeaderShare(rate_hz=10.0, latency_s=0.1)
    track = SharedLeaderTrack(max_age_s=0.5)

    def at(t_s: float, stamp_s: float) -> np.ndarray | None:
        for position in share.arrived(t_s):
            track.add(position)
        return track.at(stamp_s)

    share.sample(1.0, (10.0, 0.0, -5.0), valid=True)
    assert at(1.05, 1.05) is None  # not arrived yet
    share.sample(1.05, (99.0, 0.0, 0.0), valid=True)  # before the next sample time: ignored
    share.sample(1.1, (10.2, 0.0, -5.0), valid=True)  # 2 m/s north
    p = at(1.2, 1.25)
    assert p is not None
    assert p[0] == pytest.approx(10.5)
    assert at(3.0, 3.0) is None  # stale


def _frame(seq: int) -> RgbdFrame:
    rgb = np.full((480, 640, 3), 120, np.uint8)
    return RgbdFrame(rgb, np.zeros((480, 640), np.float32), INTR, stamp_s=seq / 30.0, seq=seq)


def test_the_writer_writes_a_dataset_the_trainer_reads(tmp_path: Path) -> None:
    label = AutoLabel(Verdict.LABEL, "", (100.0, 120.0, 140.0, 140.0), 0.9, None, 6.0)
    negative = AutoLabel(Verdict.NEGATIVE, "leader outside the field of view")
    rejected = AutoLabel(Verdict.REJECTED, "no depth at the expected range")
    with AutoLabelWriter(tmp_path / "ds", sequence="flight1", negative_every=2) as w:
        w.offer(_frame(1), label)
        for seq in (2, 3, 4):
            w.offer(_frame(seq), negative)
        w.offer(_frame(5), rejected)
    assert w.counts.labels == 1
    assert w.counts.negatives == 2  # one in two negatives kept
    assert w.counts.rejected == 1
    assert w.counts.reasons == {"no depth at the expected range": 1}
    samples = find_samples(tmp_path / "ds")
    assert [s.key for s in samples] == ["flight1_f000001", "flight1_f000002", "flight1_f000004"]
    assert {s.group for s in samples} == {"flight1"}
    boxes = read_labels(samples[0], 640, 480)
    assert np.allclose(boxes, [[100.0, 120.0, 140.0, 140.0]], atol=1e-3)
    assert read_labels(samples[1], 640, 480).shape == (0, 4)
    with (tmp_path / "ds" / "manifest.csv").open() as f:
        rows = list(csv.DictReader(f))
    assert [r["verdict"] for r in rows] == ["label", "negative", "negative"]


def test_the_writer_never_blocks_and_stops_at_its_disk_budget(tmp_path: Path) -> None:
    label = AutoLabel(Verdict.LABEL, "", (100.0, 120.0, 140.0, 140.0), 0.9, None, 6.0)
    with AutoLabelWriter(tmp_path / "ds", max_bytes=1, queue_frames=2) as w:
        t0 = time.perf_counter()
        for seq in range(200):
            w.offer(_frame(seq), label)
        offered_s = time.perf_counter() - t0
    c = w.counts
    assert c.labels == 1  # the first frame passes the budget, nothing after it
    assert c.labels + c.over_budget + c.dropped == 200
    assert offered_s < 5.0  # 200 offers of 640x480 frames; a blocking writer would encode them all first


def test_the_writer_refuses_a_folder_with_data(tmp_path: Path) -> None:
    (tmp_path / "ds").mkdir()
    (tmp_path / "ds" / "keep.txt").write_text("x")
    with pytest.raises(FileExistsError, match="not empty"), AutoLabelWriter(tmp_path / "ds"):
        pass


def test_the_service_tap_labels_only_with_gps_and_a_fresh_share(tmp_path: Path) -> None:
    from companion.config import Config
    from companion.kernel.flight import VehicleState
    from companion.mission.types import SharedLeaderPosition
    from companion.perception.transform import AttitudeHistory, CameraGeometry
    from companion.service.autolabel_tap import AutoLabelTap

    cfg = Config.model_validate({"autolabel": {"enabled": True, "out_dir": str(tmp_path)}})
    geometry = CameraGeometry(np.array([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]]), np.zeros(3))  # cam z = body x
    attitude = AttitudeHistory()
    attitude.push(0.0, (1.0, 0.0, 0.0, 0.0))  # level, facing north
    attitude.push(10.0, (1.0, 0.0, 0.0, 0.0))
    depth, box = _scene((0.0, 0.0, 6.0))  # the leader 6 m north of the follower, at its height
    frame = RgbdFrame(np.zeros((480, 640, 3), np.uint8), depth, INTR, stamp_s=2.0, seq=7)
    good = VehicleState(global_position_ok=True, p_ned_m=(0.0, 0.0, -5.0), local_position_stamp_s=2.0)
    with AutoLabelTap(cfg, geometry, now_wall_s=0.0) as tap:
        tap.on_frame(frame, good, attitude)  # no share yet
        tap.share(SharedLeaderPosition(1.7, (5.4, 0.0, -5.0)))
        tap.share(SharedLeaderPosition(1.8, (5.6, 0.0, -5.0)))  # 2 m/s north: at 2.0 s it is at 6.0 m
        tap.on_frame(frame, VehicleState(global_position_ok=False), attitude)  # GPS not good
        tap.on_frame(frame, good, attitude)
        late = RgbdFrame(frame.rgb, depth, INTR, stamp_s=2.4, seq=8)
        tap.on_frame(late, good, attitude)  # the share is 0.6 s old: too old
    assert tap.gated_out == 3
    assert tap.counts.labels == 1
    out = next(tmp_path.iterdir())
    label = (out / "labels" / f"{out.name}_f000007.txt").read_text().split()
    cx = float(label[1]) * 640
    assert cx == pytest.approx((box[0] + box[2]) / 2, abs=0.5)


async def test_a_folder_it_may_not_write_turns_labels_off_not_the_flight(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from companion.config import Config
    from companion.kernel.clock import ManualClock
    from companion.service.flight import FlightService

    blocker = tmp_path / "file"
    blocker.write_text("not a folder")  # the labels' folder would have to be inside a file
    cfg = Config.model_validate({"autolabel": {"enabled": True, "out_dir": str(blocker / "labels")}})

    class _Stage:
        def after_track(self, _track: object) -> None:
            pass

    core = FlightService(cfg, object(), ManualClock(0.0), _Stage())  # type: ignore[arg-type]
    ran: list[bool] = []

    async def mission() -> None:
        ran.append(True)

    core.runner.run = mission  # type: ignore[method-assign]
    await core.run()
    assert ran == [True]
    assert core.autolabel is None
    assert "auto-labels off" in caplog.text
