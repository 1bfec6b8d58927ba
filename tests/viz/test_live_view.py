"""The live view: a Foxglove WebSocket client subscribes to the real server and decodes what it sends."""

from __future__ import annotations

import asyncio
import base64
import json
import struct

import cv2
import numpy as np
import websockets

from companion.config import Config, VizConfig
from companion.estimation.pipeline import PerceptionPipeline
from companion.kernel import compat
from companion.kernel.clock import ManualClock
from companion.kernel.flight import FlightMode, VehicleState, VelocityNedSetpoint
from companion.mission.types import MissionInputs, MissionState, Reason, StepOutput, Transition
from companion.perception.sources.mcap_file import protobuf_class
from companion.perception.types import Detection, DetectorResult
from companion.viz.setup import build_recorder
from tests.synthetic import sequence_frames

WANTED = ("/camera/image", "/camera/annotations", "/scene", "/camera/depth")


async def _json_op(ws: websockets.ClientConnection, op: str) -> dict:
    while True:
        msg = await ws.recv()
        if isinstance(msg, str) and json.loads(msg)["op"] == op:
            return json.loads(msg)


def _complete(channels: dict, scene: bytes) -> bool:
    ids = {e.id for e in _decode(channels, "/scene", scene).entities}
    return {"follower/body", "follower/slot", "follower/leader", "follower/frustum"} <= ids


def _decode(channels: dict, topic: str, data: bytes):
    c = channels[topic]
    assert c["encoding"] == "protobuf"
    assert c["schemaEncoding"] == "protobuf"
    return protobuf_class(c["schemaName"], base64.b64decode(c["schema"])).FromString(data)


async def test_a_foxglove_client_subscribes_and_decodes_images_annotations_and_the_scene() -> None:
    cfg = Config()
    frames = sequence_frames(12, fps=30.0)
    clock = ManualClock(frames[0].stamp_s)
    pipeline = PerceptionPipeline.from_config(cfg, guard_brake_m_s2=None)
    viz = VizConfig(live=True, port=0, live_image_rate_hz=30.0, live_depth_rate_hz=30.0)
    rec = build_recorder(viz, pipeline.camera, clock, log_place=None)
    assert rec is not None
    with rec:
        port = rec.outputs[0].port
        url = f"ws://127.0.0.1:{port}"
        async with websockets.connect(url, subprotocols=["foxglove.sdk.v1", "foxglove.websocket.v1"]) as ws:
            assert (await _json_op(ws, "serverInfo"))["name"] == "wingman"
            channels = {c["topic"]: c for c in (await _json_op(ws, "advertise"))["channels"]}
            assert set(WANTED) <= set(channels)
            subs = {k + 1: channels[t] for k, t in enumerate(WANTED)}
            await ws.send(
                json.dumps(
                    {
                        "op": "subscribe",
                        "subscriptions": [{"id": i, "channelId": c["id"]} for i, c in subs.items()],
                    }
                )
            )
            live = rec.outputs[0]
            for _ in range(200):  # the server takes the subscription on its own thread
                if all(live.wants(t) for t in WANTED):
                    break
                await asyncio.sleep(0.02)
            rec.on_transition(
                Transition(
                    frames[0].stamp_s, MissionState.ACQUIRE, MissionState.FOLLOW, Reason.LEADER_ACQUIRED
                )
            )
            for frame in frames:
                clock.set(frame.stamp_s)
                assert frame.truth is not None
                assert frame.truth.box_xyxy_px is not None
                result = DetectorResult([Detection(frame.truth.box_xyxy_px, 0.9)])
                track = pipeline.process(frame, result.detections)
                rec.on_frame(frame, result, track)
                est = track.leader_estimate()
                inputs = MissionInputs(
                    vehicle=VehicleState(connected=True, armed=True, flight_mode=FlightMode.OFFBOARD),
                    leader=est,
                )
                out = StepOutput(
                    MissionState.FOLLOW,
                    setpoint=VelocityNedSetpoint((0.5, 0.0, 0.0), 0.0),
                    formation_error_ned_m=(0.2, -0.1, 0.0),
                )
                rec.on_step(inputs, out)
            got: dict[str, list[bytes]] = {t: [] for t in WANTED}
            async with compat.timeout(20.0):
                # Steps queued faster than the worker sends reach the live view as their newest: at
                # least one scene, never more than one per step; the last step's scene has them all.
                while (
                    len(got["/scene"]) < 1
                    or not all(got.values())
                    or not _complete(channels, got["/scene"][-1])
                ):
                    msg = await ws.recv()
                    if isinstance(msg, bytes) and msg[0] == 0x01:
                        sub_id, _log_time_ns = struct.unpack_from("<IQ", msg, 1)
                        got[subs[sub_id]["topic"]].append(msg[13:])

    image = _decode(channels, "/camera/image", got["/camera/image"][-1])
    assert image.format == "jpeg"
    assert image.frame_id == "camera"
    rgb = cv2.imdecode(np.frombuffer(image.data, np.uint8), cv2.IMREAD_COLOR)
    assert rgb.shape == frames[0].rgb.shape
    depth = _decode(channels, "/camera/depth", got["/camera/depth"][-1])
    assert depth.encoding == "16UC1"
    assert (depth.width, depth.height) == (320, 240)
    ann = _decode(channels, "/camera/annotations", got["/camera/annotations"][-1])
    assert len(ann.points) == 1
    assert len(ann.points[0].points) == 4
    assert any(t.text.startswith("leader 0.90") for t in ann.texts)  # the tracked leader and its confidence
    assert 1 <= len(got["/scene"]) <= len(frames)
    scenes = [_decode(channels, "/scene", d) for d in got["/scene"]]
    ids = {e.id for s in scenes for e in s.entities}
    assert {"follower/body", "follower/slot", "follower/leader", "follower/frustum"} <= ids
    frames_used = {e.frame_id for s in scenes for e in s.entities}
    assert frames_used == {"world", "follower", "camera"}
