"""Preflight checks behind ``companion health``: config, model, camera, autopilot, GPS, broker.

When the service is running, it owns the camera and the autopilot link, so those checks come from it
(over the status socket); the checks that need no device (config, model checksum and a test inference,
broker) run here. Without a running service, the device checks probe the devices directly.
Healthy means every check passed; the command exits 0 then, 1 otherwise.
"""

from __future__ import annotations

import asyncio
import logging
import socket
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import aiomqtt
import numpy as np

from companion.config import Config, ConfigCheck, DetectorConfig, check_config
from companion.kernel import compat
from companion.kernel.errors import CompanionError, ModelError
from companion.service.status import ServiceNotRunningError, query_status
from companion.telemetry.mqtt_setup import load_mqtt_credentials

log = logging.getLogger(__name__)


@dataclass(frozen=True, slots=True)
class CheckResult:
    """One check: its name, whether it passed, and what was found (one line)."""

    name: str
    ok: bool
    detail: str


@dataclass(frozen=True, slots=True)
class HealthReport:
    """All checks; ``healthy`` when every one passed."""

    checks: list[CheckResult]
    service_running: bool
    state: str | None = None

    @property
    def healthy(self) -> bool:
        return bool(self.checks) and all(c.ok for c in self.checks)

    def to_json(self) -> dict[str, Any]:
        return {
            "healthy": self.healthy,
            "service_running": self.service_running,
            "state": self.state,
            "checks": [asdict(c) for c in self.checks],
        }


@dataclass(frozen=True, slots=True)
class ConfigVerdict:
    """What ``companion check-config`` reports: the config's problems and the model files' (one pass)."""

    check: ConfigCheck
    #: The model files' problems (``detector.model_path: ...``), one line each.
    model: list[str]

    @property
    def config(self) -> Config | None:
        """The resolved config when nothing at all is wrong with it."""
        return self.check.config if not self.model else None

    @property
    def problems(self) -> list[str]:
        return [*self.check.problems, *self.model]

    @property
    def sources(self) -> list[str]:
        return [*self.check.sources, *[self.check.source_of(("detector", "model_path"))] * len(self.model)]

    def lines(self) -> list[str]:
        """``source: problem``, one per problem."""
        return [f"{s}: {p}" for s, p in zip(self.sources, self.problems, strict=True)]


def verify_config(path: Path | None, environ: Mapping[str, str] | None = None) -> ConfigVerdict:
    """Every problem of the config at ``path`` and of the model files it names, in one pass.

    Raises :class:`ConfigError` only for a file that cannot be read or parsed at all.
    """
    check = check_config(path, environ)
    resolved = check.paths.get(("detector", "model_path"))
    return ConfigVerdict(check, model_problems(check.detector, resolved.note() if resolved else ""))


def model_problems(detector: DetectorConfig | None, note: str = "") -> list[str]:
    """What ``companion run`` would refuse about the model files, one line each (empty: none).

    The file ``model_path`` names and the one the runtime would load (the ONNX export under ``auto`` when
    onnxruntime is there) must both be present and match their checksums. ``note`` (how a relative path
    was resolved) is added to a "not found".
    """
    if detector is None or detector.runtime == "truth":
        return []
    from companion.perception.detector import choose_runtime  # noqa: PLC0415 (torch, onnxruntime: lazily)
    from companion.perception.detector.weights import verify_model_file  # noqa: PLC0415

    named = Path(detector.model_path)
    _, loaded = choose_runtime(detector)
    problems = []
    for path in dict.fromkeys([named, loaded]):
        try:
            verify_model_file(path, detector.model_sha256 if path == named else "")
        except ModelError as exc:
            missing = not path.exists()
            problems.append(f"detector.model_path: {exc}{note if missing else ''}")
    return problems


def check_config_file(path: Path) -> tuple[Config | None, CheckResult]:
    """The config check: the same problems as ``companion check-config``, the model files' included."""
    try:
        verdict = verify_config(path)
    except CompanionError as exc:
        return None, CheckResult("config", False, " / ".join(str(exc).splitlines()))
    cfg = verdict.check.config
    if verdict.problems:
        return cfg, CheckResult("config", False, " / ".join(verdict.lines()))
    assert cfg is not None  # noqa: S101 (no problem: the config is there)
    return cfg, CheckResult("config", True, f"{path} valid (vehicle {cfg.vehicle_id})")


def check_model(cfg: Config) -> CheckResult:
    """The model file the service will load matches its checksum, and one inference on a blank frame runs."""
    if cfg.detector.runtime == "truth":
        return CheckResult(
            "model", True, "not used: ground-truth boxes (detector.runtime = truth, tests only)"
        )
    problems = model_problems(cfg.detector)
    if problems:
        return CheckResult("model", False, " / ".join(problems))
    from companion.perception import detector as detector_mod  # noqa: PLC0415 (torch, onnxruntime: lazily)

    runtime, loaded = detector_mod.choose_runtime(cfg.detector)
    try:
        t0 = time.monotonic()
        detector = detector_mod.load_detector(cfg.detector)
        t1 = time.monotonic()
        blank = np.zeros((cfg.camera.height_px, cfg.camera.width_px, 3), np.uint8)
        result = detector.detect(blank)
        t2 = time.monotonic()
    except CompanionError as exc:
        return CheckResult("model", False, str(exc))
    except Exception as exc:  # a broken model file can fail in many ways inside torch/onnxruntime
        return CheckResult("model", False, f"{loaded}: test inference failed: {type(exc).__name__}: {exc}")
    return CheckResult(
        "model",
        True,
        f"{loaded} ({runtime}, the file the service loads) checksum ok, loaded in {(t1 - t0) * 1e3:.0f} ms, "
        f"test inference {(t2 - t1) * 1e3:.0f} ms ({len(result.detections)} detections on a blank frame)",
    )


def check_camera_offline(cfg: Config) -> CheckResult:
    """Without the service: is the configured frame source there at all?"""
    cam = cfg.camera
    if cam.source == "file":
        p = Path(cam.path)
        return CheckResult("camera", p.exists(), f"recording {p} {'found' if p.exists() else 'missing'}")
    if cam.source == "sim":
        p = Path(cam.path)
        if not p.exists():
            return CheckResult(
                "camera", False, f"simulator camera socket {p} missing (is `sitl serve` running?)"
            )
        with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as s:
            s.settimeout(1.0)
            try:
                s.connect(str(p))
            except OSError as exc:
                return CheckResult("camera", False, f"simulator camera {p}: {exc.strerror}")
        return CheckResult("camera", True, f"simulator camera {p} answers")
    from companion.perception.sources.realsense import import_pyrealsense2  # noqa: PLC0415

    try:
        rs = import_pyrealsense2()
    except CompanionError as exc:
        return CheckResult("camera", False, str(exc))
    devices = rs.context().query_devices()
    names = [d.get_info(rs.camera_info.name) for d in devices]
    return CheckResult("camera", bool(names), ", ".join(names) or "no RealSense device found")


async def check_broker(cfg: Config, timeout_s: float = 3.0) -> CheckResult:
    """Connect to the configured MQTT broker with the configured credentials."""
    if not cfg.mqtt.enabled:
        return CheckResult("broker", True, "MQTT disabled")
    try:
        creds = load_mqtt_credentials(cfg.mqtt)
    except CompanionError as exc:
        return CheckResult("broker", False, str(exc))
    m = cfg.mqtt
    try:
        async with (
            compat.timeout(timeout_s),
            aiomqtt.Client(
                m.host,
                m.port,
                username=m.username or None,
                password=creds.password,
                tls_context=creds.tls_context,
                identifier=f"wingman-{cfg.vehicle_id}-health",
            ),
        ):
            pass
    except (aiomqtt.MqttError, OSError, TimeoutError) as exc:
        return CheckResult("broker", False, f"{m.host}:{m.port}: {exc or 'timed out'}")
    return CheckResult("broker", True, f"{m.host}:{m.port} accepted the connection")


#: Probes the autopilot without the service: returns the autopilot and GPS checks.
AutopilotProbe = Callable[[Config, float], list[CheckResult]]


def _no_probe(cfg: Config, timeout_s: float) -> list[CheckResult]:
    why = "service not running, and no standalone probe is wired for " + cfg.link.url
    return [CheckResult("autopilot", False, why), CheckResult("gps", False, "unknown (no autopilot)")]


def run_health(
    config_path: Path,
    *,
    probe_autopilot: AutopilotProbe = _no_probe,
    check_model_fn: Callable[[Config], CheckResult] = check_model,
    timeout_s: float = 5.0,
) -> HealthReport:
    """All checks for ``config_path``; the running service answers for the devices it owns."""
    cfg, config_result = check_config_file(config_path)
    checks = [config_result]
    if cfg is None:
        return HealthReport(checks, service_running=False)
    checks.append(check_model_fn(cfg))
    try:
        live = query_status(Path(cfg.status.socket_path), "health", timeout_s=timeout_s)
    except ServiceNotRunningError as exc:
        log.debug("no running service: %s", exc)
        live = None
    if live is not None and "checks" in live:
        checks += [CheckResult(str(c["name"]), bool(c["ok"]), str(c["detail"])) for c in live["checks"]]
        return HealthReport(checks, service_running=True, state=live.get("state"))
    checks.append(check_camera_offline(cfg))
    checks += probe_autopilot(cfg, timeout_s)
    checks.append(asyncio.run(check_broker(cfg)))
    return HealthReport(checks, service_running=False)
