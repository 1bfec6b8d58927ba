"""PerceptionLoop: at most one inference in flight, stale frames dropped and counted, nothing queued."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import AsyncIterator
from types import TracebackType

import numpy as np

from companion.kernel import compat
from companion.kernel.camera import Intrinsics, RgbdFrame, RgbImage
from companion.kernel.clock import MonotonicClock
from companion.kernel.compat import Self
from companion.perception.types import Detection, DetectorResult, DetectorTiming
from companion.service.health import HealthBoard
from companion.service.latency import LatencyStats
from companion.service.perception_loop import PerceptionLoop

K = Intrinsics.from_hfov(64, 48, 87.0)


class BurstSource:
    """Yields n frames every period_s (faster than the detector)."""

    def __init__(self, n: int, period_s: float) -> None:
        self.n = n
        self.period_s = period_s

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        return None

    def __aiter__(self) -> AsyncIterator[RgbdFrame]:
        return self._gen()

    async def _gen(self) -> AsyncIterator[RgbdFrame]:
        for i in range(self.n):
            rgb = np.full((48, 64, 3), i % 256, np.uint8)
            yield RgbdFrame(rgb, np.ones((48, 64), np.float32), K, time.monotonic(), seq=i)
            await asyncio.sleep(self.period_s)


class SlowDetector:
    """Sleeps in its thread and records how many calls overlap."""

    def __init__(self, delay_s: float) -> None:
        self.delay_s = delay_s
        self.active = 0
        self.max_active = 0
        self.calls = 0
        self.threads: set[str] = set()
        self._lock = threading.Lock()

    def detect(self, rgb: RgbImage) -> DetectorResult:
        with self._lock:
            self.active += 1
            self.calls += 1
            self.max_active = max(self.max_active, self.active)
            self.threads.add(threading.current_thread().name)
        time.sleep(self.delay_s)
        with self._lock:
            self.active -= 1
        return DetectorResult([Detection((1, 2, 3, 4), 0.9)], DetectorTiming(1.0, self.delay_s * 1e3, 0.5))


async def test_one_inference_in_flight_and_stale_frames_dropped() -> None:
    health = HealthBoard(MonotonicClock())
    PerceptionLoop.register(health)
    latency = LatencyStats()
    detector = SlowDetector(0.03)
    seen: list[int] = []

    def process(frame: RgbdFrame, result: DetectorResult) -> int:
        assert threading.current_thread() is threading.main_thread()  # post-detector stages on the loop
        seen.append(frame.seq)
        return frame.seq

    loop = PerceptionLoop(
        BurstSource(60, 0.005),
        lambda f: detector.detect(f.rgb),
        process,
        clock=MonotonicClock(),
        latency=latency,
        health=health,
    )
    async with compat.timeout(20):
        await loop.run()
    loop.close()
    c = loop.counters()
    assert c["received"] == 60
    assert detector.max_active == 1
    assert len(detector.threads) == 1
    assert c["dropped"] > 20  # the detector is ~6x slower than the camera
    assert c["processed"] + c["dropped"] == c["received"]
    assert seen == sorted(seen)
    assert seen[-1] == 59  # the newest frame is always the one processed last
    s = latency.summary()
    assert s["detect"]["p50_ms"] >= 25
    assert set(s) >= {"queue", "detect", "inference", "track", "end_to_end"}
    assert health.component("perception").ok


async def test_cancel_mid_inference_does_not_overlap_the_next_call() -> None:
    health = HealthBoard(MonotonicClock())
    PerceptionLoop.register(health)
    detector = SlowDetector(0.2)
    loop = PerceptionLoop(
        BurstSource(1000, 0.01),
        lambda f: detector.detect(f.rgb),
        lambda f, r: f.seq,
        clock=MonotonicClock(),
        latency=LatencyStats(),
        health=health,
    )
    for _ in range(2):  # as supervise() would restart it
        with_cancel = asyncio.create_task(loop.run())
        await asyncio.sleep(0.1)  # mid-inference
        with_cancel.cancel()
        await asyncio.gather(with_cancel, return_exceptions=True)
    processed_before = loop.frames_processed
    loop2_task = asyncio.create_task(loop.run())
    await asyncio.sleep(0.7)
    assert not loop2_task.done()  # the restarted loop runs (it would die on a closed mailbox)
    loop2_task.cancel()
    await asyncio.gather(loop2_task, return_exceptions=True)
    loop.close()
    assert detector.max_active == 1
    assert loop.frames_processed >= processed_before + 2
