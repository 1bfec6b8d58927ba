"""What ``companion sim`` runs *inside* ``sitl serve`` (passed in by :mod:`.sitl_host`).

Tasks beside the simulation, configured by the JSON file named in ``$WINGMAN_SIM_RUN`` (written by
``companion sim`` for this run; read once here, at the component's edge):

* ``clock``: publishes the sim time for the service (:mod:`companion.lab.evaluation.simclock`);
* ``truth``: records both vehicles' truth for scoring (:mod:`companion.lab.evaluation.truthlog`);
* ``camera``: the renderer's :class:`~sitl.render.camera_server.CameraServer` for the follower at the
  scenario's camera rate, blind to the leader inside the scenario's ``[run] leader_hidden_s`` windows;
* ``autopilot``: every vehicle's flight modes (from its HEARTBEAT) and STATUSTEXTs, as JSON lines, so the
  report shows what the autopilot itself did (its failsafes above all), on either backend;
* ``leader_share`` (when set): what the leader's companion would share over MQTT for the service's
  ``vision_external_position`` fallback: the global position the leader's *autopilot* reports (its
  estimate, never the truth), on ``{"host", "port", "topic", "rate_hz"}``.

Keys: ``camera_socket``, ``camera_rate_hz``, ``clock_path``, ``truth_path``, ``truth_rate_hz``, ``seed``,
``mount`` (the service's ``[camera.mount]``), ``leader_hidden_s``, ``autopilot_log_path`` and
``leader_share`` (optional).
"""

from __future__ import annotations

import asyncio
import json
import logging
import os
import time
from pathlib import Path
from typing import Any

import aiomqtt

from companion.kernel.camera import MountConfig
from companion.lab.evaluation.simclock import SimClockWriter
from companion.lab.evaluation.truthlog import TruthWriter, truth_row
from companion.telemetry.payloads import LeaderPositionMsg

log = logging.getLogger(__name__)

RUN_ENV = "WINGMAN_SIM_RUN"
#: How often the clock is published, sim s (the simulation advances in 5 ms physics steps).
CLOCK_PERIOD_S = 0.002


async def run(sim: Any) -> None:
    """The component: the tasks above (those its settings ask for) until ``sitl serve`` stops."""
    settings = json.loads(Path(os.environ[RUN_ENV]).read_text())  # noqa: ASYNC240 (once, at start)
    async with asyncio.TaskGroup() as tg:
        tg.create_task(_clock(sim, Path(settings["clock_path"])), name="sim.clock")
        tg.create_task(
            _truth(sim, Path(settings["truth_path"]), float(settings["truth_rate_hz"])), name="sim.truth"
        )
        tg.create_task(_camera(sim, settings), name="sim.camera")
        if settings.get("autopilot_log_path"):
            tg.create_task(_autopilot_log(sim, Path(settings["autopilot_log_path"])), name="sim.autopilot")
        if settings.get("leader_share"):
            tg.create_task(_leader_share(sim, settings["leader_share"]), name="sim.leader_share")


async def _clock(sim: Any, path: Path) -> None:
    with SimClockWriter(path) as writer:
        writer.publish(sim.t_s, time.monotonic())
        if hasattr(sim, "on_time"):
            # An autopilot in its own process (PX4) keeps time whatever this loop does: publish from its
            # clock stream as it arrives.
            sim.on_time(lambda t_s: writer.publish(t_s, time.monotonic()))
            await asyncio.Event().wait()
        while True:
            writer.publish(sim.t_s, time.monotonic())
            await sim.wait_until(sim.t_s + CLOCK_PERIOD_S)


async def _truth(sim: Any, path: Path, rate_hz: float) -> None:
    period_s = 1.0 / rate_hz
    next_s = 0.0
    with TruthWriter(path) as writer:
        while True:
            await sim.wait_until(next_s)
            t_s = sim.t_s
            writer.write(truth_row(t_s, sim.truth("follower"), sim.truth("leader")))
            next_s = max(next_s + period_s, t_s)


#: How often the autopilots' modes and texts are polled, sim s.
AUTOPILOT_POLL_S = 0.05


async def _autopilot_log(sim: Any, path: Path) -> None:
    """Mode changes and STATUSTEXTs of every vehicle, one JSON object a line, flushed as they come."""
    modes: dict[str, tuple[str, bool]] = {}
    texts_seen: dict[str, int] = {}
    with path.open("w", encoding="utf-8") as out:
        while True:
            t_s = sim.t_s
            for name in sim.names:
                mode = tuple(sim.mode(name))
                if modes.get(name) != mode:
                    modes[name] = mode
                    row = {"t_s": round(t_s, 3), "vehicle": name, "mode": mode[0], "armed": bool(mode[1])}
                    out.write(json.dumps(row) + "\n")
                texts = sim.status_texts(name)
                for text_t_s, severity, text in texts[texts_seen.get(name, 0) :]:
                    row = {"t_s": round(text_t_s, 3), "vehicle": name, "severity": severity, "text": text}
                    out.write(json.dumps(row) + "\n")
                texts_seen[name] = len(texts)
            out.flush()
            await sim.wait_until(t_s + AUTOPILOT_POLL_S)


#: Reconnect delay of the leader's share publisher after the broker went away, s.
SHARE_RETRY_S = 0.5


async def _leader_share(sim: Any, where: dict[str, Any]) -> None:
    """The leader autopilot's global position on MQTT at ``rate_hz`` (sim time), as its companion would."""
    period_s = 1.0 / float(where["rate_hz"])
    topic = str(where["topic"])
    while True:
        try:
            async with aiomqtt.Client(
                str(where["host"]), int(where["port"]), identifier="wingman-sim-leader"
            ) as c:
                next_s = sim.t_s
                while True:
                    await sim.wait_until(next_s)
                    g = sim.global_estimate("leader")
                    if g is not None:
                        msg = LeaderPositionMsg(
                            lat_deg=g.lat_deg,
                            lon_deg=g.lon_deg,
                            alt_amsl_m=g.alt_amsl_m,
                            v_ned_m_s=g.v_ned_m_s,
                            time_unix_s=time.time(),
                            yaw_deg=g.yaw_deg,
                        )
                        await c.publish(topic, msg.model_dump_json(exclude_none=True), qos=0)
                    next_s = max(next_s + period_s, sim.t_s)
        except aiomqtt.MqttError as exc:
            log.warning("leader share: %s; retrying", exc)
            await asyncio.sleep(SHARE_RETRY_S)


async def _camera(sim: Any, settings: dict[str, Any]) -> None:
    from sitl.render.camera_server import CameraServer  # noqa: PLC0415
    from sitl.render.config import CameraModel, visual_from_mapping  # noqa: PLC0415 (renderer: heavy)

    scenario = sim.scenario
    hidden = [(float(a), float(b)) for a, b in settings.get("leader_hidden_s", [])]

    def truth() -> tuple[Any, Any]:
        t_s = sim.t_s
        leader = None if any(a <= t_s < b for a, b in hidden) else sim.truth("leader")
        return sim.truth("follower"), leader

    rate_hz = float(settings["camera_rate_hz"])
    async with CameraServer(
        settings["camera_socket"],
        truth,
        lambda: sim.t_s,
        rate_hz=rate_hz,
        camera=CameraModel(rate_hz=rate_hz),
        visual=visual_from_mapping(scenario.visual, f"scenario {scenario.name} [visual]"),
        mount=MountConfig.model_validate(settings["mount"]),
        seed=int(settings["seed"]),
        wait_until=sim.wait_until,
        depth_glitches=scenario.faults("follower").camera.glitches(),
    ) as server:
        await server.run()
