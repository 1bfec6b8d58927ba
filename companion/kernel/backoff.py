"""Retry delays for anything that reconnects (the MQTT client, supervised parts): exponential with jitter."""

from __future__ import annotations

import random


class Backoff:
    """Exponential backoff with "equal jitter": delay n is uniform in [d/2, d], d = min(max, base * 2^n).

    Half the delay is jitter so that several clients restarted together (e.g. after a broker restart) do
    not reconnect in lockstep; the other half keeps a floor so a failing peer is never hammered.
    """

    def __init__(self, initial_s: float, max_s: float, rng: random.Random) -> None:
        if not 0 < initial_s <= max_s:
            raise ValueError(f"need 0 < initial_s <= max_s (got {initial_s}, {max_s})")
        self.initial_s = initial_s
        self.max_s = max_s
        self._rng = rng
        self._attempt = 0

    @property
    def attempt(self) -> int:
        return self._attempt

    def next_delay_s(self) -> float:
        """The delay before the next attempt; grows until ``max_s``."""
        cap_s = min(self.max_s, self.initial_s * 2.0 ** min(self._attempt, 30))
        self._attempt += 1
        return self._rng.uniform(cap_s / 2.0, cap_s)

    def reset(self) -> None:
        """Back to the initial delay (after a success)."""
        self._attempt = 0
