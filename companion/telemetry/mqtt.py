"""``MqttReporter``: state, pose, health and events to an MQTT broker with aiomqtt 2.5.

Producers never touch the network: samplers build messages at the configured rates and put them in an
:class:`Outbox` (state and events, in order, bounded: the oldest are dropped and counted when the broker
is away for long) or in one-slot mailboxes (pose and health: only the newest is worth sending). One
connection loop drains them while connected and reconnects with jittered backoff when the broker goes
away, so a dead broker can neither block nor crash the flight.

Inbound messages (commands, shares) are untrusted: one larger than ``max_inbound_bytes`` is dropped
before it is queued, each is handled inside a boundary that turns any failure into one counted,
rate-limited line (a payload, retained or not, can never end the receive loop and start a reconnect
loop), and the client id carries a random suffix per connection, so no other client can take it over by
guessing it.
"""

from __future__ import annotations

import asyncio
import contextlib
import inspect
import json
import logging
import random
import secrets
import ssl
from collections import deque
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import aiomqtt

from companion.config import MqttConfig
from companion.kernel import compat
from companion.kernel.backoff import Backoff
from companion.kernel.clock import Clock
from companion.kernel.errors import ConfigError
from companion.kernel.throttle import Throttle, and_more
from companion.telemetry.commands import (
    Command,
    CommandRejectedError,
    CommandVerifier,
    HighWaterMarks,
    RejectReason,
)
from companion.telemetry.inbound import InboundRejectedError, Keyring, parse_keyring, read_secret
from companion.telemetry.payloads import (
    EventMsg,
    HealthMsg,
    LeaderPositionMsg,
    Payload,
    PoseMsg,
    Severity,
    StateMsg,
    Topics,
    offline_state,
)
from companion.telemetry.shares import ShareGate, ShareLimits, sign_share

log = logging.getLogger(__name__)

T = TypeVar("T")

#: A QoS 1 publish not acknowledged within this is treated as a dead connection.
_PUBLISH_TIMEOUT_S = 5.0
#: Connecting (TCP + CONNACK) must finish within this.
_CONNECT_TIMEOUT_S = 5.0
#: The operators' high-water marks, in ``service.state_dir``.
COMMAND_MARKS_FILE = "command-high-water.json"
#: Inbound messages waiting for the receive loop; beyond it they are dropped and counted (a flood).
_INBOUND_QUEUE = 1000


@dataclass(frozen=True, slots=True)
class Outgoing:
    """One message waiting to be published."""

    topic: str
    payload: bytes
    qos: int
    retain: bool


class Outbox:
    """A bounded FIFO: ``push`` drops the oldest when full; ``peek``/``ack`` lose nothing on a failed send."""

    def __init__(self, max_messages: int) -> None:
        if max_messages < 1:
            raise ValueError("max_messages must be >= 1")
        self.max_messages = max_messages
        self._items: deque[Outgoing] = deque()
        self.dropped = 0
        self.pushed = 0

    def __len__(self) -> int:
        return len(self._items)

    def push(self, item: Outgoing) -> None:
        if len(self._items) >= self.max_messages:
            self._items.popleft()
            self.dropped += 1
        self._items.append(item)
        self.pushed += 1

    def peek(self) -> Outgoing | None:
        return self._items[0] if self._items else None

    def ack(self, item: Outgoing) -> None:
        """Remove ``item`` once published (unless it was already dropped to make room)."""
        if self._items and self._items[0] is item:
            self._items.popleft()


@dataclass(frozen=True, slots=True)
class TelemetrySources:
    """Where the reporter samples from (the service's snapshot functions)."""

    state: Callable[[], StateMsg]
    pose: Callable[[], PoseMsg | None]
    health: Callable[[], HealthMsg]


@dataclass(frozen=True, slots=True)
class MqttCredentials:
    """Secrets and TLS, loaded once at start-up (see :func:`load_mqtt_credentials`)."""

    password: str | None = None
    tls_context: ssl.SSLContext | None = None
    #: The operators' command keys (``command_keys_file``).
    command_keys: Keyring | None = None
    #: The formation key(s) shares are signed with (``formation_keys_file``).
    formation_keys: Keyring | None = None


class MqttReporter:
    """Publishes telemetry; optionally receives authenticated commands and the leader's position.

    Args:
        cfg: the ``[mqtt]`` section.
        vehicle_id: the topic level under the prefix.
        sources: snapshot functions sampled at the configured rates.
        clock: monotonic time (rates, uptime).
        wall_time_s: wall-clock time for ``time_unix_s`` and command freshness.
        credentials: password, TLS context and command key.
        rng: jitter for the reconnect backoff.
        on_command: called with each verified command; returns (or, a coroutine, answers once the mission
            has acted) the text reported on ``events``.
        on_leader_position: called with each valid leader position from ``cfg.leader_topic``.
        on_neighbour_pose: called with (vehicle id, pose) for each pose the ``neighbour_ids`` publish.
        neighbour_ids: the other followers of a formation plan.
        command_marks: each operator's newest accepted command time, persisted (replays after a restart).
    """

    def __init__(
        self,
        cfg: MqttConfig,
        vehicle_id: str,
        sources: TelemetrySources,
        clock: Clock,
        wall_time_s: Callable[[], float],
        *,
        credentials: MqttCredentials | None = None,
        rng: random.Random | None = None,
        on_command: Callable[[Command], str | Awaitable[str]] | None = None,
        on_leader_position: Callable[[LeaderPositionMsg], None] | None = None,
        on_neighbour_pose: Callable[[str, PoseMsg], None] | None = None,
        neighbour_ids: Sequence[str] = (),
        command_marks: HighWaterMarks | None = None,
    ) -> None:
        self.cfg = cfg
        self.topics = Topics(cfg.topic_prefix, vehicle_id)
        self._vehicle_id = vehicle_id
        self._sources = sources
        self._clock = clock
        self._wall_time_s = wall_time_s
        self._creds = credentials or MqttCredentials()
        self._backoff = Backoff(cfg.reconnect_min_s, cfg.reconnect_max_s, rng or random.Random())  # noqa: S311 (jitter, not crypto)
        self._on_command = on_command
        self._on_leader_position = on_leader_position
        self._on_neighbour_pose = on_neighbour_pose
        self._neighbour_topics = {Topics(cfg.topic_prefix, n).pose: n for n in neighbour_ids}
        self._verifier: CommandVerifier | None = None
        if cfg.command_topic:
            if self._creds.command_keys is None:
                raise ValueError("command_topic needs the operators' command keys")
            self._verifier = CommandVerifier(
                self._creds.command_keys,
                self.topics.cmd,
                cfg.command_max_age_s,
                command_marks,
                max_bytes=cfg.max_inbound_bytes,
            )
        self.shares = ShareGate(
            ShareLimits(
                max_bytes=cfg.max_inbound_bytes,
                max_age_s=cfg.share_max_age_s,
                max_ahead_s=cfg.share_max_ahead_s,
                max_speed_m_s=cfg.share_max_speed_m_s,
            ),
            wall_time_s,
            self._creds.formation_keys,
        )
        #: One line (and one event) per kind of bad input per window, the rest counted.
        self._throttle = Throttle(window_s=10.0, burst=3, now_s=clock.now_s)
        self.outbox = Outbox(cfg.buffer_messages)
        self._pose_slot: Outgoing | None = None
        self._health_slot: Outgoing | None = None
        self._wake = asyncio.Event()
        self._seq: dict[str, int] = {}
        self._start_s = clock.now_s()
        self._stopping = False
        self._drained = asyncio.Event()
        self._session_started = False
        self._offline_since_s: float | None = None
        self.connected = False
        #: True once this connection's subscriptions (commands, leader position) are in place.
        self.subscribed = False
        self.connects = 0
        self.published = 0
        self.slot_overwrites = 0
        self.commands_accepted = 0
        self.commands_rejected = 0
        self.leader_positions = 0
        #: Inbound messages dropped before parsing (too large, or the queue full), and handler failures.
        self.inbound_dropped = 0
        self.inbound_errors = 0
        #: The client id of the current (or last) connection: ``wingman-<vehicle_id>-<random>``.
        self.client_id = ""

    # ---- producers (never block, never touch the network) -------------------------------------------

    def state_changed(self) -> None:
        """Publish the state now (called on every mission transition), not only at the next tick."""
        if not self._stopping:  # after stop() the last word is "offline"
            self._push_state(self._sources.state())

    def event(self, kind: str, text: str, severity: Severity = "info", **data: Any) -> None:
        """Queue one event for ``events`` (QoS 1, kept while disconnected within the buffer bound)."""
        msg = EventMsg(kind=kind, text=text, severity=severity, data=data)
        self._push(self.topics.events, msg, qos=1, retain=False)

    def stats(self) -> dict[str, Any]:
        """Counters for the health snapshot."""
        return {
            "enabled": True,
            "connected": self.connected,
            "connects": self.connects,
            "published": self.published,
            "buffered": len(self.outbox),
            "buffer_max": self.outbox.max_messages,
            "dropped": self.outbox.dropped,
            "commands_accepted": self.commands_accepted,
            "commands_rejected": self.commands_rejected,
            "shares_accepted": self.shares.accepted,
            "shares_rejected": dict(self.shares.rejected),
            "inbound_dropped": self.inbound_dropped,
            "inbound_errors": self.inbound_errors,
        }

    def _push_state(self, msg: StateMsg) -> None:
        self._push(self.topics.state, msg, qos=1, retain=True)

    def _push(self, topic: str, msg: Payload, *, qos: int, retain: bool) -> None:
        self.outbox.push(Outgoing(topic, self._stamp(topic, msg), qos, retain))
        self._drained.clear()
        self._wake.set()

    def _stamp(self, topic: str, msg: Payload) -> bytes:
        seq = self._seq.get(topic, 0)
        self._seq[topic] = seq + 1
        stamped = msg.model_copy(
            update={
                "vehicle_id": self._vehicle_id,
                "seq": seq,
                "time_unix_s": round(self._wall_time_s(), 3),
                "uptime_s": round(self._clock.now_s() - self._start_s, 3),
            }
        )
        return stamped.to_json_bytes()

    # ---- the loops ------------------------------------------------------------------------------------

    async def run(self) -> None:
        """Sample and publish until cancelled."""
        async with compat.TaskGroup() as tg:
            tg.create_task(
                self._sample(self.cfg.state_rate_hz, self._tick_state), name="companion.mqtt.state"
            )
            tg.create_task(self._sample(self.cfg.pose_rate_hz, self._tick_pose), name="companion.mqtt.pose")
            tg.create_task(
                self._sample(self.cfg.health_rate_hz, self._tick_health), name="companion.mqtt.health"
            )
            tg.create_task(self._connection_loop(), name="companion.mqtt.connection")

    async def stop(self, reason: str, timeout_s: float = 2.0) -> bool:
        """Publish a last state and ``online: false`` and wait (bounded) until the outbox is flushed.

        Returns True when everything queued reached the broker.
        """
        if not self._stopping:
            self._stopping = True
            self._push_state(self._sources.state())
            self._push(self.topics.state, offline_state(self._vehicle_id, reason), qos=1, retain=True)
        try:
            async with compat.timeout(timeout_s):
                await self._drained.wait()
        except TimeoutError:
            log.warning("MQTT: %d message(s) not delivered at stop", len(self.outbox))
            return False
        return True

    async def _sample(self, rate_hz: float, tick: Callable[[], None]) -> None:
        period_s = 1.0 / rate_hz
        next_s = self._clock.now_s()
        while True:
            if not self._stopping:
                tick()
            next_s += period_s
            now_s = self._clock.now_s()
            if next_s < now_s:  # fell behind (suspended, overloaded): skip, do not burst
                next_s = now_s + period_s
            await self._clock.sleep_until(next_s)

    def _tick_state(self) -> None:
        self._push_state(self._sources.state())

    def _tick_pose(self) -> None:
        pose = self._sources.pose()
        if pose is None:
            return
        if self._pose_slot is not None:
            self.slot_overwrites += 1
        payload = self._stamp(self.topics.pose, pose)
        keys = self._creds.formation_keys
        if keys is not None:  # the neighbours of a formation check it (shares.py)
            payload = sign_share(keys, self.topics.pose, json.loads(payload))
        self._pose_slot = Outgoing(self.topics.pose, payload, 0, False)
        self._wake.set()

    def _tick_health(self) -> None:
        health = self._sources.health()
        if self._health_slot is not None:
            self.slot_overwrites += 1
        self._health_slot = Outgoing(self.topics.health, self._stamp(self.topics.health, health), 0, False)
        self._wake.set()

    async def _connection_loop(self) -> None:
        attempts = 0
        while True:
            self._session_started = False
            attempts += 1
            try:
                await self._connect_and_serve()
            except (*_CONNECTION_ERRORS, compat.BaseExceptionGroup) as raised:
                exc = _connection_error(raised)
                if self._session_started:
                    self._offline_since_s = self._clock.now_s()
                    log.warning(
                        "MQTT: connection lost (%s); buffering up to %d", exc, self.cfg.buffer_messages
                    )
                elif attempts == 1:
                    self._offline_since_s = self._offline_since_s or self._clock.now_s()
                    log.warning(
                        "MQTT: cannot connect to %s:%d (%s); retrying", self.cfg.host, self.cfg.port, exc
                    )
                else:
                    log.debug("MQTT: connect attempt %d failed: %s", attempts, exc)
            if self._session_started:
                attempts = 0
                self._backoff.reset()
            await asyncio.sleep(self._backoff.next_delay_s())

    async def _connect_and_serve(self) -> None:
        client = self._client()
        async with contextlib.AsyncExitStack() as stack:
            async with compat.timeout(_CONNECT_TIMEOUT_S):
                await stack.enter_async_context(client)
            self._session_started = True
            self.connected = True
            self.connects += 1
            stack.callback(setattr, self, "connected", False)
            stack.callback(setattr, self, "subscribed", False)
            if self._offline_since_s is None:
                log.info("MQTT: connected to %s:%d", self.cfg.host, self.cfg.port)
            else:
                log.info(
                    "MQTT: reconnected after %.1f s; %d buffered, %d dropped in all",
                    self._clock.now_s() - self._offline_since_s,
                    len(self.outbox),
                    self.outbox.dropped,
                )
                self._offline_since_s = None
            await self._session(client)

    def _client(self) -> aiomqtt.Client:
        will = aiomqtt.Will(
            self.topics.state,
            offline_state(self._vehicle_id, "connection to the service lost").to_json_bytes(),
            qos=1,
            retain=True,
        )
        # A fixed id lets any client of the broker knock this one off by connecting with it; a fresh random
        # suffix per connection cannot be guessed (the broker's ACLs can still match the prefix).
        self.client_id = f"wingman-{self._vehicle_id}-{secrets.token_hex(6)}"
        return aiomqtt.Client(
            self.cfg.host,
            self.cfg.port,
            username=self.cfg.username or None,
            password=self._creds.password,
            identifier=self.client_id,
            queue_type=_bounded_queue(self.cfg.max_inbound_bytes, self._drop_inbound),
            max_queued_incoming_messages=_INBOUND_QUEUE,
            will=will,
            keepalive=self.cfg.keepalive_s,
            timeout=_PUBLISH_TIMEOUT_S,
            tls_context=self._creds.tls_context,
            logger=logging.getLogger("aiomqtt"),
        )

    async def _session(self, client: aiomqtt.Client) -> None:
        # A fresh retained state at once: it replaces the broker's last-will "offline" if one fired.
        if not self._stopping:
            self._push_state(self._sources.state())
        self._wake.set()  # whatever is still buffered goes out now
        if self._verifier is not None:
            await _call(client.subscribe(self.topics.cmd, qos=1))
        if self._on_leader_position is not None:
            await _call(client.subscribe(self.cfg.leader_topic, qos=0))
        if self._on_neighbour_pose is not None:
            for topic in self._neighbour_topics:
                await _call(client.subscribe(topic, qos=0))
        self.subscribed = True
        # Not a TaskGroup: Python 3.11's leaves this task "cancelling" when a child fails while it waits in
        # __aexit__ (fixed in 3.12), and _call() then took the next session's first subscribe for a
        # cancellation: the connection loop ended quietly after a lost connection, never to resubscribe.
        tasks = (
            asyncio.create_task(self._drain(client), name="companion.mqtt.publish"),
            asyncio.create_task(self._receive(client), name="companion.mqtt.receive"),
        )
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in tasks:
                task.cancel()
            await asyncio.gather(*tasks, return_exceptions=True)
        for task in done:
            task.result()  # the error that ended the session (a loop that returns means the same)
        raise aiomqtt.MqttError("session ended")

    async def _drain(self, client: aiomqtt.Client) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while (item := self.outbox.peek()) is not None:
                await _call(client.publish(item.topic, item.payload, qos=item.qos, retain=item.retain))
                self.outbox.ack(item)
                self.published += 1
            if len(self.outbox) == 0:
                self._drained.set()
            for slot in ("_pose_slot", "_health_slot"):
                item = getattr(self, slot)
                if item is not None:
                    setattr(self, slot, None)
                    await _call(client.publish(item.topic, item.payload, qos=item.qos, retain=item.retain))
                    self.published += 1

    async def _receive(self, client: aiomqtt.Client) -> None:
        # Iterating also detects a lost connection (it raises MqttError), even when nothing is subscribed.
        async for message in client.messages:
            raw = message.payload if isinstance(message.payload, bytes) else str(message.payload).encode()
            topic = str(message.topic)
            try:
                await self._dispatch(topic, raw)
            except Exception as exc:
                # The boundary to untrusted input: whatever a payload does to a handler, the loop (and so
                # the connection and its subscriptions) lives on. A retained payload that broke it would
                # otherwise come back on every reconnect.
                self.inbound_errors += 1
                suppressed = self._throttle.allow("handler_error")
                if suppressed is not None:
                    log.error(
                        "MQTT: error handling a message on %s: %s: %s%s",
                        topic[:80],
                        type(exc).__name__,
                        exc,
                        and_more(suppressed),
                    )

    async def _dispatch(self, topic: str, raw: bytes) -> None:
        if topic == self.topics.cmd:
            await self._handle_command(raw)
        elif topic == self.cfg.leader_topic and self._on_leader_position is not None:
            try:
                pos = self.shares.leader_position(topic, raw)
            except InboundRejectedError as exc:
                self._share_rejected("leader position", topic, exc)
                return
            self.leader_positions += 1
            self._on_leader_position(pos)
        elif self._on_neighbour_pose is not None and topic in self._neighbour_topics:
            try:
                pose = self.shares.neighbour_pose(topic, raw)
            except InboundRejectedError as exc:
                self._share_rejected("neighbour pose", topic, exc)
                return
            self._on_neighbour_pose(self._neighbour_topics[topic], pose)

    def _share_rejected(self, what: str, topic: str, exc: InboundRejectedError) -> None:
        suppressed = self._throttle.allow(f"share:{topic}")
        if suppressed is not None:
            log.warning("MQTT: %s on %s dropped: %s%s", what, topic, exc, and_more(suppressed))
            self.event(
                "share_rejected",
                f"{what} on {topic} dropped: {exc}",
                "warning",
                reason=exc.reason,
                topic=topic,
                suppressed=suppressed,
            )

    def _drop_inbound(self, topic: str, size: int, why: str) -> None:
        """A message the receive queue refused (too large, or a flood): counted, reported rate-limited."""
        self.inbound_dropped += 1
        if topic == self.topics.cmd:
            self.commands_rejected += 1
        elif why == "too_large":
            self.shares.rejected["too_large"] += 1
        suppressed = self._throttle.allow(f"drop:{why}")
        if suppressed is None:
            return
        if why == "too_large":
            text = f"message on {topic[:80]} dropped unread: {size} bytes > {self.cfg.max_inbound_bytes}"
        else:
            text = f"message on {topic[:80]} dropped: {_INBOUND_QUEUE} messages already waiting"
        log.warning("MQTT: %s%s", text, and_more(suppressed))
        kind = "command_rejected" if topic == self.topics.cmd else "inbound_dropped"
        self.event(kind, text, "warning", reason=why.upper(), suppressed=suppressed)

    async def _handle_command(self, raw: bytes) -> None:
        if self._verifier is None or self._on_command is None:
            return
        try:
            cmd = self._verifier.verify(raw, self._wall_time_s())
        except CommandRejectedError as exc:
            self.commands_rejected += 1
            suppressed = self._throttle.allow(f"command:{exc.reason.name}")
            if suppressed is not None:
                log.warning("MQTT: command refused: %s%s", exc, and_more(suppressed))
                self.event(
                    "command_rejected",
                    str(exc),
                    "warning",
                    reason=exc.reason.name,
                    suppressed=suppressed,
                )
            return
        # The operator's high-water mark reaches the disk before the command is acted upon: a restart
        # can never make this command acceptable again.
        try:
            await asyncio.to_thread(self._verifier.marks.save)
        except OSError as exc:
            self.commands_rejected += 1
            log.error("MQTT: command %s refused: cannot keep its time (%s)", cmd.name.value, exc)
            self.event(
                "command_rejected",
                f"cannot keep the command's time: {exc.strerror}",
                "error",
                reason=RejectReason.REPLAYED.name,
            )
            return
        self.commands_accepted += 1
        answer = self._on_command(cmd)
        result = await answer if inspect.isawaitable(answer) else answer  # once the mission has acted
        refused = " refused: " in result
        (log.warning if refused else log.info)(
            "MQTT: command %s from %s: %s", cmd.name.value, cmd.key_id, result
        )
        data = {"cmd": cmd.name.value, "key_id": cmd.key_id, "nonce": cmd.nonce}
        if refused:
            self.event("command_refused", result, "warning", **data)
        else:
            self.event("command", result, "notice", **data)


def _bounded_queue(
    max_bytes: int, on_drop: Callable[[str, int, str], None]
) -> type[asyncio.Queue[aiomqtt.Message]]:
    """The inbound queue for aiomqtt, refusing what must never wait in memory: oversized payloads, floods.

    aiomqtt hands every message to ``put_nowait`` as it arrives; dropping here (instead of raising
    QueueFull, which aiomqtt logs once per message) keeps a flood out of the log and the memory bounded.
    """

    class BoundedQueue(asyncio.Queue[aiomqtt.Message]):
        def put_nowait(self, item: aiomqtt.Message) -> None:
            payload = item.payload
            size = len(payload) if isinstance(payload, bytes | bytearray | str) else 0
            if size > max_bytes:
                on_drop(str(item.topic), size, "too_large")
            elif self.full():
                on_drop(str(item.topic), size, "queue_full")
            else:
                super().put_nowait(item)

    return BoundedQueue


#: asyncio.TimeoutError is TimeoutError from Python 3.11 on; on 3.10 aiomqtt's wait_for raises the former.
_CONNECTION_ERRORS = (aiomqtt.MqttError, OSError, TimeoutError, asyncio.TimeoutError)


def _connection_error(raised: BaseException) -> BaseException:
    """The connection error in ``raised`` (alone or in a task group's group); anything else re-raised."""
    if not isinstance(raised, compat.BaseExceptionGroup):
        return raised
    match, rest = raised.split(_CONNECTION_ERRORS)
    if rest is not None or match is None:
        raise raised
    first: BaseException = match.exceptions[0]
    while isinstance(first, compat.BaseExceptionGroup):
        first = first.exceptions[0]
    return first


async def _call(awaitable: Awaitable[T]) -> T:
    """Await an aiomqtt call without losing a cancellation.

    aiomqtt 2.5 waits with ``asyncio.wait_for``, which on Python 3.11 can swallow a cancellation that
    arrives as the awaited operation completes (CPython gh-86296, fixed in 3.12). The task then keeps
    running with its cancellation pending and a TaskGroup waiting on it hangs: re-raise it here. (On 3.10
    only the backport's TaskGroup tasks count cancellations; others have no ``cancelling()``.)
    """
    result = await awaitable
    cancelling = getattr(asyncio.current_task(), "cancelling", None)
    if cancelling is not None and cancelling():
        raise asyncio.CancelledError
    return result


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
