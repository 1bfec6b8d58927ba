"""The wheel works outside the checkout: built here, installed elsewhere, run from another folder.

The wheel carries ``config/`` and ``models/`` (companion/kernel/shipped.py finds them), so ``sitl serve``
and ``companion sim`` need nothing from the repository. The installed package is put first on the path of a
folder outside the checkout, so nothing is imported from the source tree.
"""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from companion.lab.evaluation.procs import Child

pytestmark = [pytest.mark.lab, pytest.mark.slow, pytest.mark.timeout(600)]

REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    wheels = tmp_path_factory.mktemp("wheels")
    site = tmp_path_factory.mktemp("site")
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    subprocess.run(
        [*pip, "wheel", str(REPO), "--no-deps", "--no-build-isolation", "-w", str(wheels)],
        check=True,
        timeout=300,
        capture_output=True,
    )
    (wheel,) = wheels.glob("wingman-*.whl")
    subprocess.run([*pip, "install", "--no-deps", "--target", str(site), str(wheel)], check=True, timeout=300)
    return site


def _env(site: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(site), "WINGMAN_CONFIG": ""}


def test_the_installed_package_carries_its_config_and_weights(installed: Path, tmp_path: Path) -> None:
    code = (
        "import companion, companion.kernel.shipped as s; print(companion.__file__); print(s.project_root())"
    )
    r = subprocess.run(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        env=_env(installed),
        capture_output=True,
        text=True,
        check=True,
    )
    module, root = r.stdout.split()
    assert module.startswith(str(installed))
    assert Path(root) == installed / "companion" / "_shipped"
    assert (Path(root) / "models" / "leader_detector.onnx").is_file()


def test_sitl_serve_runs_from_the_wheel_outside_the_checkout(installed: Path, tmp_path: Path) -> None:
    env = {
        **_env(installed),
        "SITL_MAVLINK__API_LOCAL_PORT_BASE": "24780",
        "SITL_MAVLINK__API_REMOTE_PORT_BASE": "24740",
        "SITL_MAVLINK__GCS_LOCAL_PORT_BASE": "28770",
        "SITL_MAVLINK__GCS_REMOTE_PORT": "24750",
    }
    sim = Child([sys.executable, "-m", "sitl", "serve", "--no-camera", "--scenario", "straight"], env,
                tmp_path / "sitl.log", cwd=tmp_path)  # fmt: skip
    sim.start()
    try:
        deadline = time.monotonic() + 120
        while "running at" not in sim.log() and sim.running and time.monotonic() < deadline:
            time.sleep(0.2)
        assert "running at 1x real time (scenario straight" in sim.log(), sim.tail()
    finally:
        asyncio.run(sim.stop(20.0))


def test_companion_sim_runs_from_the_wheel_outside_the_checkout(installed: Path, tmp_path: Path) -> None:
    r = subprocess.run(
        [sys.executable, "-m", "companion", "sim", "--scenario", "straight", "--harness", "lockstep",
         "--duration", "5", "--no-plots", "--out", str(tmp_path / "run")],
        cwd=tmp_path, env=_env(installed), capture_output=True, text=True, timeout=500, check=False,
    )  # fmt: skip
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    assert "sim: straight: completed" in r.stdout
    assert (tmp_path / "run" / "report.json").is_file()
