"""The parts the service runs: the flight and perception parts a :data:`PartsFactory` opens for it.

:class:`~companion.app.FollowerService` lends the factory its clock, health board and latency figures
(:class:`PartsContext`); :mod:`companion.service.wiring` builds the real parts, tests build their own.
"""

from __future__ import annotations

import contextlib
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from companion.kernel.clock import Clock
from companion.service.health import HealthBoard
from companion.service.latency import LatencyStats
from companion.service.perception_loop import PerceptionLoop
from companion.service.ports import FlightPort, GcsPort
from companion.telemetry.payloads import LeaderPositionMsg, PoseMsg


@dataclass(slots=True)
class Parts:
    """The flight and perception parts, opened by a :data:`PartsFactory` on the service's exit stack."""

    mission: FlightPort
    gcs: GcsPort | None = None
    perception: PerceptionLoop | None = None
    #: Where leader positions received on MQTT go (``leader.shared_position = "mqtt"``).
    on_leader_position: Callable[[LeaderPositionMsg], None] | None = None
    #: Where the other followers' poses received on MQTT go (formations: ``formation.plan``).
    on_neighbour_pose: Callable[[str, PoseMsg], None] | None = None
    #: Does the mission runner send STATUSTEXT on transitions itself? Then the service does not.
    mission_sends_statustext: bool = False
    #: Loops the parts need while the service runs (e.g. the link's telemetry), by task name. Critical:
    #: if one raises, the service ends. They are cancelled when the service stops.
    background: dict[str, Callable[[], Awaitable[None]]] = field(default_factory=dict)
    extra_status: dict[str, Callable[[], Any]] = field(default_factory=dict)
    #: Returns once the link to the configured vehicle is up (READY=1 waits for it); None: at once.
    link_ready: Callable[[], Awaitable[None]] | None = None


@dataclass(frozen=True, slots=True)
class PartsContext:
    """What the service lends the parts it opens."""

    clock: Clock
    health: HealthBoard
    latency: LatencyStats


#: Opens the parts on the given stack (closed when the service ends).
PartsFactory = Callable[[contextlib.AsyncExitStack, PartsContext], Awaitable[Parts]]
