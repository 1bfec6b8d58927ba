"""``Latest[T]``: a one-slot mailbox where writers overwrite and readers wait for something newer.

Used for frames, estimates and setpoints: stale data is dropped (and counted), never queued without bound.
"""

from __future__ import annotations

import asyncio
from typing import Generic, TypeVar

T = TypeVar("T")


class MailboxClosedError(Exception):
    """The writer closed the mailbox (e.g. a recording ended); no newer value will come."""


class Latest(Generic[T]):
    """A latest-value mailbox.

    ``put()`` never blocks and replaces the value. One consumer uses :meth:`take` (each value at most
    once; values overwritten before it took them count as ``dropped``). Any number of observers use
    :meth:`peek` or :meth:`wait_newer` with the sequence number they last saw.
    """

    def __init__(self) -> None:
        self._value: T | None = None
        self._seq = 0
        self._taken_seq = 0
        self._dropped = 0
        self._closed = False
        self._waiters: set[asyncio.Future[None]] = set()

    @property
    def seq(self) -> int:
        """Number of values put so far (0: none yet)."""
        return self._seq

    @property
    def dropped(self) -> int:
        """Values overwritten before the consumer took them."""
        return self._dropped

    @property
    def closed(self) -> bool:
        return self._closed

    def put(self, value: T) -> None:
        """Replace the value and wake every waiter."""
        if self._closed:
            raise MailboxClosedError("put() on a closed mailbox")
        if self._seq > self._taken_seq:
            self._dropped += 1
        self._value = value
        self._seq += 1
        self._wake()

    def close(self) -> None:
        """No more values: waiters (now and later) raise :class:`MailboxClosedError`."""
        self._closed = True
        self._wake()

    def peek(self) -> T | None:
        """The newest value, or None before the first put."""
        return self._value

    async def take(self) -> T:
        """Wait for a value the consumer has not taken yet and take it."""
        while self._seq <= self._taken_seq:
            if self._closed:
                raise MailboxClosedError("mailbox closed")
            await self._wait()
        self._taken_seq = self._seq
        assert self._value is not None  # noqa: S101 (seq > 0 implies a value)
        return self._value

    async def wait_newer(self, after_seq: int) -> tuple[int, T]:
        """Wait until a value newer than ``after_seq`` exists; return it with its sequence number."""
        while self._seq <= after_seq:
            if self._closed:
                raise MailboxClosedError("mailbox closed")
            await self._wait()
        assert self._value is not None  # noqa: S101
        return self._seq, self._value

    async def _wait(self) -> None:
        fut: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._waiters.add(fut)
        try:
            await fut
        finally:
            self._waiters.discard(fut)

    def _wake(self) -> None:
        for fut in self._waiters:
            if not fut.done():
                fut.set_result(None)
        self._waiters.clear()
