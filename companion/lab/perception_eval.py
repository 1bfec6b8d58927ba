"""Perception accuracy against ground truth: per-frame rows, RMSE by range bin, bearing RMSE. Pure.

Used by ``companion replay`` on recordings that carry ground truth (rendered sequences). The truth is
the leader's centre in the camera frame at the frame's stamp; the estimate is the tracker's output
expressed in the camera frame with the follower's attitude at that stamp, so the two compare directly.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.kernel.frames import Vec3
from companion.perception.types import Detection

#: Range bins (truth distance camera -> leader centre), m.
RANGE_BINS_M: tuple[tuple[float, float], ...] = (
    (0.0, 3.0),
    (3.0, 6.0),
    (6.0, 8.0),
    (8.0, 10.0),
    (10.0, 12.0),
    (12.0, math.inf),
)
#: The acceptance bands of the pose accuracy targets (m, by range).
BANDS_M: tuple[tuple[float, float], ...] = ((0.0, 6.0), (6.0, 12.0))


def angle_between_deg(a: Vec3, b: Vec3) -> float:
    """Angle between two directions, deg (numerically safe near 0)."""
    return math.degrees(math.atan2(float(np.linalg.norm(np.cross(a, b))), float(np.dot(a, b))))


@dataclass(frozen=True, slots=True)
class FrameError:
    """Errors of one evaluated frame (estimate usable and truth present)."""

    range_m: float
    err_m: float
    bearing_err_deg: float
    #: Error of the raw pose measurement accepted this frame, and of the paper's centre-patch depth.
    meas_err_m: float | None = None
    paper_err_m: float | None = None


def _json_safe(value: Any) -> Any:
    """``value`` with every NaN or infinity as None: JSON has no NaN (a reader's parser may refuse it)."""
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, dict):
        return {k: _json_safe(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_safe(v) for v in value]
    return value


def _cell(value: float, width: int) -> str:
    """A table cell: the value to 3 decimals, or ``-`` where there was nothing to compute."""
    return f"{value:>{width}.3f}" if math.isfinite(value) else f"{'-':>{width}}"


def _rmse(values: Sequence[float]) -> float:
    return math.sqrt(sum(v * v for v in values) / len(values)) if values else math.nan


@dataclass
class Summary:
    """Accuracy and coverage over a replay."""

    frames: int = 0
    #: Frames whose track was usable (confirmed or coasting), with or without ground truth.
    frames_tracked: int = 0
    #: Frames with a ground-truth record (a rendered recording's truth.jsonl line), the leader in view or not.
    frames_with_truth: int = 0
    #: Frames whose ground truth has the leader in view (a true box): errors can only be computed on these.
    frames_in_view: int = 0
    #: Frames with the leader in view and a usable track (the errors are over these).
    frames_usable: int = 0
    errors: list[FrameError] = field(default_factory=list)
    stage_ms: dict[str, list[float]] = field(default_factory=dict)
    #: Where the follower's attitude came from: "recording" (its attitude samples), "ground truth" (each
    #: frame's, a live simulator), "none" (the tracker assumed the follower level and facing north).
    attitude: str = "none"

    def add_timing(self, stage: str, ms: float) -> None:
        self.stage_ms.setdefault(stage, []).append(ms)

    def paper_n_in(self, lo_m: float, hi_m: float) -> int:
        """Frames in the bin where the paper's centre patch had any valid depth."""
        return sum(1 for e in self.errors if lo_m <= e.range_m < hi_m and e.paper_err_m is not None)

    def rmse_in(self, lo_m: float, hi_m: float) -> tuple[float, float, float, float, int]:
        """(position, bearing deg, raw-measurement, paper-method RMSE, n) over lo <= range < hi."""
        sel = [e for e in self.errors if lo_m <= e.range_m < hi_m]
        meas = [e.meas_err_m for e in sel if e.meas_err_m is not None]
        paper = [e.paper_err_m for e in sel if e.paper_err_m is not None]
        return (
            _rmse([e.err_m for e in sel]),
            _rmse([e.bearing_err_deg for e in sel]),
            _rmse(meas),
            _rmse(paper),
            len(sel),
        )

    def as_dict(self) -> dict[str, object]:
        """Machine-readable summary (JSON-able)."""

        def band(lo: float, hi: float) -> dict[str, object]:
            pos, brg, meas, paper, n = self.rmse_in(lo, hi)
            return {
                "range_m": [lo, hi if math.isfinite(hi) else None],
                "n": n,
                "rmse_m": pos,
                "bearing_rmse_deg": brg,
                "raw_rmse_m": meas,
                "paper_method_rmse_m": paper,
                "paper_method_n": self.paper_n_in(lo, hi),
            }

        pos, brg, _, _, n = self.rmse_in(0.0, math.inf)
        out: dict[str, object] = _json_safe(
            {
                "frames": self.frames,
                "frames_tracked": self.frames_tracked,
                "frames_with_truth": self.frames_with_truth,
                "frames_leader_in_view": self.frames_in_view,
                "frames_usable": self.frames_usable,
                "attitude": self.attitude,
                "coverage": self.frames_usable / self.frames_in_view if self.frames_in_view else None,
                "rmse_m": pos,
                "bearing_rmse_deg": brg,
                "bins": [band(lo, hi) for lo, hi in RANGE_BINS_M],
                "bands": [band(lo, hi) for lo, hi in BANDS_M],
                "stage_ms_p50": {k: float(np.percentile(v, 50)) for k, v in self.stage_ms.items() if v},
                "stage_ms_p95": {k: float(np.percentile(v, 95)) for k, v in self.stage_ms.items() if v},
                "n": n,
            }
        )
        return out

    def lines(self) -> list[str]:
        """A human-readable table."""
        out = [
            f"frames {self.frames}, tracked {self.frames_tracked} (confirmed or coasting), "
            f"with ground truth {self.frames_with_truth} (the leader in view in {self.frames_in_view}), "
            f"tracked with the leader in view {self.frames_usable}",
        ]
        if not self.frames_with_truth:
            out.append("no ground truth in this recording: estimates only, no errors to compute")
        elif not self.frames_in_view:
            out.append("the ground truth has the leader in view in no frame: no errors to compute")
        if self.attitude == "none":
            out.append(
                "no follower attitude (no telemetry, no ground truth): the tracker assumed the follower "
                "level and never turning, so its errors include the follower's turns and tilts"
            )
        else:
            out.append(f"follower attitude from the {self.attitude}")
        out += [
            "rmse: tracker output vs truth (camera frame); raw: this frame's pose measurement; paper: depth"
            " = median of a 5x5 patch at the box centre, unfiltered (paper n: frames where it had depth)",
            f"{'range m':>10} {'n':>6} {'rmse m':>8} {'bearing deg':>12} {'raw m':>8} {'paper m':>8}"
            f" {'paper n':>8}",
        ]
        for lo, hi in (*RANGE_BINS_M, *BANDS_M, (0.0, math.inf)):
            pos, brg, meas, paper, n = self.rmse_in(lo, hi)
            label = f"{lo:g}-{hi:g}" if math.isfinite(hi) else f">={lo:g}"
            out.append(
                f"{label:>10} {n:>6} {_cell(pos, 8)} {_cell(brg, 12)} {_cell(meas, 8)} {_cell(paper, 8)}"
                f" {self.paper_n_in(lo, hi):>8}"
            )
        for stage, ms in self.stage_ms.items():
            if ms:
                out.append(
                    f"{stage} ms: p50 {np.percentile(ms, 50):.3f}  p95 {np.percentile(ms, 95):.3f}"
                    f"  max {max(ms):.3f}"
                )
        return out


def paper_centre_depth_m(depth_m: np.ndarray, det: Detection, half_px: int = 2) -> float | None:
    """The paper's depth: median of the valid pixels in a (2h+1)^2 patch at the box centre, m."""
    u, v = det.center_px
    h, w = depth_m.shape
    x, y = round(u), round(v)
    patch = depth_m[
        max(0, y - half_px) : min(h, y + half_px + 1), max(0, x - half_px) : min(w, x + half_px + 1)
    ]
    valid = patch[patch > 0]
    return float(np.median(valid)) if valid.size else None
