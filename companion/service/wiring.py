"""Builds the real parts (vehicle link, mission runner, frame source, detector, tracker) for the service.

This is the only module of the service that imports the flight and perception packages; it adapts them
to :mod:`companion.service.ports`. Imports happen when the service starts, not at import time.
"""

from __future__ import annotations

import contextlib
import importlib

from companion.app import Parts, PartsFactory
from companion.clock import Clock
from companion.config import Config
from companion.errors import NotBuiltError
from companion.service.health_checks import CheckResult

#: The modules the service wires together, and which part of the project owns each.
REQUIRED = {
    "companion.vehicle.mavsdk_link": "flight",
    "companion.mission.runner": "flight",
    "companion.perception.detector": "detector",
    "companion.perception.pipeline": "perception",
    "companion.perception.sources": "render/perception",
}


def missing_parts() -> list[str]:
    """Required modules that are not importable yet, as ``module (owner)``."""
    missing = []
    for module, owner in REQUIRED.items():
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as exc:
            if exc.name is not None and module.startswith(exc.name):
                missing.append(f"{module} ({owner})")
            else:
                raise
    return missing


def make_parts_factory(cfg: Config, clock: Clock) -> PartsFactory:
    """The factory ``FollowerService`` calls to open the parts on its exit stack."""

    async def open_parts(stack: contextlib.AsyncExitStack) -> Parts:
        missing = missing_parts()
        if missing:
            raise NotBuiltError("run: not built yet: waiting on " + ", ".join(missing))
        raise NotBuiltError("run: not built yet: parts present but not wired")

    return open_parts


def autopilot_probe(cfg: Config, timeout_s: float) -> list[CheckResult]:
    """Standalone autopilot and GPS checks (no service running)."""
    why = "service not running; the standalone probe needs companion.vehicle.mavsdk_link (flight)"
    return [CheckResult("autopilot", False, why), CheckResult("gps", False, "unknown (no autopilot)")]
