"""The per-frame path on the event loop: camera -> latest-frame mailbox -> detector in a thread -> tracker.

Two tasks share one :class:`~companion.service.mailbox.Latest` slot: the pump writes every frame the source
yields, the worker takes the newest one when it is free. At most one inference is in flight, and a frame
that arrives while the detector is busy replaces the waiting one (it is dropped and counted), so latency
never builds up behind a slow detector. The detector runs in one dedicated worker thread (not the shared
default executor): even when a cancelled call is still finishing in its thread, the next one queues behind
it, so the detector, which is not thread-safe, never runs twice at once. The
post-detector stages (pose, tracker) are sub-millisecond numpy and run on the loop, next to the telemetry
that feeds them their attitude history.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

from companion.kernel import compat
from companion.kernel.camera import RgbdFrame
from companion.kernel.clock import Clock
from companion.perception.types import DetectorResult, FrameSource
from companion.service.health import HealthBoard
from companion.service.latency import LatencyStats
from companion.service.mailbox import Latest, MailboxClosedError

log = logging.getLogger(__name__)

CAMERA = "camera"
PERCEPTION = "perception"


@dataclass(frozen=True, slots=True)
class _Arrival:
    frame: RgbdFrame
    arrived_s: float


class PerceptionLoop:
    """Runs a frame source and a detector, and hands each frame and its detections to ``process``.

    Args:
        source: an opened frame source (the caller owns its context).
        detect: the detector on one frame (usually ``lambda f: detector.detect(f.rgb)``); only ever
            called from one worker thread, one frame at a time.
        process: pose, tracker and mission for one frame (on the loop, after the detector).
        clock: the service clock (latency, health).
        latency: per-stage latency sink (``queue``, ``detect``, ``preprocess``, ``inference``,
            ``postprocess``, ``track``, ``end_to_end``; ms).
        health: board with ``camera`` and ``perception`` registered by :meth:`register`.
    """

    def __init__(
        self,
        source: FrameSource,
        detect: Callable[[RgbdFrame], DetectorResult],
        process: Callable[[RgbdFrame, DetectorResult], object],
        *,
        clock: Clock,
        latency: LatencyStats,
        health: HealthBoard,
    ) -> None:
        self._source = source
        self._detect = detect
        self._process = process
        self._clock = clock
        self._latency = latency
        self._health = health
        self._frames: Latest[_Arrival] | None = None
        self._dropped_before = 0
        # One thread for the loop's whole life, across restarts: the detector never runs twice at once.
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="companion-detector")
        self.frames_received = 0
        self.frames_processed = 0
        self.source_ended = False

    @staticmethod
    def register(health: HealthBoard, camera_stale_s: float = 2.0) -> None:
        """Declare the two components (neither is critical: the mission handles a stalled camera)."""
        health.register(CAMERA, critical=False, stale_after_s=camera_stale_s)
        health.register(PERCEPTION, critical=False, stale_after_s=camera_stale_s)

    @property
    def frames_dropped(self) -> int:
        """Frames replaced in the mailbox before the detector was free to take them."""
        return self._dropped_before + (0 if self._frames is None else self._frames.dropped)

    def counters(self) -> dict[str, int]:
        return {
            "received": self.frames_received,
            "processed": self.frames_processed,
            "dropped": self.frames_dropped,
        }

    async def run(self) -> None:
        """Pump and worker until the source ends (a recording) or the task is cancelled."""
        frames: Latest[_Arrival] = Latest()  # fresh per run: a restart never sees a closed mailbox
        self._frames = frames
        try:
            async with compat.TaskGroup() as tg:
                tg.create_task(self._pump(frames), name="companion.perception.camera")
                tg.create_task(self._work(frames), name="companion.perception.detector")
        finally:
            self._dropped_before += frames.dropped
            self._frames = None

    def close(self) -> None:
        """Release the detector thread (after the last :meth:`run`; a call still running finishes)."""
        self._executor.shutdown(wait=False, cancel_futures=True)

    async def _pump(self, frames: Latest[_Arrival]) -> None:
        async for frame in self._source:
            self.frames_received += 1
            frames.put(_Arrival(frame, self._clock.now_s()))
            self._health.beat(CAMERA, detail=f"frame {frame.seq}")
        frames.close()  # the worker finishes the last frame, then returns
        self.source_ended = True
        log.info("frame source ended after %d frames", self.frames_received)

    async def _work(self, frames: Latest[_Arrival]) -> None:
        loop = asyncio.get_running_loop()
        while True:
            try:
                arrival = await frames.take()
            except MailboxClosedError:
                return
            t0 = self._clock.now_s()
            self._latency.record("queue", (t0 - arrival.arrived_s) * 1e3)
            result = await loop.run_in_executor(self._executor, self._detect, arrival.frame)
            t1 = self._clock.now_s()
            self._process(arrival.frame, result)
            t2 = self._clock.now_s()
            self.frames_processed += 1
            self._latency.record("detect", (t1 - t0) * 1e3)
            if result.timing is not None:
                self._latency.record("preprocess", result.timing.preprocess_ms)
                self._latency.record("inference", result.timing.inference_ms)
                self._latency.record("postprocess", result.timing.postprocess_ms)
            self._latency.record("track", (t2 - t1) * 1e3)
            self._latency.record("end_to_end", (t2 - arrival.arrived_s) * 1e3)
            self._health.beat(PERCEPTION, detail=f"{len(result.detections)} detection(s)")
