"""``companion run``: the service."""

from __future__ import annotations

import argparse
import asyncio
import os
import signal
import time
from typing import Any

from companion.commands._common import add_config_arg, load
from companion.config import Config
from companion.errors import CompanionError


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("run", help="run the follower service")
    add_config_arg(p)
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from companion.service.systemd import NotifyConfig
    from companion.telemetry.mqtt import MqttCredentials, load_mqtt_credentials

    cfg = load(args)
    # The edge: the only place that reads systemd's variables and the secret files.
    notify = NotifyConfig.from_environ(os.environ, os.getpid())
    creds = load_mqtt_credentials(cfg.mqtt) if cfg.mqtt.enabled else MqttCredentials()
    try:
        return asyncio.run(_serve(cfg, notify, creds))
    except BaseExceptionGroup as eg:
        raise _first_companion_error(eg) or eg from None


async def _serve(cfg: Config, notify: Any, creds: Any) -> int:
    from companion.app import FollowerService
    from companion.clock import MonotonicClock
    from companion.service.systemd import SystemdNotifier
    from companion.service.wiring import make_parts_factory

    clock = MonotonicClock()
    with SystemdNotifier(notify) as notifier:
        service = FollowerService(
            cfg,
            make_parts_factory(cfg, clock),
            clock=clock,
            wall_time_s=time.time,
            notifier=notifier,
            mqtt_credentials=creds,
        )
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, service.request_stop, sig.name)
        try:
            return await service.run()
        finally:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)


def _first_companion_error(eg: BaseExceptionGroup[Any]) -> CompanionError | None:
    """The first of our own errors inside a TaskGroup's group (the CLI maps it to an exit code)."""
    for exc in eg.exceptions:
        if isinstance(exc, CompanionError):
            return exc
        if isinstance(exc, BaseExceptionGroup):
            found = _first_companion_error(exc)
            if found is not None:
                return found
    return None
