"""The reporter's inbound half: operators' commands and other vehicles' shares, untrusted until checked.

Each message is handled inside a boundary that turns any failure into one counted, rate-limited line: a
payload, retained or not, can never end the receive loop and start a reconnect loop. Commands are verified
(signature, topic, age, the operator's high-water mark, kept on disk before the command is acted upon);
shares go through :class:`~companion.telemetry.shares.ShareGate`.
"""

from __future__ import annotations

import asyncio
import inspect
import logging
from collections.abc import Awaitable, Callable, Sequence
from typing import Any

from companion.config import MqttConfig
from companion.kernel.throttle import Throttle, and_more
from companion.mission.types import OperatorVerdict
from companion.telemetry.commands import (
    Command,
    CommandRejectedError,
    CommandVerifier,
    HighWaterMarks,
    RejectReason,
)
from companion.telemetry.inbound import InboundRejectedError
from companion.telemetry.mqtt_client import INBOUND_QUEUE
from companion.telemetry.mqtt_setup import MqttCredentials
from companion.telemetry.payloads import LeaderPositionMsg, PoseMsg, Topics
from companion.telemetry.shares import ShareGate, ShareLimits

log = logging.getLogger(__name__)


class MqttInbound:
    """Commands and shares from the broker: checked, handed on, counted; never a failure past :meth:`handle`.

    Args:
        cfg: the ``[mqtt]`` section (topics, limits).
        topics: this vehicle's topics.
        wall_time_s: the wall clock (command and share times are Unix times).
        credentials: the command and formation keys.
        throttle: one line (and one event) per kind of bad input per window, the rest counted.
        event: the reporter's ``event`` (what goes out on the events topic).
        on_command: an accepted command to the mission; returns (or resolves to) the mission's verdict.
        on_leader_position: each valid leader position from ``cfg.leader_topic``.
        on_neighbour_pose: each valid pose of a formation neighbour (its vehicle id, the pose).
        neighbour_ids: the other followers of a formation plan.
        command_marks: each operator's newest accepted command time, persisted (replays after a restart).
    """

    def __init__(
        self,
        cfg: MqttConfig,
        topics: Topics,
        wall_time_s: Callable[[], float],
        *,
        credentials: MqttCredentials,
        throttle: Throttle,
        event: Callable[..., None],
        on_command: Callable[[Command], OperatorVerdict | Awaitable[OperatorVerdict]] | None = None,
        on_leader_position: Callable[[LeaderPositionMsg], None] | None = None,
        on_neighbour_pose: Callable[[str, PoseMsg], None] | None = None,
        neighbour_ids: Sequence[str] = (),
        command_marks: HighWaterMarks | None = None,
    ) -> None:
        self.cfg = cfg
        self.topics = topics
        self._wall_time_s = wall_time_s
        self._throttle = throttle
        self._event = event
        self._on_command = on_command
        self._on_leader_position = on_leader_position
        self._on_neighbour_pose = on_neighbour_pose
        self._neighbour_topics = {Topics(cfg.topic_prefix, n).pose: n for n in neighbour_ids}
        self._verifier: CommandVerifier | None = None
        if cfg.command_topic:
            if credentials.command_keys is None:
                raise ValueError("command_topic needs the operators' command keys")
            self._verifier = CommandVerifier(
                credentials.command_keys,
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
            credentials.formation_keys,
        )
        self.commands_accepted = 0
        self.commands_rejected = 0
        self.leader_positions = 0
        #: Inbound messages dropped before parsing (too large, or the queue full), and handler failures.
        self.inbound_dropped = 0
        self.inbound_errors = 0

    def subscriptions(self) -> list[tuple[str, int]]:
        """(topic, QoS) to subscribe to on every connection."""
        subs = [(self.topics.cmd, 1)] if self._verifier is not None else []
        if self._on_leader_position is not None:
            subs.append((self.cfg.leader_topic, 0))
        if self._on_neighbour_pose is not None:
            subs += [(topic, 0) for topic in self._neighbour_topics]
        return subs

    def stats(self) -> dict[str, Any]:
        return {
            "commands_accepted": self.commands_accepted,
            "commands_rejected": self.commands_rejected,
            "shares_accepted": self.shares.accepted,
            "shares_rejected": dict(self.shares.rejected),
            "inbound_dropped": self.inbound_dropped,
            "inbound_errors": self.inbound_errors,
        }

    async def handle(self, topic: str, raw: bytes) -> None:
        """One message off the broker, inside the boundary to untrusted input."""
        try:
            await self._dispatch(topic, raw)
        except Exception as exc:
            # Whatever a payload does to a handler, the receive loop (and so the connection and its
            # subscriptions) lives on. A retained payload that broke it would otherwise come back on every
            # reconnect.
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
            self._event(
                "share_rejected",
                f"{what} on {topic} dropped: {exc}",
                "warning",
                reason=exc.reason,
                topic=topic,
                suppressed=suppressed,
            )

    def drop(self, topic: str, size: int, why: str) -> None:
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
            text = f"message on {topic[:80]} dropped: {INBOUND_QUEUE} messages already waiting"
        log.warning("MQTT: %s%s", text, and_more(suppressed))
        kind = "command_rejected" if topic == self.topics.cmd else "inbound_dropped"
        self._event(kind, text, "warning", reason=why.upper(), suppressed=suppressed)

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
                self._event(
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
            self._event(
                "command_rejected",
                f"cannot keep the command's time: {exc.strerror}",
                "error",
                reason=RejectReason.REPLAYED.name,
            )
            return
        self.commands_accepted += 1
        answer = self._on_command(cmd)
        verdict = await answer if inspect.isawaitable(answer) else answer  # once the mission has acted
        (log.info if verdict.taken else log.warning)(
            "MQTT: command %s from %s: %s", cmd.name.value, cmd.key_id, verdict
        )
        data = {"cmd": cmd.name.value, "key_id": cmd.key_id, "nonce": cmd.nonce}
        if verdict.taken:
            self._event("command", str(verdict), "notice", **data)
        else:
            self._event("command_refused", str(verdict), "warning", **data)
