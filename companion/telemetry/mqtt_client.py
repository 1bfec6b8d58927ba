"""aiomqtt's edges: a bounded inbound queue, cancellation-safe calls, and what counts as a lost connection."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
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
