"""``supervise()``: restart a non-critical component with jittered exponential backoff.

Only non-critical parts (MQTT, metrics, optional sources) are supervised. A failure in the autopilot link
or the mission is not: it propagates, ends the TaskGroup, and PX4's offboard-loss failsafe takes over.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Awaitable, Callable

from companion.kernel import compat
from companion.kernel.backoff import Backoff
from companion.kernel.clock import Clock
from companion.service.health import HealthBoard

__all__ = ["Backoff", "describe", "supervise"]

log = logging.getLogger(__name__)


async def supervise(
    name: str,
    run: Callable[[], Awaitable[None]],
    health: HealthBoard,
    clock: Clock,
    backoff: Backoff,
    *,
    stable_after_s: float = 30.0,
    sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
) -> None:
    """Run ``run()`` until it returns; restart it with backoff whenever it raises.

    A run that lasted ``stable_after_s`` or more resets the backoff. ``CancelledError`` and
    non-``Exception`` errors (KeyboardInterrupt, SystemExit) propagate untouched.

    Args:
        name: component name on the health board (registered by the caller).
        run: a factory for one attempt (a fresh coroutine each time).
        health: where failures and restarts are reported.
        clock: measures how long an attempt lasted.
        backoff: delay policy between attempts.
        stable_after_s: an attempt this long counts as a success for the backoff.
        sleep: how to wait (injectable for tests).
    """
    while True:
        started_s = clock.now_s()
        try:
            await run()
        except Exception as exc:  # a supervised component may fail in any way; that is the point
            if clock.now_s() - started_s >= stable_after_s:
                backoff.reset()
            first_of_streak = backoff.attempt == 0
            delay_s = backoff.next_delay_s()
            what = describe(exc)
            health.fail(name, what)
            # The traceback once per streak of failures: enough to debug, not a log flood.
            log.warning(
                "%s failed (%s); restart %d in %.2f s",
                name,
                what,
                backoff.attempt,
                delay_s,
                exc_info=exc if first_of_streak else None,
            )
            await sleep(delay_s)
            health.restarted(name)
        else:
            log.info("%s finished", name)
            return


def describe(exc: BaseException) -> str:
    """``Type: message``, with the leaves of an exception group (a TaskGroup's) instead of the group."""
    if isinstance(exc, compat.BaseExceptionGroup):
        return "; ".join(describe(e) for e in exc.exceptions)
    return f"{type(exc).__name__}: {exc}"
