"""Progress of a campaign on one line: done/total, failures, what is running, elapsed time and ETA.

:func:`progress_text` is the line both executors print (child processes, Ray tasks); :class:`StatusLine`
rewrites it in place on a terminal; :class:`ProgressLine` builds it from the child processes of
:func:`companion.lab.evaluation.campaign.run_many`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Protocol, TextIO


class ChildProgress(Protocol):
    """What the progress line reads of a child run."""

    @property
    def name(self) -> str: ...
    @property
    def proc(self) -> object | None: ...
    @property
    def t_s(self) -> float: ...
    @property
    def end_s(self) -> float: ...
    @property
    def done(self) -> bool: ...
    @property
    def rc(self) -> int | None: ...


def eta_s(done: int, total: int, elapsed_s: float) -> float | None:
    """Seconds left at the throughput so far (None before the first run ends)."""
    if done <= 0 or total <= done:
        return None if done <= 0 else 0.0
    return elapsed_s / done * (total - done)


def clock_text(seconds: float) -> str:
    """``m:ss`` (``h:mm:ss`` past an hour)."""
    whole = max(0, round(seconds))
    h, rest = divmod(whole, 3600)
    m, sec = divmod(rest, 60)
    return f"{h}:{m:02d}:{sec:02d}" if h else f"{m}:{sec:02d}"


def progress_text(
    done: int, failed: int, total: int, running: Sequence[str], elapsed_s: float, *, label: str = "sim"
) -> str:
    """One progress line: ``sim: 3/8 done, 1 failed | <running> | 1:02, ETA 1:40``."""
    eta = eta_s(done, total, elapsed_s)
    head = f"{label}: {done}/{total} done" + (f", {failed} failed" if failed else "")
    tail = clock_text(elapsed_s) + (f", ETA {clock_text(eta)}" if eta is not None and done < total else "")
    return f"{head} | {' | '.join(running) or '-'} | {tail}"


@dataclass(slots=True)
class StatusLine:
    """One line, rewritten in place on a terminal (new lines elsewhere, at most every 10 s)."""

    out: TextIO
    tty: bool = False
    _last_s: float = -math.inf
    _width: int = 0

    def write(self, text: str, force: bool = False) -> None:
        now = time.monotonic()
        if not self.tty and not force and now - self._last_s < 10.0:
            return
        self._last_s = now
        if self.tty:
            pad = max(0, self._width - len(text))
            self.out.write("\r" + text + " " * pad)
            self._width = len(text)
        else:
            self.out.write(text + "\n")
        self.out.flush()

    def close(self) -> None:
        if self.tty:
            self.out.write("\n")
            self.out.flush()


@dataclass(slots=True)
class ProgressLine:
    """The child processes' progress: done/total, failures, each running run's sim time, ETA."""

    out: TextIO
    total: int
    tty: bool = False
    t0_s: float = field(default_factory=time.monotonic)
    _line: StatusLine | None = None

    def show(self, children: Sequence[ChildProgress], force: bool = False) -> None:
        if self._line is None:
            self._line = StatusLine(self.out, self.tty)
        running = [
            f"{c.name} {c.t_s:.0f}/{c.end_s:.0f} s" if math.isfinite(c.end_s) else f"{c.name} starting"
            for c in children
            if c.proc is not None and not c.done
        ]
        done = sum(c.done for c in children)
        failed = sum(c.done and c.rc != 0 for c in children)
        text = progress_text(done, failed, self.total, running, time.monotonic() - self.t0_s)
        self._line.write(text, force)

    def close(self) -> None:
        if self._line is not None:
            self._line.close()
