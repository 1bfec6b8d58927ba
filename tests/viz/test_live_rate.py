"""The live view's rate: no topic above the cap however fast frames come, a backlog sent as its newest only.

Lichtblick warns of topics above 60 Hz; a viewer wants the latest state, not a burst. The flight log keeps
every message.
"""

from __future__ import annotations

from collections import Counter, defaultdict
from itertools import pairwise

from companion.config import Config, VizConfig
from companion.estimation.pipeline import PerceptionPipeline
from companion.kernel.clock import ManualClock
from companion.perception.types import Detection, DetectorResult
from companion.viz.recorder import LIVE_MAX_RATE_HZ, FlightRecorder
from tests.synthetic import sequence_frames


class _Sink:
    """A sink that keeps what it is given: (topic, send time) per message; it wants no images."""

    def __init__(self, name: str, clock: list[float]) -> None:
        self.name = name
        self.clock = clock
        self.sent: list[tuple[str, float]] = []
        self.data: dict[str, bytes] = {}

    def wants(self, topic: str) -> bool:
        return False

    def write(self, topic: str, log_time_ns: int, data: bytes) -> None:
        self.sent.append((topic, self.clock[0]))
        self.data[topic] = data

    def close(self) -> None:
        pass


def _recorder(synchronous: bool, send_s: list[float]) -> tuple[FlightRecorder, _Sink, _Sink]:
    geometry = PerceptionPipeline.from_config(Config(), guard_brake_m_s2=None).camera
    rec = FlightRecorder(
        VizConfig(live=True, log=True),
        geometry,
        ManualClock(0.0),
        synchronous=synchronous,
        send_clock_s=lambda: send_s[0],
    )
    live, log = _Sink("live view", send_s), _Sink("flight log", send_s)
    rec.add_live(live)  # type: ignore[arg-type]
    rec.add_log(log)  # type: ignore[arg-type]
    return rec, live, log


def _feed(rec: FlightRecorder, n: int, send_s: list[float], dt_s: float) -> None:
    pipeline = PerceptionPipeline.from_config(Config(), guard_brake_m_s2=None)
    for frame in sequence_frames(n, fps=30.0):
        assert frame.truth is not None
        assert frame.truth.box_xyxy_px is not None
        result = DetectorResult([Detection(frame.truth.box_xyxy_px, 0.8)])
        rec.on_frame(frame, result, pipeline.process(frame, result.detections))
        send_s[0] += dt_s


def test_frames_at_200_hz_reach_the_live_view_at_the_cap_the_latest_last_and_the_log_whole() -> None:
    send_s = [100.0]
    rec, live, log = _recorder(True, send_s)
    _feed(rec, 60, send_s, 0.005)  # 200 Hz on the send clock: 0.3 s
    times: dict[str, list[float]] = defaultdict(list)
    for topic, t in live.sent:
        times[topic].append(t)
    assert set(times) >= {"/perception/frame", "/camera/annotations"}
    for topic, ts in times.items():
        gaps = [b - a for a, b in pairwise(ts)]
        assert min(gaps) >= 1.0 / LIVE_MAX_RATE_HZ - 1e-9, (topic, min(gaps))
        assert len(ts) <= 0.3 * LIVE_MAX_RATE_HZ + 1, (topic, len(ts))
    assert Counter(t for t, _ in log.sent)["/perception/frame"] == 60
    assert rec.counters()["live_dropped"] > 0
    send_s[0] += 1.0 / LIVE_MAX_RATE_HZ
    rec._release()  # what the worker does when it wakes: the held-back latest goes out
    assert live.data["/perception/frame"] == log.data["/perception/frame"]  # the last frame's


def test_a_backlog_goes_to_the_live_view_as_its_newest_frame_only() -> None:
    send_s = [100.0]
    rec, live, log = _recorder(False, send_s)  # the worker not started: the frames queue up
    _feed(rec, 5, send_s, 0.0)
    rec._drain()  # what the worker does when it wakes
    assert Counter(t for t, _ in live.sent)["/perception/frame"] == 1
    assert Counter(t for t, _ in log.sent)["/perception/frame"] == 5
    assert live.data["/perception/frame"] == log.data["/perception/frame"]  # the newest
