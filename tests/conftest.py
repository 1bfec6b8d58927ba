"""Shared test fixtures."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest
from hypothesis import HealthCheck, settings

REPO = Path(__file__).resolve().parents[1]

# Hypothesis's wall-clock checks (a per-example deadline, slow input generation) fail on a busy machine for
# reasons the code under test does not control: off for every property test; the properties stay.
settings.register_profile("wingman", deadline=None, suppress_health_check=[HealthCheck.too_slow])
settings.load_profile("wingman")

if sys.version_info < (3, 11):  # noqa: UP036 (the service side also runs on 3.10)
    # The flight service runs on Python 3.10 (JetPack 6); the simulator and the lab tools (training,
    # evaluation, companion sim) need 3.11, so their tests are not collected there.
    collect_ignore_glob = [
        "evaluation/*",
        "packaging/*",
        "flight/*",
        "integration/*",
        "render/*",
        "sitl/*",
        "unit/detector/*",
        "unit/test_detector*",
        "unit/test_campaign_*.py",
        "unit/test_camera_timing.py",
        "unit/test_dataset_profiles.py",
        "unit/test_procs.py",
        "unit/test_sim_command.py",
        "unit/test_tilt_probe.py",
        "service/test_safety_sitl.py",
        "service/test_service_sitl.py",
        "service/test_simulator_page.py",
    ]


@pytest.fixture
def repo_root() -> Path:
    return REPO
