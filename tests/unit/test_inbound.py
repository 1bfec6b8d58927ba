"""Untrusted MQTT input: bounded parsing, keyrings, signed commands with persisted replay marks, shares."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.mission.types import OperatorCommand
from companion.telemetry.commands import (
    CommandRejectedError,
    CommandVerifier,
    HighWaterMarks,
    RejectReason,
    sign_command,
)
from companion.telemetry.inbound import (
    InboundRejectedError,
    Keyring,
    format_keyring,
    parse_keyring,
    parse_object,
    read_secret,
    sign,
    topic_matches,
)
from companion.telemetry.shares import SHARE_DOMAIN, ShareGate, ShareLimits, sign_share

ALICE = b"a" * 32
BOB = b"b" * 32
RING = Keyring({"alice": ALICE, "bob": BOB})
TOPIC = "wingman/f1/cmd"


def cmd(**kw: object) -> dict[str, Any]:
    return {"cmd": "land", "time_unix_s": 1000.0, **kw}


def verifier(marks: HighWaterMarks | None = None, topic: str = TOPIC) -> CommandVerifier:
    return CommandVerifier(RING, topic, max_age_s=30.0, marks=marks)


# ---------------------------------------------------------------------- parsing
HOSTILE = [
    b"[" * 100_000,
    b"{" * 100_000,
    b'{"a":' * 5000,
    b"[" * 20 + b"]" * 20,
    b'{"x": NaN}',
    b'{"x": Infinity}',
    b'{"x": -Infinity}',
    b'{"x": 1e999}',
    b'{"x": ' + b"9" * 5000 + b"}",
    b'{"x": ' + b"9" * 400 + b"}",
    b"\xff\xfe\x00",
    b"",
    b"null",
    b'"string"',
    b"\x00" * 100,
    b'{"cmd": "land"' + b" " * 10_000 + b"}",
]


@pytest.mark.parametrize("raw", HOSTILE, ids=range(len(HOSTILE)))
def test_parse_object_rejects_hostile_payloads_and_raises_nothing_else(raw: bytes) -> None:
    with pytest.raises(InboundRejectedError):
        parse_object(raw, 4096)


@settings(max_examples=500)
@given(st.binary(max_size=600) | st.text(alphabet='[]{}",:0123456789.eE-+naNIfity \\u', max_size=300))
def test_parse_object_never_raises_anything_but_a_rejection(raw: bytes | str) -> None:
    data = raw.encode() if isinstance(raw, str) else raw
    try:
        out = parse_object(data, 512)
    except InboundRejectedError:
        return
    assert isinstance(out, dict)


def test_parse_object_keeps_ordinary_json() -> None:
    assert parse_object(b'{"a": [1, 2.5, {"b": null}], "c": "d"}', 4096) == {
        "a": [1, 2.5, {"b": None}],
        "c": "d",
    }


# ---------------------------------------------------------------------- keyrings and secrets
def test_keyring_file_round_trip_and_its_errors() -> None:
    text = "# operators\n" + format_keyring([("alice", ALICE), ("bob", BOB)]) + "\n"
    assert parse_keyring(text).keys == {"alice": ALICE, "bob": BOB}
    assert parse_keyring(text).signing_id == "alice"
    for bad, why in [
        ("", "no keys"),
        ("alice zz\n", "not hexadecimal"),
        ("alice 00\n", "at least 16 bytes"),
        (f"alice {ALICE.hex()}\nalice {BOB.hex()}\n", "twice"),
        ("alice\n", "KEY_ID HEX_KEY"),
        (f"al ice {ALICE.hex()}\n", "not hexadecimal"),
        (f"al/ice {ALICE.hex()}\n", "key id"),
    ]:
        with pytest.raises(ValueError, match=why):
            parse_keyring(bad)


def test_a_secret_readable_by_others_is_refused(tmp_path: Path) -> None:
    f = tmp_path / "key"
    f.write_bytes(b"secret")
    f.chmod(0o644)
    with pytest.raises(PermissionError, match="chmod 600"):
        read_secret(f)
    f.chmod(0o640)
    with pytest.raises(PermissionError):
        read_secret(f)
    f.chmod(0o600)
    assert read_secret(f) == b"secret"


# ---------------------------------------------------------------------- commands
def test_a_signed_command_is_accepted_once_and_forgeries_are_refused() -> None:
    v = verifier()
    ok = v.verify(sign_command(ALICE, "alice", TOPIC, cmd(nonce="n1")), now_unix_s=1010.0)
    assert (ok.name, ok.key_id, ok.nonce) == (OperatorCommand.LAND, "alice", "n1")
    cases = [
        (sign_command(ALICE, "alice", TOPIC, cmd()), RejectReason.REPLAYED),
        (sign_command(ALICE, "alice", TOPIC, cmd(time_unix_s=999.0)), RejectReason.REPLAYED),
        (sign_command(b"z" * 32, "alice", TOPIC, cmd(time_unix_s=1001.0)), RejectReason.BAD_MAC),
        (sign_command(ALICE, "bob", TOPIC, cmd(time_unix_s=1001.0)), RejectReason.BAD_MAC),
        (sign_command(ALICE, "mallory", TOPIC, cmd(time_unix_s=1001.0)), RejectReason.BAD_MAC),
        # Signed for another vehicle's topic: refused here.
        (sign_command(ALICE, "alice", "wingman/f2/cmd", cmd(time_unix_s=1001.0)), RejectReason.BAD_MAC),
        (sign_command(ALICE, "alice", TOPIC, cmd(time_unix_s=900.0)), RejectReason.EXPIRED),
        (sign_command(ALICE, "alice", TOPIC, cmd(time_unix_s=1002.0, cmd="x")), RejectReason.UNKNOWN_COMMAND),
        # A start is the status socket's only (``companion start``), never MQTT's.
        (
            sign_command(ALICE, "alice", TOPIC, cmd(time_unix_s=1002.0, cmd="start")),
            RejectReason.UNKNOWN_COMMAND,
        ),
        (
            sign_command(
                ALICE, "alice", TOPIC, cmd(time_unix_s=1003.0, cmd="set_offset", offset_cam_m=[0, 0])
            ),
            RejectReason.BAD_ARGUMENTS,
        ),
        (b"[1, 2]", RejectReason.MALFORMED),
        (b"\xff\xfe", RejectReason.MALFORMED),
        (b"[" * 100_000, RejectReason.TOO_LARGE),
        (b"[" * 4000, RejectReason.MALFORMED),
    ]
    for raw, reason in cases:
        with pytest.raises(CommandRejectedError) as exc:
            v.verify(raw, now_unix_s=1010.0)
        assert exc.value.reason is reason, raw[:80]
    # Tampering with a signed field breaks the MAC.
    tampered = sign_command(ALICE, "alice", TOPIC, cmd(time_unix_s=1004.0, cmd="hold")).replace(
        b'"hold"', b'"land"'
    )
    with pytest.raises(CommandRejectedError, match="authentication"):
        v.verify(tampered, now_unix_s=1010.0)
    # Bob has his own mark: his older time is still new for him.
    assert v.verify(sign_command(BOB, "bob", TOPIC, cmd(time_unix_s=1000.5)), 1010.0).key_id == "bob"
    ok = v.verify(
        sign_command(
            ALICE, "alice", TOPIC, cmd(time_unix_s=1005.0, cmd="set_offset", offset_cam_m=[0.5, 0, 6])
        ),
        1010.0,
    )
    assert ok.offset_cam_m == (0.5, 0.0, 6.0)


def test_revoking_an_operator_is_deleting_their_line() -> None:
    raw = sign_command(BOB, "bob", TOPIC, cmd())
    assert verifier().verify(raw, 1000.0).key_id == "bob"
    without_bob = CommandVerifier(Keyring({"alice": ALICE}), TOPIC, max_age_s=30.0)
    with pytest.raises(CommandRejectedError, match="authentication"):
        without_bob.verify(raw, 1000.0)


def test_high_water_marks_survive_a_restart(tmp_path: Path) -> None:
    path = tmp_path / "state" / "marks.json"
    raw = sign_command(ALICE, "alice", TOPIC, cmd(time_unix_s=time.time()))
    first = verifier(HighWaterMarks(path))
    first.verify(raw, time.time())
    first.marks.save()
    assert json.loads(path.read_text())["alice"] == pytest.approx(json.loads(raw)["time_unix_s"])
    restarted = verifier(HighWaterMarks(path))
    with pytest.raises(CommandRejectedError) as exc:
        restarted.verify(raw, time.time())
    assert exc.value.reason is RejectReason.REPLAYED
    assert not [p for p in path.parent.iterdir() if p.name.startswith(".high-water")]  # no temp left


def test_a_corrupt_marks_file_is_an_error_not_a_fresh_start(tmp_path: Path) -> None:
    path = tmp_path / "marks.json"
    for text in ("{", '["alice"]', '{"alice": "soon"}'):
        path.write_text(text)
        with pytest.raises(ValueError, match=r"Expecting|expected an object"):
            HighWaterMarks(path)


@settings(max_examples=300)
@given(
    st.dictionaries(
        st.sampled_from(["cmd", "time_unix_s", "key_id", "mac", "nonce", "offset_cam_m"]),
        st.one_of(
            st.none(),
            st.booleans(),
            st.integers(-(10**20), 10**20),
            st.floats(allow_nan=False, allow_infinity=False),
            st.text(max_size=20),
            st.lists(st.floats(-100, 100), max_size=4),
        ),
    )
)
def test_the_verifier_raises_only_rejections(msg: dict[str, Any]) -> None:
    """Whatever the fields hold (huge integers, wrong types), the answer is a rejection with its reason."""
    with pytest.raises(CommandRejectedError) as exc:
        verifier().verify(json.dumps(msg).encode(), 1000.0)
    assert isinstance(exc.value.reason, RejectReason)


# ---------------------------------------------------------------------- shares
LEADER = "wingman/leader/position"
FORMATION = Keyring({"v1": b"f" * 32})


class Wall:
    def __init__(self, t: float) -> None:
        self.t = t

    def __call__(self) -> float:
        return self.t


def leader(t: float, lat: float = 47.4, **kw: Any) -> dict[str, Any]:
    return {"lat_deg": lat, "lon_deg": 8.5, "alt_amsl_m": 500.0, "time_unix_s": t, **kw}


def test_shares_are_signed_checked_and_counted() -> None:
    wall = Wall(1000.0)
    gate = ShareGate(ShareLimits(), wall, FORMATION)
    ok = gate.leader_position(LEADER, sign_share(FORMATION, LEADER, leader(1000.0, yaw_deg=10.0)))
    assert ok.yaw_deg == 10.0
    wall.t = 1000.1
    bad = [
        (json.dumps(leader(1000.1)).encode(), "malformed"),  # unsigned
        (sign_share(Keyring({"v1": b"x" * 32}), LEADER, leader(1000.1)), "bad_mac"),
        (sign_share(FORMATION, "wingman/f2/pose", leader(1000.1)), "bad_mac"),
        (sign_share(FORMATION, LEADER, leader(1000.1, v_ned_m_s=[1e308, 0, 0])), "implausible"),
        (sign_share(FORMATION, LEADER, leader(9e18)), "future"),
        (sign_share(FORMATION, LEADER, leader(990.0)), "stale"),
        (sign_share(FORMATION, LEADER, leader(1000.0)), "replayed"),
        (sign_share(FORMATION, LEADER, leader(1000.1, lat=47.5)), "jump"),  # 11 km in 0.1 s
        (sign_share(FORMATION, LEADER, leader(1000.1, lat=91.0)), "malformed"),
        (b'{"lat_deg": NaN, "lon_deg": Infinity, "alt_amsl_m": 1e308, "time_unix_s": 1000.1}', "malformed"),
        (b"[" * 100_000, "too_large"),
    ]
    for raw, reason in bad:
        with pytest.raises(InboundRejectedError) as exc:
            gate.leader_position(LEADER, raw)
        assert exc.value.reason == reason, raw[:80]
    assert gate.leader_position(LEADER, sign_share(FORMATION, LEADER, leader(1000.1, lat=47.40001))).lat_deg
    assert gate.accepted == 2
    assert sum(gate.rejected.values()) == len(bad)


def test_neighbour_poses_need_finite_plausible_values() -> None:
    wall = Wall(1000.0)
    gate = ShareGate(ShareLimits(), wall, None)  # no formation key: checked, not authenticated
    topic = "wingman/f2/pose"
    pose = {"p_ned_m": [1.0, 2.0, -5.0], "lat_deg": 47.4, "lon_deg": 8.5, "alt_amsl_m": 500.0}
    assert gate.neighbour_pose(topic, json.dumps({**pose, "time_unix_s": 1000.0}).encode()).p_ned_m
    for body, reason in [
        ({**pose, "time_unix_s": 1000.1, "p_ned_m": [1e308, 0.0, 0.0]}, "implausible"),
        ({**pose, "time_unix_s": 1000.1, "v_ned_m_s": [0.0, 99.0, 0.0]}, "implausible"),
        ({**pose, "time_unix_s": 1000.1, "alt_amsl_m": -9000.0}, "implausible"),
        ({**pose}, "malformed"),
        ({**pose, "time_unix_s": 1000.1, "unknown": 1}, "malformed"),
    ]:
        with pytest.raises(InboundRejectedError) as exc:
            gate.neighbour_pose(topic, json.dumps(body).encode())
        assert exc.value.reason == reason, body


def test_a_sender_is_held_to_its_last_share_however_long_it_was_silent() -> None:
    wall = Wall(1000.0)
    gate = ShareGate(ShareLimits(), wall, None)
    gate.leader_position(LEADER, json.dumps(leader(1000.0)).encode())
    # A forged 50 km jump after 2.01 s of silence (past max_age_s) is refused; the real leader goes on.
    wall.t = 1002.01
    with pytest.raises(InboundRejectedError) as exc:
        gate.leader_position(LEADER, json.dumps(leader(1002.01, lat=47.85)).encode())
    assert exc.value.reason == "jump"
    wall.t = 1002.11
    assert gate.leader_position(LEADER, json.dumps(leader(1002.11, lat=47.4001)).encode()).lat_deg == 47.4001
    # After 10 s, 11 km is still too far (30 m/s); after 400 s it is not.
    wall.t = 1012.11
    with pytest.raises(InboundRejectedError):
        gate.leader_position(LEADER, json.dumps(leader(1012.11, lat=47.5)).encode())
    wall.t = 1402.11
    assert gate.leader_position(LEADER, json.dumps(leader(1402.11, lat=47.5)).encode()).lat_deg == 47.5


def test_a_share_stamped_ahead_is_not_accepted_twice() -> None:
    wall = Wall(1000.0)
    gate = ShareGate(ShareLimits(), wall, None)
    ahead = json.dumps(leader(1000.5)).encode()
    gate.leader_position(LEADER, ahead)
    wall.t = 1002.2
    with pytest.raises(InboundRejectedError) as exc:
        gate.leader_position(LEADER, ahead)
    assert exc.value.reason == "replayed"


@pytest.mark.parametrize("key_id", ["v1", "unknown"])
@pytest.mark.parametrize("mac", ["\u00e9" * 64, "0" * 63, "g" * 64, "0" * 65, ""])
def test_a_mac_that_is_not_64_hex_digits_is_refused_alike_for_every_key_id(key_id: str, mac: str) -> None:
    with pytest.raises(InboundRejectedError) as exc:
        FORMATION.verify(b"d", LEADER, {"time_unix_s": 1.0, "key_id": key_id, "mac": mac})
    assert (exc.value.reason, exc.value.detail) == ("malformed", "mac must be 64 hexadecimal digits")


def test_a_key_bound_to_its_vehicles_topics_signs_nothing_else() -> None:
    """Per-vehicle keys: follower1's key cannot sign the leader's position, nor another follower's pose."""
    leader_key, f1_key = b"L" * 32, b"1" * 32
    ring = parse_keyring(
        f"leader {leader_key.hex()} wingman/leader/#  # the leader's publisher\n"
        f"follower1 {f1_key.hex()} wingman/follower1/pose\n"
    )
    assert ring.topics == {"leader": ("wingman/leader/#",), "follower1": ("wingman/follower1/pose",)}
    wall = Wall(1000.0)
    gate = ShareGate(ShareLimits(), wall, ring)
    forged = sign(f1_key, "follower1", SHARE_DOMAIN, LEADER, leader(1000.0))
    with pytest.raises(InboundRejectedError) as exc:
        gate.leader_position(LEADER, forged)
    assert exc.value.reason == "wrong_topic"
    assert gate.leader_position(LEADER, sign(leader_key, "leader", SHARE_DOMAIN, LEADER, leader(1000.0)))
    pose = {"p_ned_m": [1.0, 2.0, -5.0], "time_unix_s": 1000.0}
    own = sign(f1_key, "follower1", SHARE_DOMAIN, "wingman/follower1/pose", pose)
    assert gate.neighbour_pose("wingman/follower1/pose", own).p_ned_m
    with pytest.raises(InboundRejectedError):
        gate.neighbour_pose(
            "wingman/f2/pose", sign(f1_key, "follower1", SHARE_DOMAIN, "wingman/f2/pose", pose)
        )


@pytest.mark.parametrize(
    ("topic_filter", "topic", "expected"),
    [
        ("wingman/leader/#", "wingman/leader/position", True),
        ("wingman/+/pose", "wingman/f2/pose", True),
        ("wingman/f1/pose", "wingman/f1/pose", True),
        ("wingman/f1/pose", "wingman/f1/pose/x", False),
        ("wingman/+/pose", "wingman/f2/cmd", False),
        ("wingman/leader/#", "wingman/leaderx/position", False),
    ],
)
def test_topic_filters(topic_filter: str, topic: str, expected: bool) -> None:
    assert topic_matches(topic_filter, topic) is expected
