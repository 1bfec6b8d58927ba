"""systemd/wingman.service: lint clean, exposure <= 3.0, and the directives docs/service.md describes."""

from __future__ import annotations

import base64
import hashlib
import re
import secrets
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from companion.config import Config

UNIT = Path(__file__).resolve().parents[2] / "systemd" / "wingman.service"
INSTALLED_EXE = "/opt/wingman/.venv/bin/companion"


def analyze(*args: str) -> subprocess.CompletedProcess[str]:
    exe = shutil.which("systemd-analyze")
    assert exe, "systemd-analyze is required (Debian package systemd)"
    return subprocess.run([exe, *args], capture_output=True, text=True, timeout=60, check=False)


def directives(text: str) -> dict[str, list[str]]:
    out: dict[str, list[str]] = {}
    for raw in text.splitlines():
        line = raw.strip()
        if not line or line.startswith(("#", ";", "[")):
            continue
        key, _, value = line.partition("=")
        out.setdefault(key.strip(), []).append(value.strip())
    return out


def local_copy(tmp_path: Path, text: str | None = None) -> Path:
    """The unit with ExecStart pointing at this venv's companion, so verify can check the binary exists."""
    exe = Path(sys.prefix) / "bin" / "companion"
    assert exe.exists(), f"{exe} missing: run scripts/setup (pip install -e .)"
    path = tmp_path / "wingman.service"
    path.write_text((text or UNIT.read_text()).replace(INSTALLED_EXE, str(exe)))
    return path


def test_verify_prints_nothing(tmp_path: Path) -> None:
    r = analyze("verify", str(local_copy(tmp_path)))
    assert r.returncode == 0
    assert r.stderr == "", r.stderr
    assert r.stdout == ""


def test_verify_lint_can_fail(tmp_path: Path) -> None:
    # systemd-analyze returns 0 on bad values; only stderr tells. Make sure our check would see it.
    bad = UNIT.read_text().replace("Type=notify", "Type=notifyy")
    r = analyze("verify", str(local_copy(tmp_path, bad)))
    assert "Failed to parse service type" in r.stderr


def test_security_exposure_at_most_3(tmp_path: Path) -> None:
    r = analyze("security", "--offline=true", str(local_copy(tmp_path)))
    m = re.search(r"Overall exposure level for wingman\.service: (\d+\.\d+)", r.stdout)
    assert m, r.stdout[-500:] + r.stderr
    exposure = float(m.group(1))
    print(f"exposure {exposure}")
    assert exposure <= 3.0


def test_unit_has_the_required_directives() -> None:
    d = directives(UNIT.read_text())
    one = {k: v[-1] for k, v in d.items()}
    assert one["Type"] == "notify"
    assert one["NotifyAccess"] == "main"
    assert float(one["WatchdogSec"]) > 0
    assert one["Restart"] == "on-failure"
    assert one["RestartPreventExitStatus"].split() == ["2", "4"]
    assert one["User"] == "wingman"
    assert one["Group"] == "wingman"
    for key in ("NoNewPrivileges", "ProtectHome", "PrivateTmp"):
        assert one[key] == "yes", key
    assert one["ProtectSystem"] == "strict"
    assert one["DevicePolicy"] == "closed"
    assert "PrivateDevices" not in d  # it would hide the camera and the serial port too
    allowed = {v.split()[0] for v in d["DeviceAllow"]}
    assert allowed == {"/dev/ttyTHS1", "char-usb_device", "char-video4linux"}
    assert one["ExecStart"].startswith(INSTALLED_EXE + " run --config /etc/wingman/wingman.toml")
    # The safe landing at stop must fit inside systemd's stop timeout.
    assert float(one["TimeoutStopSec"]) > Config().service.shutdown_timeout_s


def test_install_script_parses() -> None:
    script = UNIT.parent / "install.sh"
    r = subprocess.run(["bash", "-n", str(script)], capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
    r = subprocess.run(["bash", str(script), "--bogus"], capture_output=True, text=True, check=False)
    assert r.returncode == 2
    assert "unknown argument" in r.stderr


@pytest.mark.skipif(shutil.which("mosquitto_passwd") is None, reason="needs mosquitto_passwd")
def test_the_installer_hands_the_broker_password_over_standard_input(tmp_path: Path) -> None:
    """The installer's own lines, run with a mosquitto_passwd that records its arguments first."""
    script = (UNIT.parent / "install.sh").read_text()
    start = script.index("    # On standard input")
    block = script[start : script.index("    unset pw", start)]
    passwd_file = tmp_path / "wingman.passwd"
    block = block.replace("/etc/mosquitto/wingman.passwd", str(passwd_file))
    creds = tmp_path / "creds"
    creds.mkdir()
    password = "p" + secrets.token_hex(12)
    (creds / "mqtt-password").write_text(password + "\n")
    shim = tmp_path / "bin" / "mosquitto_passwd"
    shim.parent.mkdir()
    shim.write_text(
        f'#!/bin/sh\necho "$@" >> {tmp_path}/argv\nexec {shutil.which("mosquitto_passwd")} "$@"\n'
    )
    shim.chmod(0o755)
    passwd_file.touch()
    env = {"PATH": f"{shim.parent}:/usr/bin:/bin", "CRED_SRC": str(creds), "VEHICLE_ID": "follower1"}
    r = subprocess.run(["bash", "-euc", block], env=env, capture_output=True, text=True, check=False)
    assert r.returncode == 0, r.stderr
    assert password not in (tmp_path / "argv").read_text()
    # The file holds the password itself: mosquitto's $7$ is PBKDF2-SHA512, 101 rounds, base64 fields.
    user, _, entry = passwd_file.read_text().strip().partition(":")
    _, kind, rounds, salt, digest = entry.split("$")
    assert (user, kind) == ("follower1", "7")
    derived = hashlib.pbkdf2_hmac("sha512", password.encode(), base64.b64decode(salt), int(rounds))
    assert base64.b64encode(derived).decode() == digest
