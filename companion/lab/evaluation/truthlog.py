"""The simulator's truth, recorded inside ``sitl serve`` to score the run later (never read by the service).

One row of float64 per sample, appended to a flat file: ``t_s``, then for the follower and the leader
``p_ned_m`` (3), ``v_ned_m_s`` (3), ``q_ned_body_wxyz`` (4); world NED frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any, BinaryIO, Self

import numpy as np
from numpy.typing import NDArray

COLUMNS = 21
F64 = NDArray[np.float64]


def truth_row(t_s: float, follower: Any, leader: Any) -> F64:
    """One row from two truth objects (anything with ``p_ned_m``, ``v_ned_m_s``, ``q_ned_body_wxyz``)."""
    return np.concatenate(
        [
            [t_s],
            follower.p_ned_m,
            follower.v_ned_m_s,
            follower.q_ned_body_wxyz,
            leader.p_ned_m,
            leader.v_ned_m_s,
            leader.q_ned_body_wxyz,
        ]
    ).astype(np.float64)


class TruthWriter:
    """Appends rows; flushes every ``flush_every`` rows so a killed run still leaves most of its truth."""

    def __init__(self, path: Path, flush_every: int = 50) -> None:
        self.path = path
        self.flush_every = flush_every
        self._file: BinaryIO | None = None
        self._n = 0

    def __enter__(self) -> Self:
        self._file = self.path.open("wb")
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        if self._file is not None:
            self._file.close()
            self._file = None

    def write(self, row: F64) -> None:
        assert self._file is not None  # noqa: S101 (inside the context)
        self._file.write(row.tobytes())
        self._n += 1
        if self._n % self.flush_every == 0:
            self._file.flush()


@dataclass(frozen=True, slots=True)
class TruthTrack:
    """A recorded truth file, with interpolation at any sim time inside it."""

    t_s: F64
    rows: F64

    @classmethod
    def read(cls, path: Path) -> TruthTrack:
        raw = np.fromfile(path, dtype=np.float64)
        rows = raw[: raw.size - raw.size % COLUMNS].reshape(-1, COLUMNS)
        return cls(rows[:, 0].copy(), rows)

    def __len__(self) -> int:
        return int(self.t_s.size)

    def at(self, t_s: float) -> F64:
        """The row at ``t_s``, linearly interpolated (quaternions renormalised); clamped at the ends."""
        i = int(np.searchsorted(self.t_s, t_s))
        if i <= 0:
            first: F64 = self.rows[0]
            return first
        if i >= self.t_s.size:
            last: F64 = self.rows[-1]
            return last
        t0, t1 = self.t_s[i - 1], self.t_s[i]
        a = (t_s - t0) / (t1 - t0) if t1 > t0 else 0.0
        row: F64 = (1.0 - a) * self.rows[i - 1] + a * self.rows[i]
        for q in (slice(7, 11), slice(17, 21)):
            row[q] /= np.linalg.norm(row[q])
        return row


def follower_of(row: F64) -> tuple[F64, F64, F64]:
    """(p, v, q) of the follower in a row."""
    return row[1:4], row[4:7], row[7:11]


def leader_of(row: F64) -> tuple[F64, F64, F64]:
    """(p, v, q) of the leader in a row."""
    return row[11:14], row[14:17], row[17:21]
