"""Ages of inputs that do not count the reader's own stalls.

A loop that judges its inputs stale by ``now - stamp`` mistakes its own pause (a loaded companion computer,
a garbage collection, a stopped process) for the world going quiet: the messages that arrived meanwhile
wait in socket buffers and callback queues and are read a moment after the loop resumes. So a loop that
notices it was not ticked for ``stall_gap_s`` counts every input as fresh from the moment it resumed; an
input that stays silent for its whole timeout after that is stale, as before. A real loss that falls
inside a stall is found late by at most the stall's length.
"""

from __future__ import annotations

import math


class StallAwareAge:
    """The age of a stamped input with the reader's stalls left out, s.

    Pure: call :meth:`tick` with the loop's time once per iteration, then :meth:`age_s` for each input.

    Args:
        stall_gap_s: a gap between two ticks longer than this is a stall of the reader, s.
    """

    def __init__(self, stall_gap_s: float) -> None:
        if not stall_gap_s > 0.0:
            raise ValueError("stall_gap_s must be > 0")
        self.stall_gap_s = stall_gap_s
        self._prev_tick_s = math.nan
        #: When the reader last resumed after a stall (-inf: never stalled), s.
        self.resumed_s = -math.inf
        #: Stalls seen, and the longest one, s.
        self.stalls = 0
        self.longest_stall_s = 0.0

    def tick(self, now_s: float) -> None:
        """One iteration of the reading loop at ``now_s``."""
        gap_s = now_s - self._prev_tick_s
        if gap_s > self.stall_gap_s:  # False for the first tick (NaN)
            self.resumed_s = now_s
            self.stalls += 1
            self.longest_stall_s = max(self.longest_stall_s, gap_s)
        self._prev_tick_s = now_s

    def age_s(self, stamp_s: float, now_s: float) -> float:
        """``now_s - stamp_s``, counted from the last resume at most."""
        return now_s - max(stamp_s, self.resumed_s)
