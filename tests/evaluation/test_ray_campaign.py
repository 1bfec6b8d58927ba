"""``companion sim --seeds --executor ray`` on a real Ray on 127.0.0.1, through the CLI as a user runs it.

Each test's CLI starts its own single-node Ray (no ``--ray-address``), on the loopback address, with two
CPUs. The runs are short (``straight``, a 2-s formation window, ground-truth boxes) so that the three tests
fit in about two minutes on two busy cores; the figures checked are the lockstep harness's, which are the
same for a seed whichever process flies it.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SEEDS = "1-2"
#: Report keys measured on the wall clock (the rest is a function of the seed).
WALL_KEYS = {"wall_s", "run_wall_s", "perception_latency_ms", "detector_compute_ms", "scenario_file"}

pytestmark = [pytest.mark.render, pytest.mark.slow, pytest.mark.ray]


def _cmd(out: Path, *extra: str, seeds: str = SEEDS) -> list[str]:
    return [sys.executable, "-m", "companion", "sim", "--scenario", "straight", "--seeds", seeds,
            "--duration", "2", "--detector", "truth", "--jobs", "2", "--out", str(out), *extra]  # fmt: skip


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO), "RAY_USAGE_STATS_ENABLED": "0"}


def _run(cmd: list[str], timeout_s: float) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        cmd, cwd=REPO, env=_env(), capture_output=True, text=True, timeout=timeout_s, check=False
    )


def _figures(run_dir: Path) -> dict[str, object]:
    report = json.loads((run_dir / "report.json").read_text())
    return {k: v for k, v in report.items() if k not in WALL_KEYS}


@pytest.fixture(scope="module")
def local_campaign(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The same seeds through today's process pool: the reference figures."""
    out = tmp_path_factory.mktemp("local")
    proc = _run(_cmd(out), 180)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return out


@pytest.mark.timeout(300)
def test_ray_campaign_gives_the_local_pools_figures(local_campaign: Path, tmp_path: Path) -> None:
    out = tmp_path / "ray"
    proc = _run(_cmd(out, "--executor", "ray"), 240)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "sim[ray]: 2/2 done" in proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    reference = json.loads((local_campaign / "summary.json").read_text())
    assert summary["executor"] == "ray"
    assert summary["failed"] == []
    assert summary["outcomes"]["completed"] == 2
    assert summary["runs_by_seed"] == reference["runs_by_seed"]
    for seed in ("seed-001", "seed-002"):
        assert _figures(out / seed) == _figures(local_campaign / seed)
        assert (out / seed / "flight_log.npz").stat().st_size > 1000


def _descendants(root: int) -> list[int]:
    children: dict[int, list[int]] = {}
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            ppid = int((entry / "stat").read_text().rsplit(")", 1)[1].split()[1])
        except (OSError, IndexError, ValueError):
            continue
        children.setdefault(ppid, []).append(int(entry.name))
    out: list[int] = []
    todo = [root]
    while todo:
        pid = todo.pop()
        for c in children.get(pid, []):
            out.append(c)
            todo.append(c)
    return out


def _cmdline(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
    except OSError:
        return ""


@pytest.mark.timeout(480)
def test_a_killed_worker_is_retried_and_a_resumed_campaign_reports_every_seed(
    local_campaign: Path, tmp_path: Path
) -> None:
    """Seed 1 is kept from an earlier campaign (``--resume``); seed 2's worker is killed mid-run."""
    out = tmp_path / "ray"
    out.mkdir()
    shutil.copytree(local_campaign / "seed-001", out / "seed-001")
    kept_mtime_ns = (out / "seed-001" / "report.json").stat().st_mtime_ns
    proc = subprocess.Popen(
        _cmd(out, "--executor", "ray", "--resume"),
        cwd=REPO,
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
    )
    killed: int | None = None
    try:
        # Ray's start on two busy cores can take minutes: watch for as long as the campaign runs.
        deadline = time.monotonic() + 300.0
        first_seen: dict[int, float] = {}
        while killed is None and time.monotonic() < deadline and proc.poll() is None:
            for pid in _descendants(proc.pid):
                if _cmdline(pid).startswith("ray::run_seed"):
                    first_seen.setdefault(pid, time.monotonic())
                    if time.monotonic() - first_seen[pid] > 3.0:  # well into the run, not yet done
                        os.kill(pid, signal.SIGKILL)
                        killed = pid
                        break
            time.sleep(0.2)
        stdout, stderr = proc.communicate(timeout=150)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert killed is not None, "no Ray worker was seen running a seed"
    assert proc.returncode == 0, stdout[-3000:] + stderr[-3000:]
    assert "1 of 2 seeds already have a report" in stdout
    summary = json.loads((out / "summary.json").read_text())
    assert summary["failed"] == []
    assert summary["resumed"] == 1
    assert sorted(summary["runs_by_seed"]) == ["seed-001", "seed-002"]
    assert (out / "seed-001" / "report.json").stat().st_mtime_ns == kept_mtime_ns
    # The retried run is the same flight as the undisturbed one.
    assert _figures(out / "seed-002") == _figures(local_campaign / "seed-002")


@pytest.mark.timeout(240)
def test_a_run_that_fails_every_attempt_is_reported_with_its_error(tmp_path: Path) -> None:
    out = tmp_path / "ray"
    # A config value the service refuses (not a number): every attempt fails on the worker, as a run that
    # raises would.
    proc = _run(_cmd(out, "--executor", "ray", "--set", "formation.kp_xy=fast", seeds="3"), 200)
    assert proc.returncode == 1, proc.stdout[-3000:] + proc.stderr[-3000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["runs"] == 0
    assert len(summary["failed"]) == 1
    assert summary["failed"][0].startswith("seed-003: ConfigError: ")
    assert "kp_xy" in summary["failed"][0]
    assert "Runs without a report: seed-003: ConfigError" in (out / "summary.md").read_text()
    assert "ConfigError" in (out / "seed-003" / "sim.log").read_text()
