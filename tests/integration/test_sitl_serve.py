"""``sitl serve`` as a process: banner, in-process components, clean stop on SIGINT/SIGTERM."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import pytest

from tests.integration.sitl_process import REPO, sitl_serve

pytestmark = [pytest.mark.sitl, pytest.mark.timeout(120)]


def test_banner_components_and_ctrl_c() -> None:
    with sitl_serve(speed=2.0, host="tests.integration.sitl_component") as sim:
        deadline = time.monotonic() + 20
        while sum("component:" in line for line in sim.output) < 6 and time.monotonic() < deadline:
            time.sleep(0.1)
        banner = [line for line in sim.output if line.startswith("sitl: ") and "system" in line]
        assert len(banner) == 2
        assert f"MAVSDK: udpin://0.0.0.0:{sim.ports.api_remote}" in banner[0]
        assert f"MAVSDK: udpin://0.0.0.0:{sim.ports.api_remote + 1}" in banner[1]
        seen = [line for line in sim.output if line.startswith("component:")]
        assert len(seen) == 6

        # The component sees ground truth at sim time: leader spawned at 8 m north, both on the ground.
        def parse(line: str) -> dict[str, str]:
            # "component: t=1.000 leader n=8.00 e=0.00 d=-0.094"
            return dict(kv.split("=") for kv in line.split()[1:] if "=" in kv) | {"who": line.split()[2]}

        rows = [parse(line) for line in seen]
        leader = next(r for r in rows if r["who"] == "leader")
        follower = next(r for r in rows if r["who"] == "follower")
        assert float(leader["n"]) == pytest.approx(8.0, abs=0.01)
        assert float(follower["n"]) == pytest.approx(0.0, abs=0.01)
        assert float(follower["d"]) == pytest.approx(-0.09, abs=0.01)
        assert seen[0].startswith("component: t=1.0")
        sim.proc.send_signal(signal.SIGINT)
        assert sim.proc.wait(timeout=15) == 0
        time.sleep(0.2)
    assert "sitl: stopped" in sim.output
    assert not any("Traceback" in line for line in sim.output)


def test_a_taken_port_is_a_clear_error() -> None:
    with sitl_serve(speed=1.0) as sim:
        env_ports = sim.ports.env()
        env = {**os.environ, **env_ports, "PYTHONPATH": str(REPO)}
        r = subprocess.run(
            [sys.executable, "-m", "sitl", "serve", "--no-camera"],
            cwd=REPO,
            env=env,
            capture_output=True,
            text=True,
            timeout=60,
            check=False,
        )
    assert r.returncode == 3
    assert "cannot bind UDP" in r.stderr
    assert "Traceback" not in r.stderr
