"""What waits to be published: a bounded FIFO that drops the oldest and loses nothing on a failed send."""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class Outgoing:
    """One message waiting to be published."""

    topic: str
    payload: bytes
    qos: int
    retain: bool


class Outbox:
    """A bounded FIFO: ``push`` drops the oldest when full; ``peek``/``ack`` lose nothing on a failed send."""

    def __init__(self, max_messages: int) -> None:
        if max_messages < 1:
            raise ValueError("max_messages must be >= 1")
        self.max_messages = max_messages
        self._items: deque[Outgoing] = deque()
        self.dropped = 0
        self.pushed = 0

    def __len__(self) -> int:
        return len(self._items)

    def push(self, item: Outgoing) -> None:
        if len(self._items) >= self.max_messages:
            self._items.popleft()
            self.dropped += 1
        self._items.append(item)
        self.pushed += 1

    def peek(self) -> Outgoing | None:
        return self._items[0] if self._items else None

    def ack(self, item: Outgoing) -> None:
        """Remove ``item`` once published (unless it was already dropped to make room)."""
        if self._items and self._items[0] is item:
            self._items.popleft()
