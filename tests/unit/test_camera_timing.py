"""The lockstep camera pipeline's timing and the timing profiles that set it."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.kernel.errors import ConfigError
from companion.lab.evaluation.camera_timing import CameraTiming
from companion.lab.evaluation.campaign import RunSpec, child_args, effective_scenario, read_timing_profile
from companion.lab.evaluation.setup import scenario_path
from sitl.world.scenario import TimingSpec

REPO = Path(__file__).resolve().parents[2]
REAL_PATH = REPO / "config" / "timing" / "real-path.toml"


def test_the_default_is_a_fixed_60_ms_and_draws_nothing() -> None:
    t = CameraTiming(TimingSpec(), seed=1)
    dues = [t.due_s(k / 15.0) for k in range(30)]
    assert all(d is not None and d == pytest.approx(k / 15.0 + 0.06) for k, d in enumerate(dues))
    assert t.dropped == 0


def test_drawn_timing_is_seeded_ordered_and_drops_the_asked_share() -> None:
    spec = TimingSpec(camera_latency_ms=40.0, camera_jitter_ms=15.0, frame_drop=0.05, detector_load_ms=10.0)
    captures = np.arange(20_000) / 15.0

    def fates(seed: int) -> list[float | None]:
        t = CameraTiming(spec, seed)
        return [t.due_s(c) for c in captures]

    a, b, c = fates(1), fates(1), fates(2)
    assert a == b
    assert a != c
    dropped = sum(d is None for d in a) / len(a)
    assert dropped == pytest.approx(0.05, abs=0.01)
    kept = [(cap, d) for cap, d in zip(captures, a, strict=True) if d is not None]
    dues = np.array([d for _, d in kept])
    assert np.all(np.diff(dues) >= 0.0)  # one pipeline: in capture order
    lat_ms = (dues - np.array([cap for cap, _ in kept])) * 1e3
    assert np.median(lat_ms) == pytest.approx(40.0 + 10.0 * np.log(2), abs=3.0)  # + the load's median
    assert lat_ms.min() >= 0.0


def test_the_real_path_profile_merges_into_every_paper_scenario() -> None:
    for name in ("straight", "circle", "gps-loss", "visibility"):
        sc = effective_scenario(scenario_path(name), None, REAL_PATH)
        assert sc.timing.camera_latency_ms == 40.0
        assert sc.timing.frame_drop == 0.05
        assert sc.faults("follower").link.latency_ms == 12.0
        plain = effective_scenario(scenario_path(name), None)
        assert sc.faults("follower").gps == plain.faults("follower").gps  # the rest is the scenario's
        assert sc.leader == plain.leader


def test_a_profile_sets_only_timing_tables(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[wind]\nmean_speed_m_s = 9.0\n[vehicles.follower.gps]\nnoise_scale = 2.0\n")
    with pytest.raises(ConfigError) as e:
        read_timing_profile(bad)
    text = str(e.value)
    assert "wind: not a timing table" in text
    assert "vehicles.follower.gps: a profile sets only vehicles.follower.link" in text
    with pytest.raises(ConfigError, match="no such timing profile"):
        read_timing_profile(tmp_path / "missing.toml")
    wrong = tmp_path / "wrong.toml"
    wrong.write_text("[timing]\nframe_drop = 1.5\n")
    with pytest.raises(ConfigError, match="frame_drop"):
        effective_scenario(scenario_path("straight"), None, wrong)


def test_child_runs_get_the_profile(tmp_path: Path) -> None:
    spec = RunSpec("circle", 4, tmp_path / "c", harness="lockstep", timing=REAL_PATH)
    args = child_args(spec)
    assert args[args.index("--timing") + 1] == str(REAL_PATH)
