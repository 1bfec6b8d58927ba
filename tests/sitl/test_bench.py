"""``sitl bench`` runs end to end (its figure is reported by the command, not asserted here)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[2]


def test_bench_writes_its_json(tmp_path: Path) -> None:
    out = tmp_path / "bench.json"
    r = subprocess.run(
        [sys.executable, "-m", "sitl", "bench", "--sim-s", "14", "--repeats", "1", "--json", str(out)],
        cwd=REPO,
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
    )
    assert r.returncode == 0, r.stderr
    data = json.loads(out.read_text())
    assert data["vehicles"] == 2
    assert data["rtf_median"] > 1.0
    assert data["stream_messages_per_sim_s"] > 300  # ~185 default stream messages/s per API link
    assert "real-time factor" in r.stdout
