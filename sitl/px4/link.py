"""MAVLink to one PX4 instance on SIH's display link: ground truth in, state in, commands out.

PX4 SITL with SIH starts a MAVLink instance bound to UDP ``19450 + i`` that sends to ``19410 + i`` for a
visualiser. The simulator binds ``19410 + i``: that link carries ``HIL_STATE_QUATERNION``, which PX4 fills
from SIH's ground truth (the true pose, not the estimate), and, once asked with SET_MESSAGE_INTERVAL, the
state a pilot and the run's record need (HEARTBEAT modes, SYS_STATUS, EXTENDED_SYS_STATE, HOME_POSITION,
LOCAL_POSITION_NED, GLOBAL_POSITION_INT, GPS_RAW_INT, ESTIMATOR_STATUS) and STATUSTEXT. The offboard API
link (``14540 + i``) stays free for the companion under test, exactly as on a vehicle.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import socket
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mavlink

log = logging.getLogger(__name__)

#: Messages the simulator asks for on the display link, and their rates (Hz). HIL_ACTUATOR_CONTROLS is the
#: clock: PX4 leaves HIL_STATE_QUATERNION's time_usec at 0, and the actuator stream carries its boot time.
STREAMS_HZ: dict[int, float] = {
    mavlink.MAVLINK_MSG_ID_HIL_STATE_QUATERNION: 100.0,
    mavlink.MAVLINK_MSG_ID_HIL_ACTUATOR_CONTROLS: 100.0,
    mavlink.MAVLINK_MSG_ID_SYS_STATUS: 5.0,
    mavlink.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    mavlink.MAVLINK_MSG_ID_HOME_POSITION: 1.0,
    mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 20.0,
    mavlink.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    mavlink.MAVLINK_MSG_ID_GPS_RAW_INT: 5.0,
    mavlink.MAVLINK_MSG_ID_ESTIMATOR_STATUS: 5.0,
    mavlink.MAVLINK_MSG_ID_STATUSTEXT: 20.0,
}
#: ESTIMATOR_STATUS flags for a usable horizontal estimate (VELOCITY_HORIZ | POS_HORIZ_REL).
EST_HORIZ_FLAGS = 2 | 8
#: What the simulator says it is on this link: a ground station's system id, a visualiser's component.
OWN_SYSTEM = 250
OWN_COMPONENT = 190
#: How many STATUSTEXTs are kept per vehicle.
MAX_TEXTS = 2000


@dataclass(frozen=True, slots=True)
class TruthSample:
    """One HIL_STATE_QUATERNION: PX4's ground truth, geodetic, as received.

    ``time_s`` is PX4's boot time (lockstep sim time) when it arrived, from the clock stream; ``mono_s`` when
    it arrived on the host's monotonic clock.
    """

    time_s: float
    mono_s: float
    lat_deg: float
    lon_deg: float
    alt_m: float
    v_ned_m_s: tuple[float, float, float]
    q_wxyz: tuple[float, float, float, float]
    omega_body_rad_s: tuple[float, float, float]


@dataclass(frozen=True, slots=True)
class StatusText:
    """A STATUSTEXT as PX4 sent it: PX4 boot time (s), severity (MAV_SEVERITY), text."""

    time_s: float
    severity: int
    text: str


class Px4Link:
    """The simulator's end of one PX4 instance's display link; the latest of everything it said.

    Datagrams are received and parsed in a thread of their own: PX4 runs on in its own process whatever
    this one does, and a busy event loop here (the renderer starting, a loaded host) must not make PX4's
    clock or ground truth look older than they are. Each datagram also wakes the event loop
    (:attr:`received`), and every new PX4 time goes to the :attr:`on_clock` callbacks from that thread.
    """

    def __init__(self, name: str, sysid: int, px4_port: int, local_port: int) -> None:
        self.name = name
        self.sysid = sysid
        self.px4_addr = ("127.0.0.1", px4_port)
        self.local_addr = ("127.0.0.1", local_port)
        self.counters: Counter[str] = Counter()
        self.truth: TruthSample | None = None
        self.heartbeat: Any = None
        self.sys_status: Any = None
        self.extended_state: Any = None
        self.home: Any = None
        self.local_position: Any = None
        self.global_position: Any = None
        self.gps: Any = None
        self.estimator_flags: int | None = None
        self.texts: list[StatusText] = []
        self.boot_s = 0.0
        self.received = asyncio.Event()
        #: Called with PX4's boot time (s) from the receiving thread each time it advances.
        self.on_clock: list[Callable[[float], None]] = []
        self._packers: dict[tuple[int, int], mavlink.MAVLink] = {}
        self._sock: socket.socket | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._loop: asyncio.AbstractEventLoop | None = None

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        """Bind the display link's port and start receiving."""
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind(self.local_addr)
        except OSError as exc:
            sock.close()
            raise OSError(f"px4 {self.name}: cannot bind UDP {self.local_addr[1]}: {exc.strerror}") from None
        sock.settimeout(0.2)
        self._sock, self._loop = sock, loop
        self._thread = threading.Thread(target=self._receive, name=f"px4-link-{self.name}", daemon=True)
        self._thread.start()

    def close(self) -> None:
        """Stop receiving and release the port. Idempotent."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
            self._thread = None
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def _receive(self) -> None:
        sock = self._sock
        assert sock is not None  # noqa: S101 (started by open)
        while not self._stop.is_set():
            try:
                data = sock.recv(65536)
            except TimeoutError:
                continue
            except OSError:
                return
            self.datagram_received(data)

    def _wake(self) -> None:
        self.received.set()
        self.received = asyncio.Event()

    def datagram_received(self, data: bytes) -> None:
        """Parse one datagram and keep what it says (the receiving thread; tests call it directly)."""
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        try:
            msgs = parser.parse_buffer(data) or []
        except Exception:
            self.counters["bad_datagrams"] += 1
            return
        mono_s = time.monotonic()
        boot_s = self.boot_s
        for msg in msgs:
            if msg.get_srcSystem() != self.sysid:
                continue
            self._on_message(msg, mono_s)
        if self.boot_s != boot_s:
            for callback in list(self.on_clock):
                try:
                    callback(self.boot_s)
                except Exception:  # a listener that is gone (its file closed) never stops the link
                    self.on_clock.remove(callback)
                    log.debug("px4 %s: clock listener dropped", self.name, exc_info=True)
        loop = self._loop
        if loop is not None and not loop.is_closed():
            with contextlib.suppress(RuntimeError):  # the loop closed in between
                loop.call_soon_threadsafe(self._wake)

    def _on_message(self, msg: Any, mono_s: float) -> None:
        kind = msg.get_type()
        self.counters[kind] += 1
        if kind == "HIL_ACTUATOR_CONTROLS":
            self.boot_s = max(self.boot_s, msg.time_usec * 1e-6)
        elif kind == "HIL_STATE_QUATERNION":
            self.truth = TruthSample(
                self.boot_s,
                mono_s,
                msg.lat * 1e-7,
                msg.lon * 1e-7,
                msg.alt * 1e-3,
                (msg.vx * 0.01, msg.vy * 0.01, msg.vz * 0.01),
                tuple(float(x) for x in msg.attitude_quaternion),  # type: ignore[arg-type]
                (msg.rollspeed, msg.pitchspeed, msg.yawspeed),
            )
        elif kind == "HEARTBEAT":
            if msg.get_srcComponent() == 1:
                self.heartbeat = msg
        elif kind == "SYS_STATUS":
            self.sys_status = msg
        elif kind == "EXTENDED_SYS_STATE":
            self.extended_state = msg
        elif kind == "HOME_POSITION":
            self.home = msg
        elif kind == "LOCAL_POSITION_NED":
            self.local_position = msg
        elif kind == "GLOBAL_POSITION_INT":
            self.global_position = msg
        elif kind == "GPS_RAW_INT":
            self.gps = msg
        elif kind == "ESTIMATOR_STATUS":
            self.estimator_flags = int(msg.flags)
        elif kind == "STATUSTEXT":
            text = (
                bytes(msg.text).decode("ascii", "replace") if isinstance(msg.text, bytes) else str(msg.text)
            )
            self.texts.append(StatusText(self.boot_s, int(msg.severity), text.rstrip("\x00")))
            del self.texts[:-MAX_TEXTS]
            log.info("px4 %s: %s", self.name, text.rstrip("\x00"))

    def send(self, msg: Any, src_system: int = OWN_SYSTEM, src_component: int = OWN_COMPONENT) -> None:
        """Pack ``msg`` as (``src_system``, ``src_component``) and send it to PX4."""
        sock = self._sock
        if sock is None:
            return
        key = (src_system, src_component)
        packer = self._packers.get(key)
        if packer is None:
            packer = self._packers[key] = mavlink.MAVLink(
                None, srcSystem=src_system, srcComponent=src_component
            )
        try:
            sock.sendto(msg.pack(packer), self.px4_addr)
        except OSError:
            self.counters["send_errors"] += 1

    def command(self, command: int, *params: float) -> None:
        """A COMMAND_LONG to the autopilot (no retry: callers repeat until the state shows it worked)."""
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        self.send(mavlink.MAVLink_command_long_message(self.sysid, 1, command, 0, *p))

    def heartbeat_out(self) -> None:
        """A ground station's HEARTBEAT: PX4 sends STATUSTEXT only to a link whose partner it has heard."""
        self.send(
            mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE, 3
            )
        )

    def request_streams(self) -> None:
        """Ask PX4 for this link's streams (repeated until they arrive: UDP and a booting PX4 drop some)."""
        for msg_id, rate_hz in STREAMS_HZ.items():
            interval_us = -1.0 if rate_hz == 0 else 1e6 / rate_hz
            self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float(msg_id), interval_us)

    def streams_flowing(self) -> bool:
        return all(
            x is not None
            for x in (self.truth, self.heartbeat, self.sys_status, self.extended_state, self.local_position)
        )

    def gps_ok(self) -> bool:
        s = self.sys_status
        bit = mavlink.MAV_SYS_STATUS_SENSOR_GPS
        return s is not None and bool(
            s.onboard_control_sensors_present & s.onboard_control_sensors_health & bit
        )

    def horizontal_estimate_ok(self) -> bool:
        f = self.estimator_flags
        return f is not None and (f & EST_HORIZ_FLAGS) == EST_HORIZ_FLAGS
