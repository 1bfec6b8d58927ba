"""``companion run``: the service."""

from __future__ import annotations

import argparse
import asyncio
import faulthandler
import logging
import os
import signal
import sys
import threading
import time
from typing import Any

from companion.commands._common import add_config_arg, load
from companion.config import Config
from companion.kernel import compat
from companion.kernel.errors import first_companion_error

log = logging.getLogger("companion")

#: After the service has finished, what is left (closing the link, joining threads) gets this long.
TEARDOWN_GRACE_S = 15.0


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("run", help="run the follower service")
    add_config_arg(p)
    p.set_defaults(handler=_run)


def _run(args: argparse.Namespace) -> int:
    from companion.config import resolve_state_dir
    from companion.service.systemd import NotifyConfig
    from companion.telemetry.mqtt_setup import (
        MqttCredentials,
        load_command_marks,
        load_mqtt_credentials,
    )

    cfg = load(args)
    # The edge: the only place that reads systemd's variables, the secret files and the state folder.
    notify = NotifyConfig.from_environ(os.environ, os.getpid())
    state_dir = resolve_state_dir(cfg.service.state_dir, os.environ)
    cfg = cfg.model_copy(update={"service": cfg.service.model_copy(update={"state_dir": str(state_dir)})})
    creds = load_mqtt_credentials(cfg.mqtt) if cfg.mqtt.enabled else MqttCredentials()
    marks = load_command_marks(state_dir) if cfg.mqtt.enabled and cfg.mqtt.command_topic else None
    guard = ExitGuard()
    try:
        code = asyncio.run(_serve(cfg, notify, creds, marks, guard))
    except compat.BaseExceptionGroup as eg:
        guard.arm(TEARDOWN_GRACE_S, 1, "teardown after an error")
        raise first_companion_error(eg) or eg from None
    guard.arm(TEARDOWN_GRACE_S, code, "teardown")
    return code


async def _serve(cfg: Config, notify: Any, creds: Any, marks: Any, guard: ExitGuard) -> int:
    from companion.app import FollowerService
    from companion.kernel.clock import MonotonicClock
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
            command_marks=marks,
            freeze_heap=True,
        )
        loop = asyncio.get_running_loop()

        def on_signal(name: str) -> None:
            # The safe action is bounded by shutdown_timeout_s in the service; this bounds the process.
            guard.arm(cfg.service.shutdown_timeout_s + TEARDOWN_GRACE_S, 1, f"{name}: shutdown")
            service.request_stop(name)

        for sig in (signal.SIGTERM, signal.SIGINT):
            loop.add_signal_handler(sig, on_signal, sig.name)
        try:
            return await service.run()
        finally:
            for sig in (signal.SIGTERM, signal.SIGINT):
                loop.remove_signal_handler(sig)


class ExitGuard:
    """Makes sure a process that has decided to exit does exit.

    A native library (MAVSDK) or a worker thread that never returns would otherwise keep the process
    alive after the service is done, until systemd's SIGKILL. Armed, a daemon thread waits; if the
    process is still there when the time is up, it dumps every thread's stack to stderr (the journal)
    for the bug report, then exits with the code the service had decided.
    """

    def __init__(self) -> None:
        self._timer: threading.Timer | None = None

    def arm(self, timeout_s: float, code: int, what: str) -> None:
        if self._timer is not None:
            return
        self._timer = threading.Timer(timeout_s, self._fire, args=(timeout_s, code, what))
        self._timer.daemon = True
        self._timer.name = "companion-exit-guard"
        self._timer.start()

    @staticmethod
    def _fire(timeout_s: float, code: int, what: str) -> None:
        log.critical(
            "%s did not finish within %.0f s; thread stacks follow; exiting %d", what, timeout_s, code
        )
        faulthandler.dump_traceback(file=sys.stderr, all_threads=True)
        logging.shutdown()
        os._exit(code)
