from __future__ import annotations

import asyncio
import itertools
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from companion.config import CameraConfig
from companion.kernel.camera import Intrinsics, RgbdFrame
from companion.kernel.errors import CameraError
from companion.perception.record import FolderRecorder, RecordError
from companion.perception.sources import open_source, parse_source
from companion.perception.sources.bag import BagSource
from companion.perception.sources.bag_format import align_depth_to_color
from companion.perception.sources.bag_writer import write_realsense_bag
from companion.perception.sources.file import FolderSource, depth_to_u16
from companion.perception.sources.realsense import RealSenseSource
from tests.synthetic import D435_COLOR, frame_from_view, render

N_FRAMES = 6


def synthetic_frames(n: int = N_FRAMES, t0_s: float = 100.0) -> list[RgbdFrame]:
    rng = np.random.default_rng(7)
    frames = []
    for k in range(n):
        view = render((0.3 + 0.05 * k, -0.2, 5.0 + 0.1 * k), rng=rng, hole_fraction=0.02)
        frames.append(frame_from_view(view, t0_s + k / 30.0 + 1e-7 * k, seq=10 + k))
    return frames


async def read_all(source: object) -> list[RgbdFrame]:
    out = []
    async with source as src:  # type: ignore[attr-defined]
        async for frame in src:
            out.append(frame)
    return out


def assert_same_frames(a: list[RgbdFrame], b: list[RgbdFrame], *, stamp_tol_s: float = 0.0) -> None:
    assert len(a) == len(b)
    for fa, fb in zip(a, b, strict=True):
        assert fa.seq == fb.seq
        assert abs(fa.stamp_s - fb.stamp_s) <= stamp_tol_s
        assert fa.intrinsics == fb.intrinsics
        assert np.array_equal(fa.rgb, fb.rgb)
        assert fa.depth_m.dtype == np.float32
        assert np.array_equal(depth_to_u16(fa.depth_m), depth_to_u16(fb.depth_m))


async def test_folder_round_trips_through_record_and_read(tmp_path: Path) -> None:
    frames = synthetic_frames()
    with FolderRecorder(tmp_path / "a") as rec:
        for f in frames:
            rec.write(f)
    back = await read_all(FolderSource(tmp_path / "a"))
    assert_same_frames(frames, back)
    for f, g in zip(frames, back, strict=True):
        assert f.stamp_s == g.stamp_s  # full float precision
        assert (
            np.max(np.abs(f.depth_m - g.depth_m)) <= 0.0005 + 1e-5
        )  # mm quantisation (plus float32 rounding at 25 m)
        assert f.truth is not None
        assert g.truth is not None
        assert g.truth.box_xyxy_px == f.truth.box_xyxy_px
        assert np.array_equal(g.truth.p_cam_leader_m, f.truth.p_cam_leader_m)
        assert np.array_equal(g.truth.q_ned_follower_wxyz, f.truth.q_ned_follower_wxyz)
    # A recording of a replay is the same recording, bit for bit.
    with FolderRecorder(tmp_path / "b") as rec:
        for g in back:
            rec.write(g)
    again = await read_all(FolderSource(tmp_path / "b"))
    for g, h in zip(back, again, strict=True):
        assert np.array_equal(g.depth_m, h.depth_m)
        assert np.array_equal(g.rgb, h.rgb)
        assert g.stamp_s == h.stamp_s


async def test_recorder_refuses_to_overwrite(tmp_path: Path) -> None:
    (tmp_path / "x").mkdir()
    (tmp_path / "x" / "keep.txt").write_text("data")
    with pytest.raises(RecordError, match="not an empty folder"), FolderRecorder(tmp_path / "x"):
        pass


async def test_realsense_bag_reads_back_frame_exact(tmp_path: Path) -> None:
    frames = synthetic_frames()
    path = tmp_path / "rec.bag"
    assert write_realsense_bag(path, frames) == N_FRAMES
    back = await read_all(BagSource(path))
    assert_same_frames(frames, back, stamp_tol_s=1e-9)


async def test_realsense_bag_is_what_the_sdk_plays(tmp_path: Path) -> None:
    # The SDK's own player (librealsense via pyrealsense2) reads the file as a device recording. The player
    # is set to non-real-time and paused before any sensor starts: a pipeline starts playing in real time,
    # and on a busy machine its first frame can be gone before `set_real_time(False)` lands.
    rs = pytest.importorskip("pyrealsense2")
    frames = synthetic_frames(4)
    path = tmp_path / "rec.bag"
    write_realsense_bag(path, frames)
    device = rs.context().load_device(str(path))
    playback = device.as_playback()
    playback.set_real_time(False)
    playback.pause()  # until every sensor listens: a sensor started late would miss the first frames
    queue = rs.frame_queue(64, keep_frames=True)
    sensors = device.query_sensors()
    got: dict[str, dict[int, tuple[np.ndarray, float]]] = {"color": {}, "depth": {}}
    for sensor in sensors:
        sensor.open(sensor.get_stream_profiles())
        sensor.start(queue)
    playback.resume()
    try:
        while len(got["color"]) + len(got["depth"]) < 2 * len(frames):
            ok, frame = queue.try_wait_for_frame(10_000)
            if not ok:
                break
            kind = "depth" if frame.get_profile().stream_type() == rs.stream.depth else "color"
            got[kind][frame.get_frame_number()] = (
                np.asanyarray(frame.get_data()).copy(),
                frame.get_timestamp(),
            )
    finally:
        for sensor in sensors:
            sensor.stop()
            sensor.close()
    assert sorted(got["color"]) == sorted(got["depth"]) == [f.seq for f in frames]
    for f in frames:
        rgb, stamp_ms = got["color"][f.seq]
        depth_u16, depth_stamp_ms = got["depth"][f.seq]
        assert np.array_equal(rgb, f.rgb)
        assert np.array_equal(depth_u16, depth_to_u16(f.depth_m))
        assert stamp_ms == pytest.approx(f.stamp_s * 1e3, abs=1e-3)
        assert depth_stamp_ms == pytest.approx(f.stamp_s * 1e3, abs=1e-3)


def test_align_depth_moves_a_near_object_by_the_parallax() -> None:
    depth_intr = Intrinsics(400.0, 400.0, 319.5, 239.5, 640, 480)
    color_intr = Intrinsics(600.0, 600.0, 320.0, 240.0, 640, 480)
    depth = np.full((480, 640), 6.0, np.float32)
    depth[230:250, 310:330] = 2.0  # a near square centred on the depth camera's axis
    t = np.array([-0.05, 0.0, 0.0])  # colour camera 5 cm to the right of the depth camera
    out = align_depth_to_color(depth, depth_intr, color_intr, np.eye(3), t)
    near = np.argwhere(np.abs(out - 2.0) < 1e-6)
    assert near.size > 0
    # In colour pixels the square sits f * dx / z = 600 * -0.05 / 2 = -15 px left of the centre.
    assert near[:, 1].mean() == pytest.approx(320.0 - 15.0, abs=1.0)
    assert near[:, 0].mean() == pytest.approx(240.0, abs=1.0)
    far = out[(out > 0) & (np.abs(out - 2.0) > 1e-6)]
    assert np.allclose(far, 6.0)


async def test_folder_source_loops_with_increasing_stamps_and_paces_in_real_time(tmp_path: Path) -> None:
    frames = synthetic_frames(3)
    with FolderRecorder(tmp_path / "a") as rec:
        for f in frames:
            rec.write(f)
    out = []
    t0 = time.monotonic()
    async with FolderSource(tmp_path / "a", loop=True, realtime=True) as src:
        async for frame in src:
            out.append(frame)
            if len(out) == 7:
                break
    elapsed = time.monotonic() - t0
    stamps = [f.stamp_s for f in out]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    assert len({f.seq for f in out}) == 7
    assert np.array_equal(out[3].rgb, out[0].rgb)  # the second lap replays the same images
    assert elapsed >= stamps[-1] - stamps[0] - 0.01  # paced by the stamps, not as fast as possible


async def test_missing_recordings_fail_with_one_line(tmp_path: Path) -> None:
    for source in (FolderSource(tmp_path / "nope"), BagSource(tmp_path / "nope.bag")):
        with pytest.raises(CameraError) as exc:
            await read_all(source)
        assert "\n" not in str(exc.value)
        assert "nope" in str(exc.value)
    (tmp_path / "junk.bag").write_bytes(b"not a bag at all")
    with pytest.raises(CameraError, match="not a readable ROS1 bag"):
        await read_all(BagSource(tmp_path / "junk.bag"))


async def test_live_realsense_without_library_is_one_clear_line(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)  # import fails as when it is not installed
    with pytest.raises(CameraError) as exc:
        await read_all(RealSenseSource(CameraConfig(source="realsense")))
    assert str(exc.value).startswith("realsense: pyrealsense2 is not installed")
    assert "\n" not in str(exc.value)


async def test_live_realsense_without_device_is_one_clear_line() -> None:
    rs = pytest.importorskip("pyrealsense2")
    if len(rs.context().query_devices()) > 0:
        pytest.skip("a RealSense is connected here")
    with pytest.raises(CameraError) as exc:
        await read_all(RealSenseSource(CameraConfig(source="realsense")))
    assert str(exc.value).startswith("realsense: no RealSense device found")


def test_source_spec_parsing_and_dispatch(tmp_path: Path) -> None:
    cam = parse_source(f"file:{tmp_path}/rec.bag", CameraConfig())
    assert cam.source == "file"
    assert isinstance(open_source(cam), BagSource)
    assert isinstance(open_source(parse_source(f"file:{tmp_path}", CameraConfig())), FolderSource)
    assert isinstance(open_source(parse_source("realsense", CameraConfig())), RealSenseSource)
    with pytest.raises(CameraError, match="expected sim, realsense or file:PATH"):
        parse_source("webcam", CameraConfig())


def test_d435_intrinsics_fixture_is_sane() -> None:
    assert D435_COLOR.width_px == 640


async def test_bag_source_loops_with_increasing_stamps(tmp_path: Path) -> None:
    frames = synthetic_frames(3)
    path = tmp_path / "rec.bag"
    write_realsense_bag(path, frames)
    out = []
    async with BagSource(path, loop=True) as src:
        async for frame in src:
            out.append(frame)
            if len(out) == 7:
                break
    stamps = [f.stamp_s for f in out]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    assert len({f.seq for f in out}) == 7
    assert np.array_equal(out[3].rgb, frames[0].rgb)


REPO = Path(__file__).resolve().parents[2]
SDK_DB3 = REPO / "tests" / "fixtures" / "realsense_sdk.db3"


def _expected_sdk_frames() -> tuple[list[np.ndarray], list[np.ndarray]]:
    sys.path.insert(0, str(REPO / "tests" / "fixtures"))
    try:
        import make_realsense_db3 as maker
    finally:
        sys.path.pop(0)
    colours = [maker.colour(i) for i in range(maker.FRAMES)]
    depths = [maker.depth_mm(i).astype(np.float32) / 1000.0 for i in range(maker.FRAMES)]
    return colours, depths


def _check_sdk_recording(frames: list[RgbdFrame]) -> None:
    colours, depths = _expected_sdk_frames()
    assert [f.seq for f in frames] == list(range(len(colours)))
    assert all(b.stamp_s > a.stamp_s for a, b in itertools.pairwise(frames))
    for f, rgb, depth_m in zip(frames, colours, depths, strict=True):
        assert np.array_equal(f.rgb, rgb)  # RGB order kept through the SDK's PNG
        assert np.allclose(f.depth_m, depth_m, atol=1e-6)
        assert f.intrinsics == Intrinsics(50.0, 50.0, 31.5, 23.5, 64, 48)


async def test_a_recording_made_by_the_realsense_sdk_replays() -> None:
    # tests/fixtures/realsense_sdk.db3 was written by pyrealsense2's own recorder (rosbag2, SDK 2.59).
    frames = await read_all(open_source(parse_source(f"file:{SDK_DB3}", CameraConfig())))
    _check_sdk_recording(frames)


async def test_the_sdk_recorder_today_writes_what_the_source_reads(tmp_path: Path) -> None:
    pytest.importorskip("pyrealsense2")
    out = tmp_path / "fresh.db3"
    r = await asyncio.to_thread(
        subprocess.run,
        [sys.executable, str(REPO / "tests" / "fixtures" / "make_realsense_db3.py"), str(out)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    _check_sdk_recording(await read_all(BagSource(out)))


async def test_a_corrupt_db3_is_one_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.db3"
    bad.write_bytes(b"not sqlite at all" * 100)
    with pytest.raises(CameraError) as exc:
        await read_all(BagSource(bad))
    assert str(exc.value).startswith(f"bag source: {bad} is not a readable rosbag2 file")
    assert "\n" not in str(exc.value)
