from __future__ import annotations

import asyncio
import random
import socket
import sys
from pathlib import Path

import pytest

from companion.lab.evaluation.procs import Child, SimRunError, SitlPorts, udp_port_free


def test_a_picked_port_block_is_free_and_the_same_for_the_same_draw() -> None:
    ports = SitlPorts.pick(random.Random(3))
    assert all(udp_port_free(ports.base + k) for k in range(SitlPorts.SIZE))
    named = {ports.api_local, ports.api_remote, ports.follower_api, ports.gcs_local, ports.follower_gcs}
    named |= {ports.gcs_remote, ports.client, ports.truth}
    assert len(named) == 8
    assert max(named) < ports.base + SitlPorts.SIZE
    # A bound port is not free, so a block holding it is never picked.
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("0.0.0.0", ports.base + 2))  # noqa: S104
        assert not udp_port_free(ports.base + 2)
        assert SitlPorts.pick(random.Random(3)).base != ports.base


def test_a_child_is_waited_for_by_its_output_and_stopped_by_sigterm(tmp_path: Path) -> None:
    async def run() -> tuple[str, int | None, bool]:
        code = "import time; print('up and running', flush=True); time.sleep(60)"
        child = Child([sys.executable, "-c", code], {}, tmp_path / "child.log", cwd=tmp_path)
        child.start()
        await child.wait_for_output("running", 10.0)
        await child.stop(timeout_s=5.0)
        await child.stop()  # idempotent
        return child.log(), child.returncode, child.running

    log, rc, running = asyncio.run(run())
    assert "up and running" in log
    assert rc is None  # forgotten once stopped
    assert not running


def test_a_child_that_exits_before_it_is_ready_is_one_clear_error(tmp_path: Path) -> None:
    async def run() -> None:
        code = "import sys; print('bad config: no such file', flush=True); sys.exit(2)"
        child = Child([sys.executable, "-c", code], {}, tmp_path / "child.log", cwd=tmp_path)
        child.start()
        await child.wait_for_output("running at", 10.0)

    with pytest.raises(SimRunError, match="bad config: no such file"):
        asyncio.run(run())
