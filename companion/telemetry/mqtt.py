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
import json
import logging
import random
import secrets
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Any

import aiomqtt

from companion.config import MqttConfig
from companion.kernel import compat
from companion.kernel.backoff import Backoff
from companion.kernel.clock import Clock
from companion.kernel.throttle import Throttle
from companion.mission.types import OperatorVerdict
from companion.telemetry.commands import (
    Command,
    HighWaterMarks,
)
from companion.telemetry.mqtt_client import (
    CONNECTION_ERRORS,
    INBOUND_QUEUE,
    bounded_queue,
    call,
    cancel_and_wait,
    connection_error,
)
from companion.telemetry.mqtt_inbound import MqttInbound
from companion.telemetry.mqtt_setup import MqttCredentials
from companion.telemetry.outbox import Outbox, Outgoing
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
from companion.telemetry.shares import sign_share

log = logging.getLogger(__name__)


#: A QoS 1 publish not acknowledged within this is treated as a dead connection.
_PUBLISH_TIMEOUT_S = 5.0
#: Connecting (TCP + CONNACK) must finish within this.
_CONNECT_TIMEOUT_S = 5.0


@dataclass(frozen=True, slots=True)
class TelemetrySources:
    """Where the reporter samples from (the service's snapshot functions)."""

    state: Callable[[], StateMsg]
    pose: Callable[[], PoseMsg | None]
    health: Callable[[], HealthMsg]


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
            has acted) the mission's verdict, reported on ``events``.
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
        on_command: Callable[[Command], OperatorVerdict | Awaitable[OperatorVerdict]] | None = None,
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
        self.inbound = MqttInbound(
            cfg,
            self.topics,
            wall_time_s,
            credentials=self._creds,
            # One line (and one event) per kind of bad input per window, the rest counted.
            throttle=Throttle(window_s=10.0, burst=3, now_s=clock.now_s),
            event=self.event,
            on_command=on_command,
            on_leader_position=on_leader_position,
            on_neighbour_pose=on_neighbour_pose,
            neighbour_ids=neighbour_ids,
            command_marks=command_marks,
        )
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
            **self.inbound.stats(),
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
            except (*CONNECTION_ERRORS, compat.BaseExceptionGroup) as raised:
                exc = connection_error(raised)
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
            queue_type=bounded_queue(self.cfg.max_inbound_bytes, self.inbound.drop),
            max_queued_incoming_messages=INBOUND_QUEUE,
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
        for topic, qos in self.inbound.subscriptions():
            await call(client.subscribe(topic, qos=qos))
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
            await cancel_and_wait(tasks)
        for task in done:
            task.result()  # the error that ended the session (a loop that returns means the same)
        raise aiomqtt.MqttError("session ended")

    async def _drain(self, client: aiomqtt.Client) -> None:
        while True:
            await self._wake.wait()
            self._wake.clear()
            while (item := self.outbox.peek()) is not None:
                await call(client.publish(item.topic, item.payload, qos=item.qos, retain=item.retain))
                self.outbox.ack(item)
                self.published += 1
            if len(self.outbox) == 0:
                self._drained.set()
            for slot in ("_pose_slot", "_health_slot"):
                item = getattr(self, slot)
                if item is not None:
                    setattr(self, slot, None)
                    await call(client.publish(item.topic, item.payload, qos=item.qos, retain=item.retain))
                    self.published += 1

    async def _receive(self, client: aiomqtt.Client) -> None:
        # Iterating also detects a lost connection (it raises MqttError), even when nothing is subscribed.
        async for message in client.messages:
            raw = message.payload if isinstance(message.payload, bytes) else str(message.payload).encode()
            await self.inbound.handle(str(message.topic), raw)
