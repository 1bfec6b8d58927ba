"""MAVLink 2 signing on raw frames, checked against pymavlink's own implementation in both directions."""

from __future__ import annotations

import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import common as mavlink

from companion.vehicle.mavlink_signing import (
    NEW_STREAM_WINDOW,
    Signer,
    SigningClock,
    TimestampStore,
    Verdict,
    Verifier,
    crc_ok,
    heartbeat_armed,
    load_key,
    parse_header,
    split_frames,
    take_stream_frames,
    unix_to_units,
    x25_crc,
)

KEY = bytes(range(32))
NOW = 1_800_000_000.0


def packer(sys_id: int = 2, comp_id: int = 195, key: bytes | None = None, ts: int = 0) -> mavlink.MAVLink:
    mav = mavlink.MAVLink(None, srcSystem=sys_id, srcComponent=comp_id)
    if key is not None:
        mav.signing.secret_key = key
        mav.signing.sign_outgoing = True
        mav.signing.timestamp = ts
    return mav


def land(mav: mavlink.MAVLink) -> bytes:
    return bytes(mavlink.MAVLink_command_long_message(2, 1, 21, 0, 0, 0, 0, 0, 0, 0, 0).pack(mav))


def reader(key: bytes, ts: int = 0) -> mavlink.MAVLink:
    mav = mavlink.MAVLink(None)
    mav.signing.secret_key = key
    mav.signing.timestamp = ts
    return mav


@given(st.binary(max_size=300))
def test_x25_matches_pymavlink(data: bytes) -> None:
    assert x25_crc(data) == mavlink.x25crc(data).crc


def test_our_signature_verifies_in_pymavlink_and_a_wrong_key_fails() -> None:
    signer = Signer(KEY, SigningClock())
    signed = signer.sign(land(packer()), NOW)
    assert signed is not None
    msgs = reader(KEY, unix_to_units(NOW)).parse_buffer(signed)
    assert msgs is not None
    assert msgs[0].get_type() == "COMMAND_LONG"
    assert msgs[0].command == 21
    with pytest.raises(mavlink.MAVError, match="Invalid signature"):
        reader(b"\x01" * 32).parse_buffer(signed)


def test_pymavlink_signatures_verify_here_once() -> None:
    clock = SigningClock(unix_to_units(NOW))
    verifier = Verifier(KEY, clock)
    frame = land(packer(key=KEY, ts=unix_to_units(NOW) + 5))
    info = parse_header(frame)
    assert info is not None
    assert info.signed
    assert crc_ok(frame, info)
    assert verifier.check(frame, info) is Verdict.OK
    assert clock.timestamp == unix_to_units(NOW) + 5  # lifted to the sender's
    assert verifier.check(frame, info) is Verdict.REPLAYED
    tampered = frame[:12] + bytes([frame[12] ^ 1]) + frame[13:]
    info_t = parse_header(tampered)
    assert info_t is not None
    assert Verifier(KEY, SigningClock()).check(tampered, info_t) is Verdict.BAD_SIGNATURE
    old = land(packer(sys_id=9, key=KEY, ts=clock.timestamp - NEW_STREAM_WINDOW - 1))
    info_o = parse_header(old)
    assert info_o is not None
    assert verifier.check(old, info_o) is Verdict.STALE_STREAM
    unsigned = land(packer())
    info_u = parse_header(unsigned)
    assert info_u is not None
    assert verifier.check(unsigned, info_u) is Verdict.UNSIGNED


def test_a_forged_frame_does_not_move_the_stream() -> None:
    """pymavlink moves a stream's timestamp before it checks the signature; a forgery could lock it out."""
    verifier = Verifier(KEY, SigningClock(unix_to_units(NOW)))
    far = land(packer(key=b"\x02" * 32, ts=unix_to_units(NOW) + 10**9))
    info = parse_header(far)
    assert info is not None
    assert verifier.check(far, info) is Verdict.BAD_SIGNATURE
    real = land(packer(key=KEY, ts=unix_to_units(NOW) + 1))
    info_r = parse_header(real)
    assert info_r is not None
    assert verifier.check(real, info_r) is Verdict.OK


def test_timestamps_only_go_up_and_follow_the_wall_clock() -> None:
    clock = SigningClock()
    signer = Signer(KEY, clock)
    stamps = []
    for _ in range(3):
        signed = signer.sign(land(packer()), NOW)
        assert signed is not None
        stamps.append(int.from_bytes(signed[-12:-6], "little"))
    assert stamps == [unix_to_units(NOW), unix_to_units(NOW) + 1, unix_to_units(NOW) + 2]
    signed = signer.sign(land(packer()), NOW - 3600)  # the clock stepped back an hour
    assert signed is not None
    assert int.from_bytes(signed[-12:-6], "little") == stamps[-1] + 1


def test_the_stored_timestamp_is_a_floor_after_a_restart(tmp_path: Path) -> None:
    store = TimestampStore(tmp_path / "state" / "ts", save_every_s=10.0)
    assert store.floor() == 0
    store.save(12345)
    assert store.floor() == 12345 + 10 * 100_000
    (tmp_path / "state" / "ts").write_text("garbage")
    with pytest.raises(ValueError, match="invalid literal"):
        store.floor()


def test_an_unknown_message_is_signed_with_its_crc_extra_recovered() -> None:
    frame = bytearray(land(packer()))
    frame[7:10] = (60_000).to_bytes(3, "little")  # not in the common dialect
    crc = x25_crc(bytes((99,)), x25_crc(bytes(frame[1:-2])))
    frame[-2:] = crc.to_bytes(2, "little")
    signed = Signer(KEY, SigningClock()).sign(bytes(frame), NOW)
    assert signed is not None
    info = parse_header(signed)
    assert info is not None
    end = 10 + len(info.payload)
    assert x25_crc(bytes((99,)), x25_crc(signed[1:end])) == int.from_bytes(signed[end : end + 2], "little")


def test_framing_datagrams_and_streams() -> None:
    a, b = land(packer()), land(packer(sys_id=3))
    frames, tail, junk = split_frames(b"\x00junk" + a + b + a[:7])
    assert frames == [a, b]
    assert tail == a[:7]
    assert junk == 5
    # A start marker in noise with a length that would swallow the next frame: skipped on a stream.
    noise = b"\xfd\x40\x00\x00\x00\x00\x00\x00\x00\x00"
    frames, rest = take_stream_frames(noise + a + b + a[:5])
    assert frames == [a, b]
    assert rest == a[:5]


@settings(max_examples=200)
@given(st.binary(max_size=400))
def test_stream_framing_never_raises(data: bytes) -> None:
    frames, rest = take_stream_frames(data)
    assert sum(len(f) for f in frames) + len(rest) <= len(data)


def test_heartbeat_armed_flag() -> None:
    hb = mavlink.MAVLink_heartbeat_message(2, 12, mavlink.MAV_MODE_FLAG_SAFETY_ARMED | 1, 0, 4, 3)
    info = parse_header(bytes(hb.pack(packer(comp_id=1))))
    assert info is not None
    assert heartbeat_armed(info)
    hb = mavlink.MAVLink_heartbeat_message(2, 12, 1, 0, 3, 3)
    info = parse_header(bytes(hb.pack(packer(comp_id=1))))
    assert info is not None
    assert not heartbeat_armed(info)


def test_key_files(tmp_path: Path) -> None:
    raw = tmp_path / "raw.key"
    raw.write_bytes(KEY)
    raw.chmod(0o600)
    assert load_key(raw) == KEY
    hexed = tmp_path / "hex.key"
    hexed.write_text(KEY.hex() + "\n")
    hexed.chmod(0o600)
    assert load_key(hexed) == KEY
    hexed.chmod(0o644)
    with pytest.raises(PermissionError):
        load_key(hexed)
    short = tmp_path / "short.key"
    short.write_bytes(b"x" * 16)
    short.chmod(0o600)
    with pytest.raises(ValueError, match="32 raw bytes or 64"):
        load_key(short)


def test_sign_and_verify_cost_per_setpoint() -> None:
    """The figure docs/service.md quotes: median cost of signing and checking one setpoint frame."""
    mav = packer()
    sp = bytes(
        mavlink.MAVLink_set_position_target_local_ned_message(
            0, 2, 1, 8, 0b0000_0101_1100_0111, 0, 0, 0, 1.0, 0.5, -0.1, 0, 0, 0, 0, 0.2
        ).pack(mav)
    )
    clock = SigningClock()
    signer, verifier = Signer(KEY, clock), Verifier(KEY, SigningClock())
    costs = []
    for _ in range(2000):
        t0 = time.perf_counter()
        signed = signer.sign(sp, NOW)
        assert signed is not None
        info = parse_header(signed)
        assert info is not None
        assert crc_ok(signed, info)
        assert verifier.check(signed, info) is Verdict.OK
        costs.append(time.perf_counter() - t0)
    costs.sort()
    median_us = costs[len(costs) // 2] * 1e6
    print(f"\nsign + verify one SET_POSITION_TARGET_LOCAL_NED: median {median_us:.1f} us (2000 frames)")
    assert median_us < 2000  # a generous bound; the figure itself is what the docs quote
