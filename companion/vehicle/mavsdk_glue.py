"""MAVSDK's loose ends for the vehicle link: logging, results, STATUSTEXT, TIMESYNC, PX4's hover thrust."""

from __future__ import annotations

import asyncio
import json
import logging
from typing import Any

from mavsdk import LogLevel
from mavsdk.asyncio import MavsdkError
from mavsdk.asyncio.plugins.mavlink_direct import MavlinkDirectError
from mavsdk.plugins.server_utility import StatusTextType

from companion.kernel import compat
from companion.kernel.clock import Clock
from companion.kernel.flight import Severity
from companion.vehicle.boottime import TIMESYNC_PERIOD_S

mavsdk_log = logging.getLogger("companion.vehicle.mavsdk")
log = logging.getLogger("companion.vehicle")

_MAVSDK_LEVEL = {
    LogLevel.DEBUG: logging.DEBUG,
    LogLevel.INFO: logging.INFO,
    LogLevel.WARN: logging.WARNING,
    LogLevel.ERROR: logging.ERROR,
}
STATUSTEXT_SEVERITY = {
    Severity.EMERGENCY: StatusTextType.EMERGENCY,
    Severity.ALERT: StatusTextType.ALERT,
    Severity.CRITICAL: StatusTextType.CRITICAL,
    Severity.ERROR: StatusTextType.ERROR,
    Severity.WARNING: StatusTextType.WARNING,
    Severity.NOTICE: StatusTextType.NOTICE,
    Severity.INFO: StatusTextType.INFO,
    Severity.DEBUG: StatusTextType.DEBUG,
}


def route_mavsdk_log(level: Any, message: str, file: str | None, line: int) -> bool:
    """MAVSDK log callback (runs on MAVSDK's threads): to Python logging, and nothing to stdout."""
    del file, line
    mavsdk_log.log(_MAVSDK_LEVEL.get(level, logging.INFO), "%s", message)
    return True


def settle(fut: asyncio.Future[Any], result: Any) -> None:
    """Set ``fut``'s result unless it is done (a late callback after a timeout)."""
    if not fut.done():
        fut.set_result(result)


def result_name(exc: MavsdkError) -> str:
    """The MAVSDK result's name in ``exc`` (DENIED, TIMEOUT...), else its text."""
    result = getattr(exc, "result", None)
    return getattr(result, "name", None) or str(exc)


async def request_timesync(direct: Any, clock: Clock) -> None:
    """Ask the autopilot for its boot time now and then (MAVLink TIMESYNC through MAVSDK's MavlinkDirect).

    The answers go to MavsdkTelemetry.on_timesync (see companion/vehicle/boottime.py).
    """
    from mavsdk.plugins.mavlink_direct import MavlinkMessage  # noqa: PLC0415 (mavsdk: heavy)

    while True:
        fields = json.dumps({"tc1": 0, "ts1": int(clock.now_s() * 1e9)})
        try:
            await direct.send_message(MavlinkMessage(message_name="TIMESYNC", fields_json=fields))
        except MavlinkDirectError as exc:
            log.debug("vehicle link: TIMESYNC not sent: %s", exc)
        await asyncio.sleep(TIMESYNC_PERIOD_S)


async def read_hover_thrust(param: Any, timeout_s: float, telemetry: Any) -> None:
    """PX4's MPC_THR_HOVER into ``telemetry``, to start the attitude law's thrust from; absent is fine."""
    try:
        async with compat.timeout(timeout_s):
            value = float(await param.get_param_float("MPC_THR_HOVER"))
    except (MavsdkError, TimeoutError) as exc:
        log.info("vehicle link: MPC_THR_HOVER not readable (%s); using the configured default", exc)
        return
    if 0.05 < value < 0.95:
        telemetry.update(hover_thrust_norm=value)
        log.info("vehicle link: hover thrust %.3f from MPC_THR_HOVER", value)
