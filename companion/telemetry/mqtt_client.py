"""aiomqtt's edges: a bounded inbound queue, cancellation-safe calls, and what counts as a lost connection."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Sequence
from typing import TypeVar

import aiomqtt

from companion.kernel import compat

T = TypeVar("T")

#: Inbound messages waiting for the receive loop; beyond it they are dropped and counted (a flood).
INBOUND_QUEUE = 1000


def bounded_queue(
    max_bytes: int, on_drop: Callable[[str, int, str], None]
) -> type[asyncio.Queue[aiomqtt.Message]]:
    """The inbound queue for aiomqtt, refusing what must never wait in memory: oversized payloads, floods.

    aiomqtt hands every message to ``put_nowait`` as it arrives; dropping here (instead of raising
    QueueFull, which aiomqtt logs once per message) keeps a flood out of the log and the memory bounded.
    """

    class BoundedQueue(asyncio.Queue[aiomqtt.Message]):
        def put_nowait(self, item: aiomqtt.Message) -> None:
            payload = item.payload
            size = len(payload) if isinstance(payload, bytes | bytearray | str) else 0
            if size > max_bytes:
                on_drop(str(item.topic), size, "too_large")
            elif self.full():
                on_drop(str(item.topic), size, "queue_full")
            else:
                super().put_nowait(item)

    return BoundedQueue


#: asyncio.TimeoutError is TimeoutError from Python 3.11 on; on 3.10 aiomqtt's wait_for raises the former.
CONNECTION_ERRORS = (aiomqtt.MqttError, OSError, TimeoutError, asyncio.TimeoutError)


def connection_error(raised: BaseException) -> BaseException:
    """The connection error in ``raised`` (alone or in a task group's group); anything else re-raised."""
    if not isinstance(raised, compat.BaseExceptionGroup):
        return raised
    match, rest = raised.split(CONNECTION_ERRORS)
    if rest is not None or match is None:
        raise raised
    first: BaseException = match.exceptions[0]
    while isinstance(first, compat.BaseExceptionGroup):
        first = first.exceptions[0]
    return first


#: How long a cancelled task has to end before it is cancelled again: longer than any cleanup of the
#: session's own tasks (a cancellation during cleanup would cut it short), short enough for a stop.
RECANCEL_PERIOD_S = 0.5


async def cancel_and_wait(tasks: Sequence[asyncio.Task[object]]) -> None:
    """Cancel ``tasks`` and return once every one has ended, cancelling again any that swallowed it.

    On Python 3.10 a task not made by a TaskGroup has no ``cancelling()``, so :func:`call` cannot see a
    cancellation that aiomqtt's ``asyncio.wait_for`` swallowed (CPython gh-86296): the task goes back to
    waiting for work and a plain ``gather`` after ``cancel()`` waits for ever. That ended the session loop
    for good: no reconnect, and no stop. The next cancellation reaches the task wherever it waits.
    A cancellation of the caller meanwhile is kept and raised once the tasks have ended.
    """
    cancelled = False
    pending = [t for t in tasks if not t.done()]
    for task in pending:
        task.cancel()
    while pending:
        try:
            await asyncio.wait(pending, timeout=RECANCEL_PERIOD_S)
        except asyncio.CancelledError:
            cancelled = True  # the tasks still get their whole period: wait again
            pending = [t for t in pending if not t.done()]
            continue
        pending = [t for t in pending if not t.done()]
        for task in pending:
            task.cancel()
    for task in tasks:
        if not task.cancelled():
            task.exception()  # retrieved: the caller reads the one that matters from its own ``done``
    if cancelled:
        raise asyncio.CancelledError


async def call(awaitable: Awaitable[T]) -> T:
    """Await an aiomqtt call without losing a cancellation.

    aiomqtt 2.5 waits with ``asyncio.wait_for``, which on Python 3.11 can swallow a cancellation that
    arrives as the awaited operation completes (CPython gh-86296, fixed in 3.12). The task then keeps
    running with its cancellation pending and a TaskGroup waiting on it hangs: re-raise it here. (On 3.10
    only the backport's TaskGroup tasks count cancellations; others have no ``cancelling()``.)
    """
    result = await awaitable
    cancelling = getattr(asyncio.current_task(), "cancelling", None)
    if cancelling is not None and cancelling():
        raise asyncio.CancelledError
    return result
