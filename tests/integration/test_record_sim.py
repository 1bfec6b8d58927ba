"""``companion record`` from the simulator's live camera: every frame it keeps, and a count of the rest.

A live source drops what is not read in time; the recorder reads in one task and writes behind a queue, and
says at the end how many frames the source skipped (gaps in its frame numbers).
"""

from __future__ import annotations

import csv
import itertools
import os
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.integration.sitl_process import REPO, sitl_serve

pytestmark = [pytest.mark.sitl, pytest.mark.render, pytest.mark.slow, pytest.mark.timeout(300)]


def test_recording_150_live_frames_keeps_them_all_or_counts_the_rest(tmp_path: Path) -> None:
    cam = tmp_path / "cam.sock"
    out = tmp_path / "rec"
    with sitl_serve(speed=1.0, camera=cam) as sim:
        deadline = time.monotonic() + 60
        while not cam.exists() and time.monotonic() < deadline:
            time.sleep(0.2)
        assert cam.exists(), "\n".join(sim.output[-20:])
        env = {**os.environ, "PYTHONPATH": str(REPO), "WINGMAN_CAMERA__PATH": str(cam)}
        r = subprocess.run(
            [sys.executable, "-m", "companion", "record", "--source", "sim", "--frames", "150",
             "--out", str(out)],
            cwd=REPO, env=env, capture_output=True, text=True, timeout=180, check=False,
        )  # fmt: skip
    assert r.returncode == 0, r.stderr[-3000:]
    line = r.stderr.strip().splitlines()[-1]
    print(line)
    with (out / "frames.csv").open(newline="") as f:
        seqs = [int(row["seq"]) for row in csv.DictReader(f)]
    assert len(seqs) == 150
    gaps = sum(b - a - 1 for a, b in itertools.pairwise(seqs) if b > a + 1)
    if gaps == 0:
        assert line == f"recorded 150 frames to {out}, none skipped"
    else:
        m = re.fullmatch(rf"recorded 150 frames to {re.escape(str(out))}; the source skipped (\d+) .*", line)
        assert m is not None, line
        assert int(m.group(1)) == gaps
