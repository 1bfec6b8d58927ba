"""docs/fly-in-the-simulator.md, run as written from a fresh clone.

Every fenced ``sh`` block of the page runs in order, in a clone of the committed repository: a block whose
first line says ``# terminal N (keeps running)`` starts a process that must stay up, every other line is a
command that must exit 0. Between them the test waits as a reader would: for the simulator and the
service to say they are ready, and for the follower to reach ``follow`` after ``start``. The page uses
the shipped defaults (UDP 14540/14541/14550, MQTT 1883, ``/run/wingman``), so the test skips when any of
them is taken on this machine.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import os
import re
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import pytest

from companion.lab.evaluation.procs import Child

pytestmark = [pytest.mark.sitl, pytest.mark.mqtt_broker, pytest.mark.slow, pytest.mark.timeout(420)]

REPO = Path(__file__).resolve().parents[2]
PAGE = REPO / "docs" / "fly-in-the-simulator.md"
_BLOCK = re.compile(r"```sh\n(.*?)```", re.DOTALL)
_TERMINAL = re.compile(r"#\s*terminal \d+ \(keeps running\)")
_ASSIGNMENT = re.compile(r"[A-Z_][A-Z0-9_]*=\S*")


def page_blocks(text: str) -> list[tuple[bool, list[str]]]:
    """(keeps running, command lines) for each ``sh`` block, comments dropped."""
    out = []
    for body in _BLOCK.findall(text):
        lines = [ln.strip() for ln in body.splitlines() if ln.strip()]
        background = bool(lines) and bool(_TERMINAL.fullmatch(lines[0]))
        out.append((background, [ln for ln in lines if not ln.startswith("#")]))
    return out


def test_the_page_has_the_whole_recipe() -> None:
    blocks = page_blocks(PAGE.read_text())
    background = [cmd for bg, cmds in blocks if bg for cmd in cmds]
    assert [c.split()[0].rsplit("/", 1)[-1] for c in background] == [
        "sitl",
        "mosquitto",
        "WINGMAN_MQTT__ENABLED=true",
        "mosquitto_sub",
    ]
    foreground = [cmd for bg, cmds in blocks if not bg for cmd in cmds]
    assert foreground[:2] == [".venv/bin/companion health --wait 60", ".venv/bin/companion start"]


def _udp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        try:
            s.bind(("0.0.0.0", port))  # noqa: S104 (the simulator binds all interfaces: so must the probe)
        except OSError:
            return False
    return True


def _tcp_free(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        try:
            s.bind(("127.0.0.1", port))
        except OSError:
            return False
    return True


def until(cond: Callable[[], bool], timeout_s: float, what: str, logs: Callable[[], str]) -> None:
    deadline = time.monotonic() + timeout_s
    while not cond():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}\n{logs()[-6000:]}")
        time.sleep(0.2)


def test_the_simulator_page_runs_as_written(tmp_path: Path) -> None:
    taken = [p for p in (14540, 14541, 14550, 14580, 14581, 18570, 18571) if not _udp_free(p)]
    if taken or not _tcp_free(1883) or Path("/run/wingman/status.sock").exists():
        pytest.skip(f"the page's default ports or sockets are in use here (UDP {taken}, TCP 1883)")
    if shutil.which("mosquitto") is None or shutil.which("mosquitto_sub") is None:
        pytest.fail("mosquitto and mosquitto_sub are installed by scripts/setup")
    clone = tmp_path / "clone"
    if (REPO / ".git").exists() and shutil.which("git") is not None:
        subprocess.run(["git", "clone", "--quiet", str(REPO), str(clone)], check=True, timeout=120)
    else:  # the container image: its /src is already a clean copy of a checkout, without git
        shutil.copytree(REPO, clone, ignore=shutil.ignore_patterns(".venv*", "runs", "__pycache__"))
    # The page's `.venv/bin/...`: the environment these tests run in (the checkout's .venv, the image's venv).
    (clone / ".venv").symlink_to(REPO / ".venv" if (REPO / ".venv").exists() else Path(sys.prefix))
    env = {
        **os.environ,
        "PYTHONPATH": str(clone),
        "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}",
    }
    env.pop("WINGMAN_CONFIG", None)
    blocks = page_blocks((clone / "docs" / "fly-in-the-simulator.md").read_text())
    procs: list[Child] = []

    def logs() -> str:
        return "\n".join(f"--- {p.args[-1]}\n{p.tail(2500)}" for p in procs)

    def status() -> dict[str, object] | None:
        r = subprocess.run(
            [".venv/bin/companion", "status", "--json"],
            cwd=clone,
            env=env,
            capture_output=True,
            text=True,
            timeout=30,
            check=False,
        )
        return json.loads(r.stdout) if r.returncode == 0 else None

    def state() -> object:
        s = status()
        return None if s is None else s["mission"]["state"]  # type: ignore[index]

    ran: list[str] = []
    try:
        for background, commands in blocks:
            for cmd in commands:
                if background:
                    words = cmd.split(" ")
                    assigned = dict(
                        w.split("=", 1) for w in itertools.takewhile(_ASSIGNMENT.fullmatch, words)
                    )
                    rest = " ".join(words[len(assigned) :])
                    child = Child(
                        ["bash", "-c", f"exec {rest}"],
                        {**env, **assigned},
                        tmp_path / f"bg{len(procs)}.log",
                        cwd=clone,
                    )
                    procs.append(child)
                    child.start()
                    ready = {"sitl serve": "camera server on", "companion run": "service ready"}
                    marker = next((m for k, m in ready.items() if k in cmd), None)
                    if marker is not None:
                        until(
                            lambda c=child, m=marker: m in c.log() or not c.running,  # type: ignore[misc]
                            150,
                            marker,
                            logs,
                        )
                    else:
                        time.sleep(1.0)
                    assert child.running, logs()
                    continue
                if cmd.endswith("companion status"):
                    until(lambda: state() == "follow", 150, "follow after start", logs)
                r = subprocess.run(
                    ["bash", "-c", cmd],
                    cwd=clone,
                    env=env,
                    capture_output=True,
                    text=True,
                    timeout=90,
                    check=False,
                )
                assert r.returncode == 0, f"{cmd}: exit {r.returncode}\n{r.stdout}\n{r.stderr}\n{logs()}"
                ran.append(cmd)
                print(f"$ {cmd}\n{r.stdout}")
        mqtt = procs[-1].log()
        assert "wingman/follower1/state" in mqtt
        assert '"state":"follow"' in mqtt.replace(" ", "") or '"state": "follow"' in mqtt
        until(lambda: state() in ("px4_land", "landed", "disarmed", None), 60, "the landing", logs)
    finally:
        for p in reversed(procs):
            asyncio.run(p.stop(20.0))
    assert ran[-1] == ".venv/bin/companion command land"
