"""MAVSDK's loose ends for the vehicle link: its log into Python logging, results, STATUSTEXT severities."""

from __future__ import annotations

import asyncio
import logging
from typing import Any

from mavsdk import LogLevel
from mavsdk.asyncio import MavsdkError
from mavsdk.plugins.server_utility import StatusTextType

from companion.kernel.flight import Severity

mavsdk_log = logging.getLogger("companion.vehicle.mavsdk")

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
