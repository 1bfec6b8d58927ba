"""What the MQTT reporter needs before it connects: secrets, TLS, keys, the operators' high-water marks.

Read once at start-up, every problem in one :class:`~companion.kernel.errors.ConfigError`.
"""

from __future__ import annotations

import logging
import ssl
from dataclasses import dataclass
from pathlib import Path

from companion.config import MqttConfig
from companion.kernel.errors import ConfigError
from companion.telemetry.commands import HighWaterMarks
from companion.telemetry.inbound import Keyring, parse_keyring, read_secret

log = logging.getLogger(__name__)

#: The operators' high-water marks, in ``service.state_dir``.
COMMAND_MARKS_FILE = "command-high-water.json"


@dataclass(frozen=True, slots=True)
class MqttCredentials:
    """Secrets and TLS, loaded once at start-up (see :func:`load_mqtt_credentials`)."""

    password: str | None = None
    tls_context: ssl.SSLContext | None = None
    #: The operators' command keys (``command_keys_file``).
    command_keys: Keyring | None = None
    #: The formation key(s) shares are signed with (``formation_keys_file``).
    formation_keys: Keyring | None = None


def load_mqtt_credentials(cfg: MqttConfig) -> MqttCredentials:
    """Read the password and key files and build the TLS context; every problem in one ConfigError.

    A secret file that other users may read is refused (see :func:`read_secret`); a password sent without
    TLS is allowed but warned about, since anyone on the path reads it.
    """
    problems: list[str] = []

    def read(key: str, path: str) -> bytes | None:
        if not path:
            return None
        try:
            return read_secret(path)
        except PermissionError as exc:
            problems.append(f"mqtt.{key}: {exc}")
        except OSError as exc:
            problems.append(f"mqtt.{key}: cannot read {path}: {exc.strerror}")
        return None

    def keyring(key: str, path: str) -> Keyring | None:
        text = read(key, path)
        if text is None:
            return None
        try:
            return parse_keyring(text.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as exc:
            problems.append(f"mqtt.{key}: {path}: {exc}")
            return None

    password = read("password_file", cfg.password_file)
    command_keys = keyring("command_keys_file", cfg.command_keys_file)
    formation_keys = keyring("formation_keys_file", cfg.formation_keys_file)
    if cfg.key_file:
        read("key_file", cfg.key_file)  # the TLS client key: the same rule as every other secret
    tls: ssl.SSLContext | None = None
    if cfg.tls:
        try:
            tls = ssl.create_default_context(cafile=cfg.ca_file or None)
            if cfg.cert_file:
                tls.load_cert_chain(cfg.cert_file, cfg.key_file)
        except (OSError, ssl.SSLError) as exc:
            problems.append(f"mqtt.tls: {exc}")
    if problems:
        raise ConfigError("[mqtt]", problems)
    if password is not None and not cfg.tls:
        log.warning("MQTT: a password without TLS crosses the network in clear text (set mqtt.tls = true)")
    return MqttCredentials(
        password=None if password is None else password.strip().decode("utf-8", "replace"),
        tls_context=tls,
        command_keys=command_keys,
        formation_keys=formation_keys,
    )


def load_command_marks(state_dir: Path) -> HighWaterMarks:
    """The operators' high-water marks from ``state_dir``; a file that cannot be read is a ConfigError."""
    path = state_dir / COMMAND_MARKS_FILE
    try:
        return HighWaterMarks(path)
    except (OSError, ValueError) as exc:
        raise ConfigError(
            "[service] state_dir",
            [f"{path}: {exc} (commands stay refused until it is readable; delete it to start afresh)"],
        ) from None
