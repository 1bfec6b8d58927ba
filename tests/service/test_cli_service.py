"""The service's CLI edge as a user meets it: exit codes and one-line errors (subprocesses)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(120)


def companion(*args: str, cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    full_env = {**os.environ, "PYTHONPATH": str(cwd), **(env or {})}
    return subprocess.run(
        [sys.executable, "-m", "companion", *args],
        cwd=cwd,
        env=full_env,
        capture_output=True,
        text=True,
        timeout=90,
        check=False,
    )


def test_run_with_an_invalid_config_is_one_line_and_exit_2(tmp_path: Path, repo_root: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text("[mqtt]\nport = 0\n")
    r = companion("run", "--config", str(bad), cwd=repo_root)
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        f"companion: {bad}: mqtt.port: Input should be greater than or equal to 1 (got 0)"
    ]


def test_run_refuses_an_unauthenticated_command_topic(tmp_path: Path, repo_root: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text("[mqtt]\nenabled = true\ncommand_topic = true\n")
    r = companion("run", "--config", str(cfg), cwd=repo_root)
    assert r.returncode == 2
    assert "command_keys_file" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_run_with_a_missing_model_fails_before_opening_anything(tmp_path: Path, repo_root: Path) -> None:
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        f'[detector]\nmodel_path = "{tmp_path}/none.pt"\n[status]\nsocket_path = "{tmp_path}/s.sock"\n'
    )
    r = companion("run", "--config", str(cfg), cwd=repo_root)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("companion: model file not found")
    assert "vehicle link" not in r.stderr  # the link was never opened


def test_status_start_and_commands_without_a_service(tmp_path: Path, repo_root: Path) -> None:
    """Not running is exit 5 and says how to start it; a refusal would be 1, a usage error 2."""
    sock = tmp_path / "none.sock"
    env = {"WINGMAN_STATUS__SOCKET_PATH": str(sock)}
    line = (
        f"companion: service not running: nothing listens on {sock} (start it with `companion run`; "
        "a service with another config: --config PATH)"
    )
    for args in (("status",), ("start",), ("command", "land"), ("command", "set_offset", "0", "0", "6")):
        r = companion(*args, cwd=repo_root, env=env)
        assert (r.returncode, r.stderr.strip()) == (5, line), args
    r = companion("status", "--json", cwd=repo_root, env=env)
    assert r.returncode == 5
    assert json.loads(r.stdout) == {
        "running": False,
        "error": line.removeprefix("companion: "),
        "exit_code": 5,
    }
    r = companion("status", "--json", cwd=repo_root, env={**env, "WINGMAN_LINK__URL": "foo"})
    assert r.returncode == 2
    answer = json.loads(r.stdout)  # a config error is JSON too
    assert answer["running"] is False
    assert answer["error"].startswith("$WINGMAN_LINK__URL: link.url: expected one of")
    for args in (("set_offset", "1"), ("land", "3")):
        r = companion("command", *args, cwd=repo_root, env=env)
        assert r.returncode == 2, args  # a usage error, found before the service is asked
        assert "service not running" not in r.stderr
    assert (
        "set_offset takes 3 numbers X Y Z (m), got 1"
        in companion("command", "set_offset", "1", cwd=repo_root, env=env).stderr
    )


def test_health_without_a_service_reports_every_check(tmp_path: Path, repo_root: Path) -> None:
    env = {
        "WINGMAN_STATUS__SOCKET_PATH": str(tmp_path / "none.sock"),
        "WINGMAN_DETECTOR__RUNTIME": "truth",
        "WINGMAN_LINK__URL": "udpin://127.0.0.1:45931",
        "WINGMAN_CAMERA__PATH": str(tmp_path / "cam.sock"),
    }
    r = companion("health", "--json", "--timeout", "1", cwd=repo_root, env=env)
    assert r.returncode == 1
    report = json.loads(r.stdout)
    assert report["healthy"] is False
    assert report["service_running"] is False
    checks = {c["name"]: c for c in report["checks"]}
    assert list(checks) == ["config", "model", "camera", "autopilot", "gps", "broker"]
    assert checks["config"]["ok"]
    assert checks["model"]["ok"]  # truth mode: nothing to check
    assert not checks["camera"]["ok"]
    assert "cam.sock missing" in checks["camera"]["detail"]
    assert not checks["autopilot"]["ok"]
    assert "no heartbeat" in checks["autopilot"]["detail"]
    assert checks["broker"]["detail"] == "MQTT disabled"


def test_exit_guard_ends_a_process_that_a_stuck_thread_keeps_alive(repo_root: Path) -> None:
    code = (
        "import threading, time\n"
        "from companion.commands.run import ExitGuard\n"
        "threading.Thread(target=time.sleep, args=(3600,), name='stuck-native-call').start()\n"
        "ExitGuard().arm(0.5, 7, 'teardown')\n"
    )
    t0 = time.monotonic()
    r = subprocess.run(
        [sys.executable, "-c", code],
        cwd=repo_root,
        env={**os.environ, "PYTHONPATH": str(repo_root)},
        capture_output=True,
        text=True,
        timeout=30,
        check=False,
    )
    assert r.returncode == 7
    assert time.monotonic() - t0 < 10
    assert "teardown did not finish within 0 s; thread stacks follow; exiting 7" in r.stderr
    assert "Thread 0x" in r.stderr  # faulthandler's dump of every thread


def test_check_config_and_health_agree_on_a_model_without_its_checksum(
    tmp_path: Path, repo_root: Path
) -> None:
    """Both name the same problem, and the file the service would load (the ONNX export), not only the .pt."""
    for name in ("leader_detector.pt", "leader_detector.onnx"):  # no leader_detector.sha256 beside them
        (tmp_path / name).write_bytes((repo_root / "models" / name).read_bytes())
    cfg = tmp_path / "c.toml"
    cfg.write_text(
        '[detector]\nmodel_path = "leader_detector.pt"\n'  # relative to this file's folder
        f'[status]\nsocket_path = "{tmp_path}/none.sock"\n[camera]\npath = "{tmp_path}/cam.sock"\n'
        '[link]\nurl = "udpin://127.0.0.1:45932"\n'
    )
    r = companion("check-config", str(cfg), cwd=repo_root)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert lines == [
        f"companion: {cfg}: detector.model_path: no checksum for {tmp_path}/{name}: "
        f"set detector.model_sha256 or list it in {tmp_path}/leader_detector.sha256"
        for name in ("leader_detector.pt", "leader_detector.onnx")
    ]
    h = companion("health", "--config", str(cfg), "--json", "--timeout", "1", cwd=repo_root)
    assert h.returncode == 1
    checks = {c["name"]: c for c in json.loads(h.stdout)["checks"]}
    assert not checks["config"]["ok"]
    assert not checks["model"]["ok"]
    assert f"no checksum for {tmp_path}/leader_detector.onnx" in checks["config"]["detail"]
    assert f"no checksum for {tmp_path}/leader_detector.onnx" in checks["model"]["detail"]


def test_health_names_the_model_file_the_service_loads(tmp_path: Path, repo_root: Path) -> None:
    env = {
        "WINGMAN_STATUS__SOCKET_PATH": str(tmp_path / "none.sock"),
        "WINGMAN_LINK__URL": "udpin://127.0.0.1:45933",
        "WINGMAN_CAMERA__PATH": str(tmp_path / "cam.sock"),
    }
    r = companion("health", "--json", "--timeout", "1", cwd=repo_root, env=env)
    checks = {c["name"]: c for c in json.loads(r.stdout)["checks"]}
    assert checks["config"]["ok"]
    assert checks["model"]["ok"], checks["model"]
    assert checks["model"]["detail"].startswith(
        f"{repo_root}/models/leader_detector.onnx (onnx, the file the service loads) checksum ok"
    )
