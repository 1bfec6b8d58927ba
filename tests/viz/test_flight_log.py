"""Flight log files: split beyond a size, the oldest deleted beyond the budget, off on a full disk."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from mcap.reader import make_reader

from companion.config import Config, VizConfig
from companion.estimation.pipeline import PerceptionPipeline
from companion.kernel.clock import ManualClock
from companion.perception.types import Detection, DetectorResult
from companion.viz.recorder import FlightRecorder
from companion.viz.sinks import McapSink
from tests.synthetic import sequence_frames


def _fly(rec: FlightRecorder, n: int) -> None:
    cfg = Config()
    pipeline = PerceptionPipeline.from_config(cfg, guard_brake_m_s2=None)
    for frame in sequence_frames(n, fps=30.0):
        assert frame.truth is not None
        assert frame.truth.box_xyxy_px is not None
        result = DetectorResult([Detection(frame.truth.box_xyxy_px, 0.8)])
        rec.clock.set(frame.stamp_s)  # type: ignore[attr-defined]
        rec.on_frame(frame, result, pipeline.process(frame, result.detections))


def test_logs_are_split_and_the_oldest_deleted_within_the_budget(tmp_path: Path) -> None:
    old = tmp_path / "follower1-20200101-000000.mcap"
    old.write_bytes(b"x" * 3_000_000)
    cfg = VizConfig(log=True, log_image_rate_hz=0.0, log_image_format="png")
    rec = FlightRecorder(
        cfg,
        PerceptionPipeline.from_config(Config(), guard_brake_m_s2=None).camera,
        ManualClock(0.0),
        synchronous=True,
    )
    sink = McapSink(
        tmp_path, "follower1-20300101-000000", rec.topics, file_max_bytes=1_500_000, budget_bytes=4_000_000
    )
    rec.add_log(sink)
    with rec:
        _fly(rec, 12)
    assert len(sink.paths) >= 2  # split beyond 1.5 MB
    assert not old.exists()  # deleted to make room for the first new file
    files = sorted(tmp_path.glob("*.mcap"))
    assert (
        sum(p.stat().st_size for p in files) <= 4_000_000 + 1_500_000
    )  # the budget plus the file being written
    frames = 0
    for p in files:
        with p.open("rb") as f:
            reader = make_reader(f)
            assert reader.get_summary() is not None  # every part closed with its summary
            frames += sum(1 for _ in reader.iter_messages(topics=["/camera/image"]))
    assert frames > 0  # the newest parts are kept


def test_a_full_disk_turns_the_log_off_with_one_line_and_the_flight_goes_on(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    (tmp_path / "flight.mcap").symlink_to("/dev/full")  # every write: ENOSPC
    cfg = VizConfig(log=True, log_image_rate_hz=0.0)
    geometry = PerceptionPipeline.from_config(Config(), guard_brake_m_s2=None).camera
    rec = FlightRecorder(cfg, geometry, ManualClock(0.0), synchronous=True)
    rec.add_log(McapSink(tmp_path, "flight", rec.topics, file_max_bytes=10**9, budget_bytes=10**12))
    with caplog.at_level(logging.WARNING, logger="companion.viz"), rec:
        _fly(rec, 30)  # 30 frames with images: far beyond the file's write buffer
    lines = [r.getMessage() for r in caplog.records]
    assert len(lines) == 1
    assert lines[0].startswith("flight log off: writing")
    assert "No space left on device" in lines[0]
    assert rec.counters()["outputs"]["flight log"] == {"on": False, "errors": 1}
    assert rec.frames_seen == 30
