"""The service around the flight: the autopilot link, MQTT, the status socket, logging, auto-labels."""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from companion.kernel.config import Section

_URL_SCHEMES = ("udpin", "udpout", "tcpin", "tcpout", "serial")


def url_problem(url: str) -> str | None:
    """What is wrong with a MAVSDK connection URL, in words; None when it is well formed."""
    scheme, sep, rest = url.partition("://")
    if not sep or scheme not in _URL_SCHEMES:
        return f"expected one of {', '.join(s + '://' for s in _URL_SCHEMES)}..."
    if scheme == "serial":
        device, _, baud = rest.partition(":")
        if not device.startswith("/dev/"):
            return "serial:// needs a device path, e.g. serial:///dev/ttyTHS1:921600"
        if baud and not baud.isdigit():
            return f"serial baud rate must be a number (got {baud!r})"
        return None
    host, colon, port = rest.rpartition(":")
    if not colon or not host or not port.isdigit() or not 0 < int(port) < 65536:
        return f"{scheme}:// needs HOST:PORT with a port in 1-65535 (got {rest!r})"
    return None


class LinkConfig(Section):
    """The autopilot link (MAVSDK connection URL and timing)."""

    #: MAVSDK connection URL: ``udpin://HOST:PORT``, ``udpout://HOST:PORT``, ``tcpin://``/``tcpout://`` or
    #: ``serial:///dev/ttyX[:BAUD]``. PX4 SITL's vehicle i sends to 14540 + i: the simulator's follower
    #: (system 2) is 14541.
    url: str = "udpin://0.0.0.0:14541"
    #: MAVLink system id of the autopilot this service flies. 0: the first autopilot heard that is not the
    #: leader's (``leader.mavlink_system_id``). Any other autopilot on the link is never commanded.
    system_id: int = Field(2, ge=0, le=255)
    connect_timeout_s: float = Field(10.0, gt=0)
    #: MAVSDK resends setpoints at 20 Hz; PX4 needs > 2 Hz. This is how often *we* compute fresh ones.
    setpoint_rate_hz: float = Field(20.0, gt=2.0, le=100.0)
    command_timeout_s: float = Field(3.0, gt=0)
    #: No fresh setpoint from the mission for this long while streaming: the link stops offboard itself, so
    #: MAVSDK's 20 Hz resend can never keep a dead mission's last setpoint alive.
    setpoint_timeout_s: float = Field(0.5, gt=0)
    #: No telemetry for this long counts as a lost link.
    telemetry_timeout_s: float = Field(1.5, gt=0)
    #: What PX4 does when our setpoints stop for COM_OF_LOSS_T (a crashed service, a cut cable): the link
    #: sets COM_OBL_RC_ACT to it on connect (vehicle/failsafe.py). PX4's own default without RC is Return,
    #: which first climbs to RTL_RETURN_ALT (60 m) out of the formation; ``autopilot`` leaves PX4's setting.
    offboard_loss_action: Literal["hold", "land", "return", "autopilot"] = "hold"
    #: MAVSDK's own log lines go to the ``companion.vehicle.mavsdk`` logger at or above this level.
    mavsdk_log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "WARNING"
    #: MAVLink 2 message signing between the service and the autopilot (a relay in the service signs what
    #: MAVSDK sends and checks what the autopilot sends; MAVSDK itself cannot sign). udpin, udpout and
    #: serial links only.
    signing: bool = False
    #: The 32-byte signing key: 32 raw bytes or 64 hexadecimal digits, mode 0600 (refused otherwise).
    signing_key_file: str = ""
    #: Send the key to an autopilot that does not sign yet (SETUP_SIGNING), only while it is disarmed, once:
    #: after it signs, ``mavlink-signing-provisioned`` in ``service.state_dir`` ends it for good. The key
    #: crosses the link in clear: over serial or udpout, or on udpin to an autopilot on loopback only.
    signing_provision: bool = False

    @field_validator("url")
    @classmethod
    def _known_url(cls, v: str) -> str:
        problem = url_problem(v)
        if problem is not None:
            raise ValueError(problem)
        return v

    @model_validator(mode="after")
    def _signing_needs(self) -> LinkConfig:
        if self.signing and not self.signing_key_file:
            raise ValueError("signing = true needs signing_key_file")
        if self.signing and self.system_id == 0:
            raise ValueError("signing = true needs the autopilot's system_id (not 0)")
        if self.signing and self.url.partition("://")[0] not in ("udpin", "udpout", "serial"):
            raise ValueError("signing needs a udpin://, udpout:// or serial:// url (the relay speaks those)")
        return self


class MqttConfig(Section):
    """Telemetry to an MQTT broker (topics under ``<topic_prefix>/<vehicle_id>/``)."""

    enabled: bool = False
    host: str = "127.0.0.1"
    port: int = Field(1883, ge=1, le=65535)
    topic_prefix: str = Field("wingman", pattern=r"^[A-Za-z0-9_/-]{1,64}$")
    username: str = ""
    #: A file holding the password (never the password itself in the config).
    password_file: str = ""
    tls: bool = False
    #: CA bundle for the broker's certificate; empty: the system's CAs.
    ca_file: str = ""
    #: Client certificate and key for mutual TLS; both or neither.
    cert_file: str = ""
    key_file: str = ""
    keepalive_s: int = Field(10, ge=2, le=600)
    #: Reconnect backoff: jittered, doubling from min to max.
    reconnect_min_s: float = Field(0.5, gt=0)
    reconnect_max_s: float = Field(30.0, gt=0)
    state_rate_hz: float = Field(2.0, gt=0)
    pose_rate_hz: float = Field(10.0, gt=0)
    health_rate_hz: float = Field(0.5, gt=0)
    #: state and events messages kept while disconnected; the oldest are dropped (and counted) beyond it.
    buffer_messages: int = Field(1000, ge=1)
    #: Accept land/hold/set_offset on <prefix>/<vehicle_id>/cmd, each signed with an operator's key.
    command_topic: bool = False
    #: The operators' keys, one line each: ``KEY_ID HEX_KEY`` (16 bytes or more; delete a line to revoke).
    command_keys_file: str = ""
    command_max_age_s: float = Field(30.0, gt=0)
    #: Where the leader's shared position arrives when leader.shared_position = "mqtt".
    leader_topic: str = "wingman/leader/position"
    #: The formation's share keys, ``KEY_ID HEX_KEY [TOPIC ...]`` a line (the first signs this vehicle's
    #: pose); a key with topics verifies only shares on them. Empty: shares are checked, not authenticated.
    formation_keys_file: str = ""
    #: Inbound messages (commands, shares) larger than this are dropped before they are parsed, bytes.
    max_inbound_bytes: int = Field(4096, ge=512, le=65536)
    #: A share older than this, or ahead of our clock by more than share_max_ahead_s, is dropped, s.
    share_max_age_s: float = Field(2.0, gt=0, le=60)
    share_max_ahead_s: float = Field(0.5, ge=0, le=10)
    #: A share whose speed, or jump from the sender's last share, says it moves faster is dropped, m/s.
    share_max_speed_m_s: float = Field(30.0, gt=0, le=200)

    @model_validator(mode="before")
    @classmethod
    def _renamed(cls, data: Any) -> Any:
        if isinstance(data, dict) and "command_key_file" in data:
            raise ValueError(
                "command_key_file is now command_keys_file: one line per operator, KEY_ID HEX_KEY"
            )
        return data

    @model_validator(mode="after")
    def _consistent(self) -> MqttConfig:
        if self.command_topic and not self.command_keys_file:
            raise ValueError("command_topic = true needs command_keys_file (commands must be authenticated)")
        if bool(self.cert_file) != bool(self.key_file):
            raise ValueError("cert_file and key_file go together")
        if self.reconnect_min_s > self.reconnect_max_s:
            raise ValueError("reconnect_min_s must be <= reconnect_max_s")
        if any(c in self.leader_topic for c in "#+"):
            raise ValueError("leader_topic must not contain wildcards")
        return self


class StatusConfig(Section):
    """The local status endpoint (a Unix socket, mode 0660)."""

    socket_path: str = "/run/wingman/status.sock"


class ServiceConfig(Section):
    """Lifecycle of the service and what it tells the ground station over MAVLink."""

    #: Start the mission (arm, take off, follow) as soon as preflight passes, without `companion start`.
    #: For the simulator and test stands; on a drone an operator starts it.
    auto_start: bool = False
    #: Bound on the safe action at SIGTERM/SIGINT (hold, land, disarm) before exiting anyway.
    #: Keep the unit's TimeoutStopSec above this.
    shutdown_timeout_s: float = Field(120.0, gt=0)
    #: STATUSTEXT to the ground station on every mission state change.
    statustext: bool = True
    #: ONBOARD_COMPUTER_STATUS (CPU, memory, temperatures) to the ground station; 0 turns it off.
    onboard_status_rate_hz: float = Field(1.0, ge=0, le=10)
    #: How often the machine's load and temperatures are sampled.
    system_sample_period_s: float = Field(1.0, gt=0)
    #: What must survive a restart (the operators' last command times, the MAVLink signing timestamp).
    #: Empty: systemd's $STATE_DIRECTORY (/var/lib/wingman under the unit), else ~/.local/state/wingman.
    state_dir: str = ""


class LoggingConfig(Section):
    """Log format and level; set once at the CLI edge."""

    format: Literal["human", "json"] = "human"
    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = "INFO"


class AutoLabelSection(Section):
    """Recording the leader's box from its shared position while GPS is good (a dataset to fine-tune on)."""

    #: Off by default: recording writes images to disk for as long as the formation flies.
    enabled: bool = False
    #: Dataset folder; each service start writes a new sub-folder named by its start time.
    out_dir: str = "/var/lib/wingman/autolabel"
    #: Stop writing beyond this many bytes per start (images and labels).
    max_bytes: int = Field(2_000_000_000, gt=0)
    #: A shared leader position older than this at a frame's time is not used, s.
    share_max_age_s: float = Field(0.5, gt=0.0, le=5.0)
    #: 1-sigma error of the expected leader position (both GPS fixes and the share's age), m.
    position_sigma_m: float = Field(0.5, gt=0.0, le=5.0)
    #: Spinning propellers leave no depth: the box is widened by this share of the span on each side.
    side_pad_fraction: float = Field(0.15, ge=0.0, le=1.0)
    #: Keep one drone-free frame in this many as a negative.
    negative_every: int = Field(5, ge=1)


def resolve_state_dir(configured: str, environ: Mapping[str, str]) -> Path:
    """``service.state_dir``, or where systemd (``STATE_DIRECTORY``) or the XDG rules put it."""
    if configured:
        return Path(configured)
    if environ.get("STATE_DIRECTORY"):
        return Path(environ["STATE_DIRECTORY"].split(":")[0])
    base = environ.get("XDG_STATE_HOME") or str(Path(environ.get("HOME", "/tmp")) / ".local" / "state")  # noqa: S108
    return Path(base) / "wingman"
