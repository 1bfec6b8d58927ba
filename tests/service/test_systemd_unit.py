"""systemd/wingman.service: lint clean, exposure <= 3.0, and the directives docs/service.md describes."""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

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
