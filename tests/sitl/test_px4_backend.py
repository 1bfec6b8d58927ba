"""The PX4 backend without PX4: finding a build, what a scenario may ask of it, its display link's parsing."""

from __future__ import annotations

import socket
import stat
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mavlink

from companion.lab.evaluation.realpath import read_autopilot_log
from sitl.px4.instance import (
    Px4Build,
    Px4NotFoundError,
    Px4Ports,
    Px4StartError,
    free_instance_base,
    param_env,
)
from sitl.px4.link import Px4Link
from sitl.px4.world import mode_name, unsupported
from sitl.world.scenario import Scenario


def _fake_build(root: Path, *, with_rcs: bool = True) -> Path:
    binary = root / "bin" / "px4"
    binary.parent.mkdir(parents=True)
    binary.write_text("#!/bin/sh\n")
    binary.chmod(binary.stat().st_mode | stat.S_IXUSR)
    (root / "bin" / "px4-commander").write_text("px4")
    (root / "bin" / "px4-alias.sh").write_text("")
    if with_rcs:
        (root / "etc" / "init.d-posix").mkdir(parents=True)
        (root / "etc" / "init.d-posix" / "rcS").write_text("")
    return binary


def test_a_build_is_its_binary_with_etc_beside_bin(tmp_path: Path) -> None:
    binary = _fake_build(tmp_path)
    build = Px4Build.locate(str(binary))
    assert build.etc_dir == tmp_path / "etc"
    assert build.modules() == ["px4-commander"]


@pytest.mark.parametrize(
    ("setup", "words"),
    [
        ("missing", "not found on PATH"),
        ("not_executable", "is not an executable file"),
        ("no_etc", "is not a PX4 SITL build"),
    ],
)
def test_a_wrong_build_is_one_line_naming_the_setting(tmp_path: Path, setup: str, words: str) -> None:
    if setup == "missing":
        name = "no-such-px4-binary"
    elif setup == "not_executable":
        path = tmp_path / "px4"
        path.write_text("")
        name = str(path)
    else:
        name = str(_fake_build(tmp_path, with_rcs=False))
    with pytest.raises(Px4NotFoundError) as info:
        Px4Build.locate(name)
    line = str(info.value)
    assert words in line
    assert "\n" not in line
    if setup != "no_etc":
        assert "SITL_PX4__BINARY" in line


def test_parameters_go_to_the_startup_script_as_px4_param_variables() -> None:
    assert param_env({"MAV_SYS_ID": 2.0, "SIH_LOC_LAT0": 47.5}) == {
        "PX4_PARAM_MAV_SYS_ID": "2",
        "PX4_PARAM_SIH_LOC_LAT0": "47.5",
    }
    with pytest.raises(Px4StartError, match="not finite"):
        param_env({"SIH_WIND_N": float("nan")})


def test_instance_numbers_skip_a_taken_port() -> None:
    base = free_instance_base(2)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("0.0.0.0", Px4Ports(base).api_remote))  # noqa: S104 (as MAVSDK binds)
        assert free_instance_base(2) > base


def test_what_px4_cannot_simulate_is_refused_by_name() -> None:
    sc = Scenario.model_validate(
        {
            "name": "t",
            "vehicles": {
                "follower": {
                    "gps": {"outages": [{"at_s": 5.0, "kind": "stuck"}, {"at_s": 9.0, "kind": "off"}]},
                    "link": {"loss": 0.1},
                }
            },
        }
    )
    problems = unsupported(sc)
    assert len(problems) == 2
    assert any("'stuck'" in p for p in problems)
    assert any("link faults" in p for p in problems)
    ok = Scenario.model_validate(
        {"name": "t", "vehicles": {"follower": {"gps": {"outages": [{"at_s": 5.0}]}}}}
    )
    assert unsupported(ok) == []


def test_px4_mode_names_from_the_heartbeat() -> None:
    assert mode_name(6 << 16) == "Offboard"
    assert mode_name((4 << 16) | (3 << 24)) == "Hold"
    assert mode_name((4 << 16) | (6 << 24)) == "Land"
    assert mode_name(2 << 16) == "Altitude"


def _pack(msg: object, sysid: int) -> bytes:
    return msg.pack(mavlink.MAVLink(None, srcSystem=sysid, srcComponent=1))  # type: ignore[attr-defined,no-any-return]


def test_the_display_link_keeps_truth_clock_and_texts_of_its_own_vehicle_only() -> None:
    link = Px4Link("follower", 2, 19451, 19411)
    ticks: list[float] = []
    link.on_clock.append(ticks.append)
    clock = mavlink.MAVLink_hil_actuator_controls_message(12_345_678, [0.0] * 16, 0, 0)
    truth = mavlink.MAVLink_hil_state_quaternion_message(
        0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.1, 473977420, 85455940, 493_000, 200, -100, 0, 0, 0, 0, 0, 0
    )
    text = mavlink.MAVLink_statustext_message(2, b"Failsafe activated", 0, 0)
    other = mavlink.MAVLink_statustext_message(2, b"not mine", 0, 0)
    link.datagram_received(_pack(clock, 2) + _pack(truth, 2) + _pack(text, 2) + _pack(other, 1))
    assert ticks == [pytest.approx(12.345678)]
    assert link.truth is not None
    assert link.truth.time_s == pytest.approx(12.345678)
    assert link.truth.lat_deg == pytest.approx(47.397742)
    assert link.truth.alt_m == pytest.approx(493.0)
    assert link.truth.v_ned_m_s == pytest.approx((2.0, -1.0, 0.0))
    assert [t.text for t in link.texts] == ["Failsafe activated"]
    link.datagram_received(b"\xfd\x09junk that is not mavlink")
    assert link.truth.time_s == pytest.approx(12.345678)


def test_the_report_names_failsafes_the_service_did_not_ask_for(tmp_path: Path) -> None:
    log = tmp_path / "autopilot.jsonl"
    log.write_text(
        '{"t_s": 1.0, "vehicle": "follower", "mode": "Offboard", "armed": true}\n'
        '{"t_s": 2.0, "vehicle": "follower", "severity": "critical", "text": "Failsafe activated"}\n'
        '{"t_s": 2.0, "vehicle": "leader", "severity": "critical", "text": "Failsafe activated"}\n'
        "not json\n"
    )
    (tmp_path / "px4-follower-0.ulg").write_bytes(b"ULog")
    ap = read_autopilot_log(log, "px4", tmp_path)
    assert [m["mode"] for m in ap["follower_modes"]] == ["Offboard"]
    assert [f["t_s"] for f in ap["follower_failsafes"]] == [2.0]
    assert ap["flight_logs"] == [str(tmp_path / "px4-follower-0.ulg")]
