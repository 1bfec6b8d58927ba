"""Progress of a campaign on one line: done/total, failures, what is running, elapsed time and ETA.

The ETA of the child processes' campaigns comes from the scenarios' lengths (:func:`eta_from_lengths`),
so a long scenario running does not make it climb; the Ray executor's counts runs.

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
    @property
    def lane(self) -> str: ...
    @property
    def started_s(self) -> float: ...
    @property
    def wall_s(self) -> float: ...


@dataclass(frozen=True, slots=True)
class RunPace:
    """One run as the ETA sees it: its lane, its scenario's length and how far it got (sim s), its wall s."""

    lane: str
    length_s: float
    t_s: float = 0.0
    wall_s: float = 0.0
    started: bool = False
    done: bool = False


#: Wall seconds per sim second assumed for a lane until one of its runs shows its own: the real path flies in
#: real time plus its start (the simulator, the service, the take-off's wait for GPS), lockstep runs faster.
PRIOR_WALL_PER_SIM_S = {"real": 1.15, "lockstep": 0.45}
#: A running run's own pace counts once it is this far through its scenario (its start is slower).
PACE_FROM_FRAC = 0.25


def eta_from_lengths(runs: Sequence[RunPace], jobs: int) -> float:
    """Seconds left: every run's unflown sim time at its lane's pace, the lanes one after the other.

    The real path runs one at a time, lockstep runs ``jobs`` at a time (the campaign's order). A lane's pace
    (wall s per sim s) is its finished runs' and its running runs' past :data:`PACE_FROM_FRAC`, else the
    prior: so the estimate follows the scenarios' lengths instead of counting runs of any length alike.
    """
    left_s = 0.0
    for lane in sorted({r.lane for r in runs}):
        mine = [r for r in runs if r.lane == lane]
        seen = [r for r in mine if r.done or (r.started and r.t_s >= PACE_FROM_FRAC * r.length_s > 0.0)]
        sim_s = sum(r.length_s if r.done else r.t_s for r in seen)
        wall_s = sum(r.wall_s for r in seen)
        pace = wall_s / sim_s if sim_s > 0.0 else PRIOR_WALL_PER_SIM_S.get(lane, 1.0)
        todo = [max(0.0, r.length_s - (r.t_s if r.started else 0.0)) for r in mine if not r.done]
        parallel = 1 if lane == "real" else max(1, min(jobs, len(todo)))
        left_s += pace * sum(todo) / parallel
    return left_s


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
    done: int,
    failed: int,
    total: int,
    running: Sequence[str],
    elapsed_s: float,
    *,
    label: str = "sim",
    left_s: float | None = None,
) -> str:
    """One progress line: ``sim: 3/8 done, 1 failed | <running> | 1:02, ETA 1:40``.

    ``left_s``: the ETA when the caller knows better (the runs' lengths) than the throughput in runs.
    """
    eta = eta_s(done, total, elapsed_s) if left_s is None else left_s
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
    jobs: int = 1
    t0_s: float = field(default_factory=time.monotonic)
    _line: StatusLine | None = None

    def show(self, children: Sequence[ChildProgress], force: bool = False) -> None:
        if self._line is None:
            self._line = StatusLine(self.out, self.tty)
        running = [
            f"{c.name} {c.t_s:.0f}/{c.end_s:.0f} s" if c.t_s > 0.0 else f"{c.name} starting"
            for c in children
            if c.proc is not None and not c.done
        ]
        done = sum(c.done for c in children)
        failed = sum(c.done and c.rc != 0 for c in children)
        now_s = time.monotonic()
        left_s = None
        if all(math.isfinite(c.end_s) for c in children):
            paces = [
                RunPace(
                    lane=c.lane,
                    length_s=c.end_s,
                    t_s=c.t_s,
                    wall_s=c.wall_s if c.done else now_s - c.started_s,
                    started=c.proc is not None,
                    done=c.done,
                )
                for c in children
            ]
            left_s = eta_from_lengths(paces, self.jobs)
        text = progress_text(done, failed, self.total, running, now_s - self.t0_s, left_s=left_s)
        self._line.write(text, force)

    def close(self) -> None:
        if self._line is not None:
            self._line.close()
