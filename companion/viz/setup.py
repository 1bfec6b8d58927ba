"""Building a :class:`FlightRecorder` from ``[viz]``: the service's and the simulator's one way in.

A sink that cannot start (the port taken, a folder it may not write) is one warning line and the flight
goes on without it; with neither sink left there is no recorder.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.config import VizConfig
from companion.kernel.clock import Clock
from companion.perception.transform import CameraGeometry
from companion.viz.messages import Namespace
from companion.viz.recorder import FlightRecorder
from companion.viz.sinks import LiveSink, McapSink, SinkError

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class LogPlace:
    """Where a flight log goes: a folder and the files' stem (``STEM.mcap``, ``STEM-002.mcap``, ...)."""

    folder: Path
    stem: str
    metadata: dict[str, str] | None = None


def health_flags(board: Any) -> Callable[[], dict[str, Any]]:
    """The service's health board (``companion.service.health.HealthBoard``) as the health channel has it."""

    def flags() -> dict[str, Any]:
        parts = board.snapshot()
        return {
            "healthy": all(c.ok for c in parts if c.critical),
            "components": {c.name: {"ok": c.ok, "alive": c.alive, "detail": c.detail} for c in parts},
        }

    return flags


def build_recorder(
    cfg: VizConfig,
    geometry: CameraGeometry,
    clock: Clock,
    *,
    log_place: LogPlace | None,
    server_name: str = "wingman",
    time_offset_s: float = 0.0,
    namespace: Namespace | None = None,
    health: Callable[[], dict[str, Any]] | None = None,
    synchronous: bool = False,
) -> FlightRecorder | None:
    """The recorder with the sinks ``cfg`` turns on (``log_place`` None: no log); not yet entered."""
    rec = FlightRecorder(
        cfg,
        geometry,
        clock,
        time_offset_s=time_offset_s,
        namespace=namespace,
        health=health,
        synchronous=synchronous,
    )
    if cfg.live:
        try:
            live = LiveSink(rec.topics, host=cfg.host, port=cfg.port, server_name=server_name)
        except SinkError as exc:
            log.warning("live view off: %s; the flight goes on without it", exc)
        else:
            rec.add_live(live)
            log.info("live view: ws://%s:%d (Foxglove or Lichtblick: open a connection)", cfg.host, live.port)
    if log_place is not None:
        try:
            sink = McapSink(
                log_place.folder,
                log_place.stem,
                rec.topics,
                file_max_bytes=cfg.log_file_max_bytes,
                budget_bytes=cfg.log_budget_bytes,
                metadata=log_place.metadata,
            )
        except SinkError as exc:
            log.warning("flight log off: %s; the flight goes on without it", exc)
        else:
            rec.add_log(sink)
            log.info("flight log: %s", sink.paths[0])
    return rec if rec.outputs else None
