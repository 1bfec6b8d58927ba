"""A simulator run's MCAP log (``flight.mcap`` beside ``report.json``): the service's recorder, lab settings.

Every harness logs through the service's own :class:`~companion.viz.recorder.FlightRecorder` observing the
service's :class:`~companion.service.flight.FlightService`, so a run's log has the channels a flight's has.
Lockstep runs record synchronously (every frame and step, the same file on every run); the real path
records as the service does, on its worker. Times are sim seconds from a fixed date, :data:`SIM_EPOCH_S`
(2000-01-01 00:00:00 UTC is the run's start), so a viewer's clock reads the run's own time and a lockstep
run's log is the same file on every run.
A formation's followers share one file, each under its vehicle id (``/follower2/camera/image``) and placed
in one ``world`` by its origin. Images follow ``[viz]`` (``log_image_rate_hz``, ``log_image_format``,
``log_depth``; ``companion sim --set viz.log_image_rate_hz=0`` logs every frame).
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from companion.config import Config
from companion.kernel.clock import Clock
from companion.service.flight import FlightService
from companion.viz.channels import Topic
from companion.viz.messages import Namespace
from companion.viz.recorder import FlightRecorder
from companion.viz.sinks import McapSink, SinkError

log = logging.getLogger(__name__)

RUN_LOG = "flight.mcap"
#: A run's sim time 0 in its log: 2000-01-01 00:00:00 UTC, s since the Unix epoch.
SIM_EPOCH_S = 946_684_800.0
#: A run's log is never split nor trimmed.
_UNBOUNDED_BYTES = 1 << 60


def run_sink(path: Path, topics: Sequence[Topic], metadata: dict[str, str] | None = None) -> McapSink | None:
    """The run's MCAP file (None, after one warning line, when it cannot be written)."""
    try:
        return McapSink(
            path.parent,
            path.stem,
            topics,
            file_max_bytes=_UNBOUNDED_BYTES,
            budget_bytes=_UNBOUNDED_BYTES,
            metadata=metadata,
        )
    except SinkError as exc:
        log.warning("flight log off: %s; the run goes on without it", exc)
        return None


def recorder_for(
    cfg: Config,
    core: FlightService,
    clock: Clock,
    *,
    synchronous: bool,
    namespace: Namespace | None = None,
    health: Callable[[], dict[str, Any]] | None = None,
) -> FlightRecorder:
    """A recorder observing ``core`` (no sink yet: :meth:`FlightRecorder.add_log`)."""
    rec = FlightRecorder(
        cfg.viz,
        core.camera,
        clock,
        time_offset_s=SIM_EPOCH_S,
        namespace=namespace,
        health=health,
        synchronous=synchronous,
    )
    core.observers.append(rec)
    return rec


def attach_run_log(
    cfg: Config,
    core: FlightService,
    clock: Clock,
    path: Path,
    *,
    synchronous: bool,
    metadata: dict[str, str] | None = None,
    health: Callable[[], dict[str, Any]] | None = None,
) -> FlightRecorder | None:
    """One follower's run log at ``path``, observing ``core``; enter the returned recorder (None: no log)."""
    rec = recorder_for(cfg, core, clock, synchronous=synchronous, health=health)
    sink = run_sink(path, rec.topics, metadata)
    if sink is None:
        core.observers.remove(rec)
        return None
    rec.add_log(sink)
    return rec
