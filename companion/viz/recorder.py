"""``FlightRecorder``: observes the flight and feeds the live view and the flight log from a worker.

On the flight loop (:meth:`on_frame`, :meth:`on_step`, :meth:`on_transition`) it only appends references
to bounded deques and sets an event: no copy, no encoding, no I/O, no lock held for long. The worker thread
takes them, builds the messages (:mod:`companion.viz.messages`), encodes images (JPEG or PNG, at most at
each sink's image rate, judged on the frames' own stamps) and writes to the sinks. A worker that falls
behind drops the oldest frames and steps (counted); transitions are kept. The live view gets only the
newest frame and step of a backlog, and no topic more than :data:`LIVE_MAX_RATE_HZ`, the latest held back
until its turn (a viewer wants the latest state at a rate it can draw, not a burst); the log gets every
one. A failing sink is turned off with one line; a failure in building a message is counted and said once
per kind. The flight never waits.

``synchronous=True`` (the lockstep simulator, which has no real time) does the same work in the caller,
every frame and step, so a log is the same on every run.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from companion.config import VizConfig
from companion.kernel.camera import RgbdFrame
from companion.kernel.clock import Clock
from companion.mission.types import MissionInputs, StepOutput, Transition
from companion.perception.transform import CameraGeometry
from companion.perception.types import DetectorResult
from companion.viz import channels as ch
from companion.viz.encode import Record, encode_colour
from companion.viz.messages import MessageBuilder, Namespace
from companion.viz.sinks import LiveSink, McapSink, SinkError

log = logging.getLogger(__name__)

#: Frames (with their images) the worker may fall behind by before the oldest is dropped.
FRAME_BACKLOG = 8
#: Control steps it may fall behind by (20 Hz: 5 s).
STEP_BACKLOG = 100
#: How often the health flags are sampled, s.
HEALTH_PERIOD_S = 1.0
#: The live view's depth image is every n-th pixel each way (a quarter of the bytes).
LIVE_DEPTH_STEP = 2
#: The most messages a second any one live topic gets, judged on the worker's clock when it sends. A viewer
#: draws at its screen's rate and Lichtblick warns of topics above 60 Hz; the sources are 20 Hz (control
#: steps) and 30 Hz (camera frames), so this only trims bursts, which a worker that fell behind would
#: otherwise send at once. The flight log keeps every message.
LIVE_MAX_RATE_HZ = 40.0


@dataclass(slots=True)
class RateCap:
    """At most ``max_rate_hz`` messages a topic, the latest kept.

    A message sooner than a period after the last one sent on its topic is held back (a newer one replaces
    it, counted as dropped) and sent by :meth:`release` once the period is over.
    """

    max_rate_hz: float
    last_sent_s: dict[str, float] = field(default_factory=dict)
    held: dict[str, tuple[int, bytes]] = field(default_factory=dict)
    dropped: int = 0

    def due(self, topic: str, now_s: float) -> bool:
        """Whether a message on ``topic`` may go now (if so, it counts as sent and replaces a held one)."""
        last_s = self.last_sent_s.get(topic)
        if last_s is not None and now_s - last_s < 1.0 / self.max_rate_hz:
            return False
        self.last_sent_s[topic] = now_s
        self.held.pop(topic, None)
        return True

    def hold(self, topic: str, log_time_ns: int, data: bytes) -> None:
        if topic in self.held:
            self.dropped += 1
        self.held[topic] = (log_time_ns, data)

    def release(self, now_s: float) -> list[Record]:
        """The held messages whose period is over, to send now."""
        out: list[Record] = []
        for topic in list(self.held):
            item = self.held[topic]
            if self.due(topic, now_s):
                out.append((topic, *item))
        return out


@dataclass(slots=True)
class _ImagePolicy:
    """One sink's images: colour format and rates (Hz; 0: every frame, None: never)."""

    colour_format: str
    colour_rate_hz: float | None
    depth_rate_hz: float | None
    depth_step: int
    next_colour_s: float = -1e18
    next_depth_s: float = -1e18

    def due(self, stamp_s: float, which: str) -> bool:
        rate = self.colour_rate_hz if which == "colour" else self.depth_rate_hz
        if rate is None:
            return False
        nxt = self.next_colour_s if which == "colour" else self.next_depth_s
        if stamp_s < nxt:
            return False
        # 0.9 of the period: frames at 30 Hz and a 10 Hz rate give every third frame, not every fourth.
        later = stamp_s + (0.9 / rate if rate > 0 else 0.0)
        if which == "colour":
            self.next_colour_s = later
        else:
            self.next_depth_s = later
        return True


@dataclass(slots=True)
class _Output:
    sink: Any
    images: _ImagePolicy
    #: The live view: its topics' rate cap, and only the newest of a backlog is sent.
    cap: RateCap | None = None
    on: bool = True
    errors: int = 0


class FlightRecorder:
    """A :class:`~companion.service.flight.FlightObserver` that feeds a live view and a flight log.

    Args:
        geometry: the camera's mount (the camera frame in the 3D scene).
        clock: the flight's clock (step times, health).
        time_offset_s: added to clock stamps for the logs' time (the wall clock's epoch in the service).
        namespace: topic and frame prefix and the origin in the shared world (formations).
        health: the service's health flags, sampled once a second on the worker (None: none).
        synchronous: do the work in the caller (the lockstep simulator); no thread.
        send_clock_s: the clock the live view's rate cap is judged on, s (monotonic).
    """

    def __init__(
        self,
        cfg: VizConfig,
        geometry: CameraGeometry,
        clock: Clock,
        *,
        time_offset_s: float = 0.0,
        namespace: Namespace | None = None,
        health: Callable[[], dict[str, Any]] | None = None,
        synchronous: bool = False,
        send_clock_s: Callable[[], float] = time.monotonic,
    ) -> None:
        self.cfg = cfg
        self._send_clock_s = send_clock_s
        self.clock = clock
        self.synchronous = synchronous
        self.builder = MessageBuilder(geometry, namespace or Namespace(), time_offset_s)
        self._health = health
        self._outputs: list[_Output] = []
        self._frames: deque[tuple[RgbdFrame, DetectorResult, Any]] = deque(maxlen=FRAME_BACKLOG)
        self._steps: deque[tuple[float, MissionInputs, StepOutput]] = deque(maxlen=STEP_BACKLOG)
        self._transitions: deque[Transition] = deque()
        self._wake = threading.Event()
        self._stop = False
        self._thread: threading.Thread | None = None
        self._said: set[str] = set()
        self._next_health_s = 0.0
        self.frames_seen = 0
        self.frames_dropped = 0
        self.steps_dropped = 0
        self.build_errors = 0
        self.images_written = 0

    @property
    def topics(self) -> list[ch.Topic]:
        """Every channel of this follower, its namespace applied."""
        ns = self.builder.ns
        return [
            ch.Topic(ns.topic(t.name), t.message_encoding, t.schema_name, t.schema_encoding, t.schema_data)
            for t in ch.TOPICS.values()
        ]

    # ---------------------------------------------------------------- sinks
    def add_live(self, sink: LiveSink) -> None:
        c = self.cfg
        policy = _ImagePolicy("jpeg", c.live_image_rate_hz, c.live_depth_rate_hz or None, LIVE_DEPTH_STEP)
        self._outputs.append(_Output(sink, policy, RateCap(LIVE_MAX_RATE_HZ)))

    def add_log(self, sink: McapSink) -> None:
        c = self.cfg
        rate = c.log_image_rate_hz
        self._outputs.append(
            _Output(sink, _ImagePolicy(c.log_image_format, rate, rate if c.log_depth else None, 1))
        )

    @property
    def outputs(self) -> list[Any]:
        """The sinks, on or off."""
        return [o.sink for o in self._outputs]

    # ---------------------------------------------------------------- the flight loop's side
    def on_frame(self, frame: RgbdFrame, result: DetectorResult, track: Any) -> None:
        self.frames_seen += 1
        if self.synchronous:
            self._guard("frame", self._frame, frame, result, track)
            self._release()
            return
        if len(self._frames) == FRAME_BACKLOG:
            self.frames_dropped += 1
        self._frames.append((frame, result, track))
        self._wake.set()

    def on_step(self, inputs: MissionInputs, out: StepOutput) -> None:
        now_s = self.clock.now_s()
        if self.synchronous:
            self._guard("step", self._step, now_s, inputs, out)
            self._release()
            self._maybe_health(now_s)
            return
        if len(self._steps) == STEP_BACKLOG:
            self.steps_dropped += 1
        self._steps.append((now_s, inputs, out))
        self._wake.set()

    def on_transition(self, tr: Transition) -> None:
        if self.synchronous:
            self._guard("transition", self._emit, self.builder.transition_records(tr), capped=False)
            return
        self._transitions.append(tr)
        self._wake.set()

    # ---------------------------------------------------------------- lifecycle
    def __enter__(self) -> FlightRecorder:
        if not self.synchronous:
            self._thread = threading.Thread(target=self._run, name="companion-viz", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def close(self) -> None:
        """Write what is queued, then close every sink (the flight log gets its summary)."""
        thread, self._thread = self._thread, None
        if thread is not None:
            self._stop = True
            self._wake.set()
            thread.join(timeout=10.0)
        for o in self._outputs:
            if o.on:
                o.on = False
                try:
                    o.sink.close()
                except SinkError as exc:
                    log.warning("%s: %s", o.sink.name, exc)

    def counters(self) -> dict[str, Any]:
        """For the status endpoint and the health channel."""
        return {
            "frames_seen": self.frames_seen,
            "frames_dropped": self.frames_dropped,
            "steps_dropped": self.steps_dropped,
            "images_written": self.images_written,
            "build_errors": self.build_errors,
            "live_dropped": sum(o.cap.dropped for o in self._outputs if o.cap is not None),
            "outputs": {o.sink.name: {"on": o.on, "errors": o.errors} for o in self._outputs},
        }

    # ---------------------------------------------------------------- the worker
    def _run(self) -> None:
        while True:
            held = any(o.cap is not None and o.cap.held for o in self._outputs)
            self._wake.wait(timeout=1.0 / LIVE_MAX_RATE_HZ if held else HEALTH_PERIOD_S)
            self._wake.clear()
            self._drain()
            self._release()
            self._maybe_health(self.clock.now_s())
            if self._stop:
                self._drain()
                return

    def _drain(self) -> None:
        while self._transitions:
            records = self.builder.transition_records(self._transitions.popleft())
            self._guard("transition", self._emit, records, capped=False)  # every change, never capped
        # Frames before steps: a frame was captured before the steps queued beside it, and it brings the
        # camera's intrinsics the scene's frustum is drawn from.
        # A backlog goes whole to the log; the live view gets its newest frame and step only.
        while self._frames:
            item = self._frames.popleft()
            self._guard("frame", self._frame, *item, live=not self._frames)
        while self._steps:
            step = self._steps.popleft()
            self._guard("step", self._step, *step, live=not self._steps)

    def _guard(self, kind: str, fn: Callable[..., None], *args: Any, **kwargs: Any) -> None:
        try:
            fn(*args, **kwargs)
        except Exception as exc:  # a bug in building a message must not end the worker or the flight
            self.build_errors += 1
            if kind not in self._said:
                self._said.add(kind)
                log.warning(
                    "viz: a %s could not be shown or logged (%s: %s); counted from now on",
                    kind,
                    type(exc).__name__,
                    exc,
                )

    def _step(self, now_s: float, inputs: MissionInputs, out: StepOutput, *, live: bool = True) -> None:
        self._emit(self.builder.step_records(now_s, inputs, out), live=live)

    def _frame(self, frame: RgbdFrame, result: DetectorResult, track: Any, *, live: bool = True) -> None:
        b = self.builder
        self._emit(b.frame_records(frame, result, track), live=live)
        encoded: dict[str, bytes] = {}
        depth: dict[int, Record] = {}
        image_topic, depth_topic = b.ns.topic(ch.IMAGE), b.ns.topic(ch.DEPTH)
        calibration: Record | None = None
        for o in self._outputs:
            if not o.on or (o.cap is not None and not live):
                continue
            pol = o.images
            colour = o.sink.wants(image_topic) and pol.due(frame.stamp_s, "colour")
            deep = o.sink.wants(depth_topic) and pol.due(frame.stamp_s, "depth")
            records: list[Record] = []
            if colour:
                fmt = pol.colour_format
                if fmt not in encoded:
                    encoded[fmt] = encode_colour(frame.rgb, fmt, self.cfg.jpeg_quality)
                records.append(b.image(frame, encoded[fmt], fmt))
            if deep:
                if pol.depth_step not in depth:
                    depth[pol.depth_step] = b.depth(frame, pol.depth_step)
                records.append(depth[pol.depth_step])
            if records:
                if calibration is None:
                    calibration = b.calibration(frame)
                records.append(calibration)
                self._write(o, records)
                self.images_written += int(colour) + int(deep)

    def _release(self) -> None:
        """Send the live view's held-back messages that are due (the latest of each topic)."""
        for o in self._outputs:
            if o.on and o.cap is not None and o.cap.held:
                records = o.cap.release(self._send_clock_s())
                if records:
                    self._write(o, records, capped=False)

    def _maybe_health(self, now_s: float) -> None:
        if now_s < self._next_health_s:
            return
        self._next_health_s = now_s + HEALTH_PERIOD_S
        payload: dict[str, Any] = {"viz": self.counters()}
        if self._health is not None:
            with contextlib.suppress(Exception):  # the board is read from another thread: best effort
                payload.update(self._health())
        self._guard("health sample", self._emit, [self.builder.health_record(now_s, payload)])

    def _emit(self, records: list[Record], *, live: bool = True, capped: bool = True) -> None:
        for o in self._outputs:
            if o.on and (live or o.cap is None):
                self._write(o, records, capped=capped)

    def _write(self, o: _Output, records: list[Record], *, capped: bool = True) -> None:
        cap = o.cap if capped else None
        now_s = self._send_clock_s() if cap is not None else 0.0
        try:
            for topic, ns, data in records:
                if cap is None or cap.due(topic, now_s):
                    o.sink.write(topic, ns, data)
                else:
                    cap.hold(topic, ns, data)
        except SinkError as exc:
            self._off(o, str(exc))
        except Exception as exc:  # the SDK's own errors: the same rule
            self._off(o, f"{type(exc).__name__}: {exc}")

    def _off(self, o: _Output, why: str) -> None:
        o.on = False
        o.errors += 1
        log.warning("%s off: %s; the flight goes on without it", o.sink.name, why)
        with contextlib.suppress(Exception):
            o.sink.close()


def wall_offset_s(clock: Clock) -> float:
    """The offset that puts ``clock``'s stamps on the wall clock's epoch (the service's logs), s."""
    return time.time() - clock.now_s()
