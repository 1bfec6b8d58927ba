"""The broker configuration install.sh ships, run by a real mosquitto: TLS, passwords, ACLs, the size limit.

The shipped files (systemd/mosquitto-wingman.conf and .acl) are used as they are, only their paths moved
to the test's folder and the listener to a free port; the certificates are made with openssl as install.sh
makes them. The service's reporter connects with the credentials load_mqtt_credentials reads.
"""

from __future__ import annotations

import asyncio
import json
import logging
import ssl
import subprocess
import time
from pathlib import Path

import aiomqtt
import pytest

from companion.config import MqttConfig
from companion.kernel import compat
from companion.kernel.clock import MonotonicClock
from companion.kernel.errors import ConfigError
from companion.telemetry.mqtt import MqttReporter, TelemetrySources
from companion.telemetry.mqtt_setup import load_mqtt_credentials
from companion.telemetry.payloads import HealthMsg, PoseMsg, StateMsg
from tests.mosquitto import Mosquitto

pytestmark = [pytest.mark.mqtt_broker, pytest.mark.timeout(120)]

SYSTEMD = Path(__file__).resolve().parents[2] / "systemd"
PASSWORD = "correct horse battery staple"  # noqa: S105 (the test broker's)


def make_certs(d: Path) -> None:
    """A CA and a server certificate for 127.0.0.1, as install.sh --broker makes them."""
    d.mkdir(parents=True)

    def run(*args: str) -> None:
        subprocess.run(["openssl", *args], check=True, capture_output=True, timeout=60)

    run("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", "/CN=wingman test CA",
        "-keyout", str(d / "ca.key"), "-out", str(d / "ca.crt"))  # fmt: skip
    run("req", "-newkey", "rsa:2048", "-nodes", "-subj", "/CN=localhost",
        "-keyout", str(d / "server.key"), "-out", str(d / "server.csr"))  # fmt: skip
    (d / "san.ext").write_text("subjectAltName=DNS:localhost,IP:127.0.0.1\n")
    run("x509", "-req", "-in", str(d / "server.csr"), "-CA", str(d / "ca.crt"),
        "-CAkey", str(d / "ca.key"), "-CAcreateserial", "-days", "2", "-extfile", str(d / "san.ext"),
        "-out", str(d / "server.crt"))  # fmt: skip


def shipped_broker(tmp_path: Path) -> Mosquitto:
    certs = tmp_path / "certs"
    make_certs(certs)
    passwd = tmp_path / "wingman.passwd"
    passwd.touch()
    for user in ("f1", "operator"):
        subprocess.run(["mosquitto_passwd", "-b", str(passwd), user, PASSWORD], check=True, timeout=30)
    acl = tmp_path / "wingman.acl"
    # The operator's block, as the file's comment says to add one per operator.
    acl.write_text(
        (SYSTEMD / "mosquitto-wingman.acl").read_text()
        + "\nuser operator\ntopic read wingman/#\ntopic write wingman/+/cmd\n"
    )
    broker = Mosquitto(tmp_path)
    conf = (
        (SYSTEMD / "mosquitto-wingman.conf")
        .read_text()
        .replace("listener 8883", f"listener {broker.port} 127.0.0.1")
        .replace("/etc/mosquitto/certs/wingman", str(certs))
        .replace("/etc/mosquitto/wingman.passwd", str(passwd))
        .replace("/etc/mosquitto/wingman.acl", str(acl))
    )
    # What the helper's own config adds that the shipped one must not lose: the log, and root's user.
    head = broker.conf.read_text().splitlines()
    keep = [line for line in head if line.startswith(("user ", "log_"))]
    broker.conf.write_text("\n".join(keep) + "\n" + conf)
    return broker


def tls_to(ca: Path) -> ssl.SSLContext:
    return ssl.create_default_context(cafile=str(ca))


async def test_the_shipped_broker_wants_tls_a_password_and_small_messages(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    broker = shipped_broker(tmp_path)
    ca = tmp_path / "certs" / "ca.crt"
    pw = tmp_path / "mqtt-password"
    pw.write_text(PASSWORD + "\n")
    pw.chmod(0o600)
    with broker:
        # No TLS, or no password: refused.
        with pytest.raises(aiomqtt.MqttError):
            async with aiomqtt.Client("127.0.0.1", broker.port, timeout=3):
                pass
        with pytest.raises(aiomqtt.MqttError):
            async with aiomqtt.Client("127.0.0.1", broker.port, tls_context=tls_to(ca), timeout=3):
                pass

        cfg = MqttConfig(
            enabled=True,
            port=broker.port,
            tls=True,
            ca_file=str(ca),
            username="f1",
            password_file=str(pw),
            state_rate_hz=10.0,
            reconnect_min_s=0.1,
            reconnect_max_s=0.5,
        )
        caplog.set_level(logging.WARNING, logger="companion.telemetry.mqtt")
        creds = load_mqtt_credentials(cfg)
        assert not [r for r in caplog.records if "clear text" in r.getMessage()]
        sources = TelemetrySources(
            state=lambda: StateMsg(state="FOLLOW"),
            pose=lambda: PoseMsg(p_ned_m=(1.0, 2.0, 3.0)),
            health=HealthMsg,
        )
        reporter = MqttReporter(cfg, "f1", sources, MonotonicClock(), time.time, credentials=creds)
        seen: list[tuple[str, int]] = []

        async def operator() -> None:
            async with aiomqtt.Client(
                "127.0.0.1", broker.port, username="operator", password=PASSWORD, tls_context=tls_to(ca)
            ) as c:
                await c.subscribe("wingman/#", qos=0)
                async for m in c.messages:
                    assert isinstance(m.payload, bytes)
                    seen.append((str(m.topic), len(m.payload)))

        async with compat.TaskGroup() as tg:
            tasks = [
                tg.create_task(operator(), name="test.operator"),
                tg.create_task(reporter.run(), name="test.f1"),
            ]
            deadline = time.monotonic() + 10
            while not any(t == "wingman/f1/state" for t, _ in seen):
                assert time.monotonic() < deadline, "the service's state never reached the operator"
                await asyncio.sleep(0.05)
            # f1 may not write another vehicle's topics (the ACL drops it), and 8 MB gets a client cut off.
            async with aiomqtt.Client(
                "127.0.0.1", broker.port, username="f1", password=PASSWORD, tls_context=tls_to(ca)
            ) as f1:
                await f1.publish("wingman/f2/state", json.dumps({"state": "spoofed"}), qos=1)
            with pytest.raises(aiomqtt.MqttError):
                async with aiomqtt.Client(
                    "127.0.0.1", broker.port, username="operator", password=PASSWORD, tls_context=tls_to(ca)
                ) as big:
                    await big.publish("wingman/f1/cmd", b"x" * (8 * 1024 * 1024), qos=1, timeout=10)
            await asyncio.sleep(1.0)
            assert reporter.connected
            assert reporter.connects == 1
            for t in tasks:
                t.cancel()
    assert not [t for t, _ in seen if t == "wingman/f2/state"]
    assert max(n for _, n in seen) < 65536
    assert "max_packet_size 65536" in (SYSTEMD / "mosquitto-wingman.conf").read_text()


def test_secrets_readable_by_others_are_refused_and_a_bare_password_is_warned_about(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    pw = tmp_path / "pw"
    pw.write_text("secret\n")
    pw.chmod(0o644)
    keys = tmp_path / "keys"
    keys.write_text(f"op {'ab' * 32}\n")
    keys.chmod(0o640)
    cfg = MqttConfig(
        enabled=True, username="f1", password_file=str(pw), command_topic=True, command_keys_file=str(keys)
    )
    with pytest.raises(ConfigError) as exc:
        load_mqtt_credentials(cfg)
    assert len(exc.value.problems) == 2
    assert all("chmod 600" in p for p in exc.value.problems)
    pw.chmod(0o600)
    keys.chmod(0o600)
    caplog.set_level(logging.WARNING, logger="companion.telemetry.mqtt")
    creds = load_mqtt_credentials(cfg)
    assert creds.password == "secret"  # noqa: S105 (what the file holds)
    assert creds.command_keys is not None
    assert [r for r in caplog.records if "clear text" in r.getMessage()]
