"""Perception (pose + tracker) on frames from the simulator's camera model, against its ground truth.

Short and within the stereo range so it fits the test budget; the full 3-12 m figures come from
``python -m tests.render_sequences`` + ``companion replay`` (see that module).
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from companion.config import Config
from companion.lab.replay import make_detect, run_replay
from companion.perception.record import FolderRecorder
from tests.render_sequences import frames

pytestmark = pytest.mark.render


def test_rendered_weave_within_issue_bars(tmp_path: Path) -> None:
    out = tmp_path / "weave"
    with FolderRecorder(out) as rec:
        for frame in frames("weave", 1.0, seed=5):  # 3.0 -> 3.1 m ahead, weaving sideways
            rec.write(frame)
    cfg = Config()
    summary = asyncio.run(run_replay(cfg, f"file:{out}", make_detect("truth", cfg, jitter_px=1.0, seed=0)))
    d = summary.as_dict()
    assert d["frames"] == 30
    assert d["coverage"] > 0.9  # all but the first frames, before confirmation
    band = d["bands"][0]
    assert band["n"] > 25
    assert band["rmse_m"] < 0.10
    assert band["bearing_rmse_deg"] < 0.5
    assert band["rmse_m"] < band["paper_method_rmse_m"]
