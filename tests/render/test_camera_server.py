"""CameraServer + SimFrameSource end to end: a real Unix socket carrying real rendered frames."""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from companion.config import CameraConfig
from companion.kernel.errors import CameraError
from companion.kernel.frames import quat_from_euler
from companion.perception.sources.sim import SimFrameSource, open_sim_source
from sitl.render.camera_server import CameraServer
from sitl.render.config import VisualConfig
from sitl.render.geometry import VehiclePose

pytestmark = pytest.mark.render


class SimClock:
    """Sim time = wall time since start (speed 1)."""

    def __init__(self) -> None:
        self.t0 = time.monotonic()

    def __call__(self) -> float:
        return time.monotonic() - self.t0


def stub_truth(clock: SimClock) -> Callable[[], tuple[VehiclePose, VehiclePose]]:
    def truth() -> tuple[VehiclePose, VehiclePose]:
        t = clock()
        follower = VehiclePose(np.array([0.0, 0.0, -5.0]), quat_from_euler(0.0, 0.0, 0.0))
        leader = VehiclePose(np.array([6.0, 0.2 * t, -5.2]), quat_from_euler(0.0, 0.0, 0.5))
        return follower, leader

    return truth


async def test_frames_arrive_with_sim_stamps_and_truth(tmp_path: Path) -> None:
    clock = SimClock()
    sock = tmp_path / "cam.sock"
    visual = VisualConfig(structures=0, tree_line=False, seed=1)
    async with CameraServer(sock, stub_truth(clock), clock, rate_hz=10.0, visual=visual) as server:
        task = asyncio.create_task(server.run(), name="test.camera")
        try:
            frames = []
            async with open_sim_source(CameraConfig(source="sim", path=str(sock))) as source:
                async for frame in source:
                    frames.append(frame)
                    if len(frames) == 4:
                        break
        finally:
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
    stamps = [f.stamp_s for f in frames]
    assert all(b > a for a, b in itertools.pairwise(stamps))
    # 10 Hz of sim time: never faster than the rate (a slow host skips slots, it never bunches them).
    assert stamps[-1] - stamps[0] >= 3 * 0.1 - 0.03
    for f in frames:
        assert f.rgb.shape == (480, 640, 3)
        assert f.rgb.dtype == np.uint8
        assert f.depth_m.dtype == np.float32
        assert f.intrinsics.width_px == 640
        assert f.truth is not None
        assert f.truth.box_xyxy_px is not None
        # The leader's true position in the camera frame at that stamp: ~6 m ahead (mount pitch 5 deg).
        assert 5.8 < float(f.truth.p_cam_leader_m[2]) < 6.1
        x0, y0, x1, y1 = (int(v) for v in f.truth.box_xyxy_px)
        inside = f.depth_m[y0:y1, x0:x1]
        valid = inside[(inside > 0) & (inside < 8.0)]
        assert valid.size > 20
        assert abs(float(np.median(valid)) - 6.0) < 0.4  # depth in mm on the wire, metres here
        assert f.truth.p_ned_leader_m is not None
        assert abs(float(f.truth.p_ned_leader_m[1]) - 0.2 * f.stamp_s) < 0.02  # truth sampled at the stamp
    assert server.frames_sent >= 4


async def test_missing_socket_is_one_clear_camera_error(tmp_path: Path) -> None:
    path = tmp_path / "nothing.sock"
    with pytest.raises(CameraError) as err:
        async with SimFrameSource(path):
            pass
    msg = str(err.value)
    assert "\n" not in msg
    assert str(path) in msg
    assert "sitl serve" in msg


async def test_stalled_camera_sends_nothing_and_slow_readers_do_not_block(tmp_path: Path) -> None:
    clock = SimClock()
    sock = tmp_path / "cam.sock"
    visual = VisualConfig(structures=0, tree_line=False, hills=False)
    async with CameraServer(sock, stub_truth(clock), clock, rate_hz=20.0, visual=visual) as server:
        task = asyncio.create_task(server.run(), name="test.camera")
        try:
            _reader, writer = await asyncio.open_unix_connection(str(sock))  # connects, never reads
            server.stalled = True
            await asyncio.sleep(0.3)
            assert server.frames_sent == 0
            server.stalled = False
            t0 = clock()
            while server.frames_sent + server.frames_dropped < 8 and clock() - t0 < 20.0:  # noqa: ASYNC110
                await asyncio.sleep(0.05)
            assert server.frames_dropped > 0  # the reader never drained its socket
            assert server.frames_sent <= 6
            writer.close()
        finally:
            task.cancel()
            with pytest.raises(asyncio.CancelledError):
                await task
    assert not sock.exists()
