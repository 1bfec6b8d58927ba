"""What the live view and the flight log cost the flight loop: ``python -m companion.lab.viz_bench``.

The service's per-frame path (:class:`~companion.service.perception_loop.PerceptionLoop`: camera task,
detector thread, then the :class:`~companion.service.flight.FlightService` on the event loop) runs on
640x480 RGB-D frames paced at 30 frames/s, with a 20 Hz control tick beside it. Blocks of ``--block-s``
alternate between the recorder off and on (the live view with a Foxglove client subscribed to every channel
in another process, and an MCAP log, both at the shipped ``[viz]`` rates), so a machine's changing load hits
both alike. Per frame: the flight's time on the loop (pose, tracker, observers) and the end-to-end
latency (arrival to estimate); per tick: how late the control tick woke; per block: frames the perception
loop dropped. The detector is the frames' own boxes, so the figures are the loop's, not the network's.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import sys
import tempfile
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any, cast

import numpy as np

from companion.config import Config, VizConfig
from companion.kernel.camera import RgbdFrame
from companion.kernel.clock import MonotonicClock
from companion.kernel.flight import FlightMode, VehicleState
from companion.lab.bench import synthetic_frames
from companion.mission.types import MissionInputs
from companion.perception.types import Detection, DetectorResult, DetectStage
from companion.service.flight import FlightService
from companion.service.health import HealthBoard
from companion.service.latency import LatencyStats
from companion.service.perception_loop import PerceptionLoop
from companion.viz.setup import LogPlace, build_recorder

FPS = 30.0
TICK_HZ = 20.0


class _PacedFrames:
    """A frame source: the same frames again and again, new stamps, at ``fps`` on the clock."""

    def __init__(self, frames: list[RgbdFrame], clock: MonotonicClock, fps: float) -> None:
        self.frames, self.clock, self.period_s = frames, clock, 1.0 / fps

    async def __aenter__(self) -> _PacedFrames:
        return self

    async def __aexit__(self, *exc: object) -> None:
        return None

    def __aiter__(self) -> AsyncIterator[RgbdFrame]:
        return self._run()

    async def _run(self) -> AsyncIterator[RgbdFrame]:
        next_s = self.clock.now_s()
        k = 0
        while True:
            await self.clock.sleep_until(next_s)
            f = self.frames[k % len(self.frames)]
            now_s = self.clock.now_s()
            yield RgbdFrame(f.rgb, f.depth_m, f.intrinsics, now_s, k, f.truth)
            k += 1
            next_s += self.period_s


def _truth_boxes(frame: RgbdFrame) -> DetectorResult:
    box = None if frame.truth is None else frame.truth.box_xyxy_px
    return DetectorResult([] if box is None else [Detection(box, 0.9)])


def _pct(xs: list[float]) -> dict[str, float]:
    if not xs:
        return {"p50": float("nan"), "p99": float("nan"), "n": 0}
    p50, p99 = np.percentile(np.asarray(xs), [50, 99])
    return {"p50": round(float(p50), 3), "p99": round(float(p99), 3), "n": len(xs)}


async def bench(block_s: float, blocks: int, out: Path) -> dict[str, Any]:
    """Alternate off/on blocks; the figures of each mode."""
    cfg = Config()
    clock = MonotonicClock()
    core = FlightService(cfg, cast(Any, None), clock, DetectStage(_truth_boxes))
    viz = cfg.viz.model_copy(update={"live": True, "port": 0, "log": True})
    rec = build_recorder(
        VizConfig.model_validate(viz.model_dump()),
        core.camera,
        clock,
        log_place=LogPlace(out, "bench"),
        time_offset_s=time.time() - clock.now_s(),
    )
    assert rec is not None  # noqa: S101 (both sinks open on a free port and a temporary folder)
    port = rec.outputs[0].port
    client = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "companion.lab.viz_bench", "--client", str(port)
    )
    mode = {"on": False}
    loop_ms: dict[bool, list[float]] = {False: [], True: []}
    tick_late_ms: dict[bool, list[float]] = {False: [], True: []}
    dropped: dict[bool, int] = {False: 0, True: 0}
    received: dict[bool, int] = {False: 0, True: 0}

    def process(frame: RgbdFrame, result: DetectorResult) -> Any:
        core.attitude.push(frame.stamp_s, np.array([1.0, 0.0, 0.0, 0.0]))
        t0 = time.perf_counter()
        track = core.on_frame(frame, result)
        loop_ms[mode["on"]].append((time.perf_counter() - t0) * 1e3)
        e2e[mode["on"]].append((clock.now_s() - frame.stamp_s) * 1e3)  # stamped as the camera task got it
        return track

    e2e: dict[bool, list[float]] = {False: [], True: []}
    frames = synthetic_frames(60)
    health = HealthBoard(clock)
    PerceptionLoop.register(health)
    perception: PerceptionLoop = PerceptionLoop(
        _PacedFrames(frames, clock, FPS),
        _truth_boxes,
        process,
        clock=clock,
        latency=LatencyStats(),
        health=health,
    )

    async def ticks() -> None:
        period = 1.0 / TICK_HZ
        next_s = clock.now_s()
        while True:
            next_s += period
            await clock.sleep_until(next_s)
            tick_late_ms[mode["on"]].append((clock.now_s() - next_s) * 1e3)
            est = None if core.track is None else core.track.leader_estimate()
            inputs = MissionInputs(
                vehicle=VehicleState(connected=True, armed=True, flight_mode=FlightMode.OFFBOARD), leader=est
            )
            out = core.machine.step(inputs, clock.now_s())
            for o in core.observers:
                o.on_step(inputs, out)

    with rec:
        try:
            async with asyncio.TaskGroup() as tg:
                ptask = tg.create_task(perception.run())
                ttask = tg.create_task(ticks())
                await asyncio.sleep(2.0)  # warm-up, the client connects
                for samples in (loop_ms, e2e, tick_late_ms):
                    samples[False].clear()
                for b in range(blocks):
                    on = b % 2 == 1
                    mode["on"] = on
                    if on:
                        core.observers.append(rec)
                    d0, r0 = perception.frames_dropped, perception.frames_received
                    await asyncio.sleep(block_s)
                    if on:
                        core.observers.remove(rec)
                    dropped[on] += perception.frames_dropped - d0
                    received[on] += perception.frames_received - r0
                ptask.cancel()
                ttask.cancel()
        except* asyncio.CancelledError:
            pass
        finally:
            client.terminate()
            await client.wait()
    counters = rec.counters()
    return {
        "fps": FPS,
        "block_s": block_s,
        "blocks": blocks,
        **{
            ("viz_on" if on else "viz_off"): {
                "flight_core_on_loop_ms": _pct(loop_ms[on]),
                "end_to_end_ms": _pct(e2e[on]),
                "control_tick_late_ms": _pct(tick_late_ms[on]),
                "frames_received": received[on],
                "frames_dropped": dropped[on],
            }
            for on in (False, True)
        },
        "recorder": counters,
    }


async def _client(port: int) -> None:
    """A Foxglove viewer: subscribe to every channel and read everything it is sent."""
    import websockets  # noqa: PLC0415

    url = f"ws://127.0.0.1:{port}"
    async with websockets.connect(url, subprotocols=[cast(Any, "foxglove.sdk.v1")]) as ws:
        while True:
            msg = await ws.recv()
            if isinstance(msg, str):
                op = json.loads(msg)
                if op["op"] == "advertise":
                    subs = [{"id": c["id"], "channelId": c["id"]} for c in op["channels"]]
                    await ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))


def main() -> int:
    """Run the benchmark and print its figures as JSON."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--block-s", type=float, default=5.0, help="seconds per block (default 5)")
    p.add_argument("--blocks", type=int, default=12, help="blocks, alternately off and on (default 12)")
    p.add_argument("--json", type=Path, default=None, help="also write the figures here")
    p.add_argument("--client", type=int, default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.client is not None:
        with contextlib.suppress(Exception):
            asyncio.run(_client(args.client))
        return 0
    with tempfile.TemporaryDirectory(prefix="viz-bench-") as tmp:
        result = asyncio.run(bench(args.block_s, args.blocks, Path(tmp)))
        result["log_bytes"] = sum(f.stat().st_size for f in Path(tmp).glob("*.mcap"))
    text = json.dumps(result, indent=2)
    print(text)
    if args.json is not None:
        args.json.write_text(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
