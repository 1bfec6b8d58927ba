"""What arrives over MQTT, before anything trusts it: bounded parsing, keyrings and message authentication.

Any client of the broker can publish anything on any topic it may write, retained or not, so a payload
is untrusted bytes until its MAC checks out. :func:`parse_object` is the only JSON parse of such bytes:
it refuses a payload above its size bound before reading it, bounds the nesting (deep ``[[[[`` would
otherwise raise RecursionError out of ``json``), and refuses ``NaN``, ``Infinity``, numbers that
overflow to infinity and integers beyond 1e15 (which ``float()`` may not convert). It raises
:class:`InboundRejectedError` and nothing else.

Authentication: HMAC-SHA256 over a domain tag, the topic the message arrived on (which names the
vehicle) and the canonical JSON of every field but ``mac`` (sorted keys, no spaces). A message signed for
one vehicle or topic fails on any other. Keys live in a :class:`Keyring` (one line per key:
``KEY_ID HEX_KEY``), and a message names its key with ``key_id``: deleting a line revokes one key.
"""

from __future__ import annotations

import hashlib
import hmac
import json
import math
import re
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from companion.kernel.secret_files import read_secret

__all__ = [
    "MIN_KEY_BYTES",
    "InboundRejectedError",
    "Keyring",
    "canonical_body",
    "format_keyring",
    "mac_hex",
    "parse_keyring",
    "parse_object",
    "read_secret",
    "sign",
    "topic_matches",
]

#: A shorter key is guessable; 32 random bytes is what the docs tell operators to generate.
MIN_KEY_BYTES = 16
#: JSON containers allowed in one inbound message: commands and shares need a handful. Counting the
#: brackets bounds the nesting depth without parsing.
MAX_CONTAINERS = 32
_KEY_ID = re.compile(r"^[A-Za-z0-9_.-]{1,32}$")
#: A MAC as messages carry it: HMAC-SHA256 in hexadecimal.
_MAC_HEX = re.compile(r"[0-9a-fA-F]{64}")
_COMMENT = re.compile(r"(^|\s)#.*$")


class InboundRejectedError(Exception):
    """An inbound payload that is not used; ``reason`` is a short word for counters and events."""

    def __init__(self, reason: str, detail: str = "") -> None:
        self.reason = reason
        self.detail = detail
        super().__init__(reason + (f": {detail}" if detail else ""))


def _finite_float(text: str) -> float:
    value = float(text)
    if not math.isfinite(value):
        raise ValueError(f"number out of range: {text[:20]}")
    return value


def _bounded_int(text: str) -> int:
    if len(text.lstrip("-")) > 15:  # beyond 1e15 nothing here is meaningful, and float() may overflow
        raise ValueError(f"integer out of range: {text[:20]}")
    return int(text)


def _no_constant(text: str) -> float:
    raise ValueError(f"{text} is not a number")


def parse_object(raw: bytes, max_bytes: int) -> dict[str, Any]:
    """A JSON object from untrusted bytes, or :class:`InboundRejectedError` (never anything else)."""
    if len(raw) > max_bytes:
        raise InboundRejectedError("too_large", f"{len(raw)} bytes > {max_bytes}")
    if raw.count(b"[") + raw.count(b"{") > MAX_CONTAINERS:
        raise InboundRejectedError("malformed", f"more than {MAX_CONTAINERS} JSON containers")
    try:
        obj = json.loads(raw, parse_float=_finite_float, parse_int=_bounded_int, parse_constant=_no_constant)
    except ValueError as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise InboundRejectedError("malformed", str(exc)[:80]) from None
    if not isinstance(obj, dict):
        raise InboundRejectedError("malformed", "not a JSON object")
    return obj


def canonical_body(message: Mapping[str, Any]) -> bytes:
    """The bytes of a message the MAC covers: every field but ``mac``, sorted keys, no spaces."""
    body = {k: v for k, v in message.items() if k != "mac"}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def mac_hex(key: bytes, domain: bytes, topic: str, message: Mapping[str, Any]) -> str:
    """HMAC-SHA256 (hex) binding the message to its kind (``domain``) and the topic it is published on."""
    data = domain + b"\x00" + topic.encode() + b"\x00" + canonical_body(message)
    return hmac.new(key, data, hashlib.sha256).hexdigest()


def sign(key: bytes, key_id: str, domain: bytes, topic: str, message: Mapping[str, Any]) -> bytes:
    """``message`` with ``key_id`` and its ``mac``, as the JSON bytes to publish on ``topic``."""
    body = {**message, "key_id": key_id}
    body.pop("mac", None)
    return json.dumps({**body, "mac": mac_hex(key, domain, topic, body)}, allow_nan=False).encode()


@dataclass(frozen=True, slots=True)
class Keyring:
    """Named keys: ``{key_id: key}``; the first is the one this side signs with.

    ``topics`` binds a key id to the topics its holder may publish (MQTT filters, ``+`` and ``#``): a
    message on any other topic is refused even with a valid MAC. A key id without topics may sign any.
    """

    keys: Mapping[str, bytes]
    topics: Mapping[str, tuple[str, ...]] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not self.keys:
            raise ValueError("a keyring needs at least one key")
        for key_id, key in self.keys.items():
            if not _KEY_ID.match(key_id):
                raise ValueError(f"key id {key_id!r}: 1-32 of A-Z a-z 0-9 _ . -")
            if len(key) < MIN_KEY_BYTES:
                raise ValueError(f"key {key_id!r}: at least {MIN_KEY_BYTES} bytes (got {len(key)})")

    @classmethod
    def single(cls, key_id: str, key: bytes) -> Keyring:
        return cls({key_id: key})

    @property
    def signing_id(self) -> str:
        return next(iter(self.keys))

    @property
    def signing_key(self) -> bytes:
        return self.keys[self.signing_id]

    def verify(self, domain: bytes, topic: str, message: Mapping[str, Any]) -> str:
        """The key id that signed ``message``; :class:`InboundRejectedError` ``bad_mac`` otherwise."""
        key_id, mac = message.get("key_id"), message.get("mac")
        if not isinstance(key_id, str) or not isinstance(mac, str):
            raise InboundRejectedError("malformed", "key_id and mac must be strings")
        # Checked before the key id is looked up, so the answer is the same for every key id.
        if not _MAC_HEX.fullmatch(mac):
            raise InboundRejectedError("malformed", "mac must be 64 hexadecimal digits")
        key = self.keys.get(key_id)
        if key is None:
            # Same answer as a wrong MAC: an outsider learns nothing about which ids exist.
            raise InboundRejectedError("bad_mac")
        try:
            expected = mac_hex(key, domain, topic, message)
        except ValueError:
            raise InboundRejectedError("malformed", "not representable as canonical JSON") from None
        if not hmac.compare_digest(bytes.fromhex(expected), bytes.fromhex(mac)):
            raise InboundRejectedError("bad_mac")
        allowed = self.topics.get(key_id)
        if allowed and not any(topic_matches(f, topic) for f in allowed):
            raise InboundRejectedError("wrong_topic", f"key {key_id} may not publish on {topic}")
        return key_id


def parse_keyring(text: str) -> Keyring:
    """``KEY_ID HEX_KEY [TOPIC ...]`` per line; comments (from a ``#`` after a space) and blank lines skipped.

    Topics after the key bind it: its holder may publish only there. ValueError on a bad line.
    """
    keys: dict[str, bytes] = {}
    topics: dict[str, tuple[str, ...]] = {}
    for n, raw_line in enumerate(text.splitlines(), start=1):
        line = _COMMENT.sub("", raw_line).strip()  # a "#" inside a topic filter (".../#") is no comment
        if not line:
            continue
        parts = line.split()
        if len(parts) < 2:
            raise ValueError(f"line {n}: expected KEY_ID HEX_KEY [TOPIC ...]")
        key_id, hex_key, *bound = parts
        if key_id in keys:
            raise ValueError(f"line {n}: key id {key_id!r} given twice")
        try:
            keys[key_id] = bytes.fromhex(hex_key)
        except ValueError:
            raise ValueError(f"line {n}: the key is not hexadecimal") from None
        if bound:
            topics[key_id] = tuple(bound)
    if not keys:
        raise ValueError("no keys in it")
    try:
        return Keyring(keys, topics)
    except ValueError as exc:
        raise ValueError(str(exc)) from None


def topic_matches(topic_filter: str, topic: str) -> bool:
    """Does ``topic`` match an MQTT filter (``+``: one level, ``#`` at the end: the rest)?"""
    want, got = topic_filter.split("/"), topic.split("/")
    for i, level in enumerate(want):
        if level == "#" and i == len(want) - 1:
            return True
        if i >= len(got) or (level != "+" and level != got[i]):
            return False
    return len(want) == len(got)


def format_keyring(keys: Iterable[tuple[str, bytes]]) -> str:
    """The text of a keyring file (what :func:`parse_keyring` reads)."""
    return "".join(f"{key_id} {key.hex()}\n" for key_id, key in keys)
