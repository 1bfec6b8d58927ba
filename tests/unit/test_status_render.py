"""``companion status``: the operator's one screen."""

from __future__ import annotations

from companion.commands.status import render_status


def test_status_shows_system_id_altitude_battery_and_formation_error() -> None:
    text = render_status(
        {
            "vehicle_id": "follower1",
            "version": "0.1.0",
            "pid": 1,
            "uptime_s": 12.0,
            "mission": {
                "state": "follow",
                "reason": "leader acquired",
                "state_age_s": 3.0,
                "formation_error_ned_m": [0.3, 0.4, 0.0],
            },
            "link": {
                "system_id": 2,
                "connected": True,
                "heartbeat_age_s": 0.1,
                "flight_mode": "offboard",
                "armed": True,
                "in_air": True,
                "offboard_loss_failsafe": "Hold",
            },
            "gps": {"fix_type": 3, "satellites": 12, "position_valid": True},
            "position": {"altitude_m": 5.04},
            "battery": {"remaining_frac": 0.815, "voltage_v": 15.62},
        }
    )
    rows = dict(line.split(None, 1) for line in text.splitlines() if line and not line.startswith(" "))
    assert rows["formation"].startswith("error 0.50 m from the slot")
    assert rows["flight"] == "altitude 5.04 m, battery 82 % (15.6 V)"
    assert rows["link"].startswith("system 2, up, ")


def test_status_says_how_old_the_leaders_share_is_and_what_is_flown_on_it() -> None:
    """The share row: its age, and whether the follower leads on its motion or flies on its position."""

    def share_row(**mission: object) -> str | None:
        text = render_status({"mission": {"state": "follow", **mission}})
        rows = dict(line.split(None, 1) for line in text.splitlines() if line and not line.startswith(" "))
        return rows.get("share")

    assert share_row() is None
    assert share_row(leader_share_age_s=0.062, led_on_leader_share=True) == (
        "leader's last share 62 ms old, leading on its motion"
    )
    assert share_row(leader_share_age_s=0.07, led_on_leader_share=True, on_leader_share_position=True) == (
        "leader's last share 70 ms old, flying on its position (camera missing the leader)"
    )
    assert share_row(leader_share_age_s=1.5) == "leader's last share 1500 ms old, not flown on"


def test_status_without_telemetry_says_so() -> None:
    text = render_status({"mission": {"state": "wait_link"}, "link": {}, "gps": {}})
    rows = dict(line.split(None, 1) for line in text.splitlines() if line and not line.startswith(" "))
    assert rows["flight"] == "altitude - m, battery -"
    assert rows["link"].startswith("system ?, DOWN")
    assert "formation" not in rows


def test_status_shows_refused_input_and_mavlink_signing() -> None:
    text = render_status(
        {
            "mission": {"state": "follow"},
            "link": {},
            "gps": {},
            "mqtt": {
                "enabled": True,
                "connected": True,
                "published": 10,
                "buffered": 0,
                "dropped": 0,
                "commands_rejected": 3,
                "shares_rejected": {"stale": 1, "bad_mac": 1},
            },
            "mavlink_signing": {
                "autopilot_signs": True,
                "counters": {
                    "in_signed": 900,
                    "out_signed": 400,
                    "in_unsigned_dropped": 7,
                    "in_unsigned_passed": 5,
                    "local_refused": 3,
                },
                "impostors": {"10.0.0.7:14550": 2},
            },
        }
    )
    rows = dict(line.split(None, 1) for line in text.splitlines() if line and not line.startswith(" "))
    assert rows["mqtt"].endswith("refused 3 commands and 2 shares")
    assert rows["signing"] == (
        "autopilot signs, 900 in, 400 out, 7 dropped, 2 IMPOSTOR frames, "
        "3 frames from LOCAL SENDERS that are not MAVSDK"
    )


def test_health_on_the_ground_says_whether_a_start_would_arm() -> None:
    from companion.service.ports import FlightSnapshot, VehicleSummary
    from companion.service.reports import live_health_json

    veh = VehicleSummary(connected=True, heartbeat_age_s=0.2, gps_fix_type=3, gps_satellites=10)
    waiting = live_health_json(
        FlightSnapshot("preflight", "link up", vehicle=veh, preflight_problems=("no GPS", "no home")),
        [],
        None,
    )
    checks = {c["name"]: c for c in waiting["checks"]}
    assert checks["gps"]["ok"]  # a fix, but the mission's debounce and home are not there yet
    assert checks["preflight"] == {"name": "preflight", "ok": False, "detail": "no GPS, no home"}
    ready = live_health_json(
        FlightSnapshot("preflight", "link up", vehicle=veh, preflight_problems=()), [], None
    )
    assert all(c["ok"] for c in ready["checks"])
    flying = live_health_json(FlightSnapshot("follow", "leader acquired", vehicle=veh), [], None)
    assert "preflight" not in {c["name"] for c in flying["checks"]}
    invalid = VehicleSummary(connected=True, heartbeat_age_s=0.2, gps_fix_type=3, position_valid=False)
    lost = live_health_json(FlightSnapshot("follow", "leader acquired", vehicle=invalid), [], None)
    assert not {c["name"]: c for c in lost["checks"]}["gps"]["ok"]  # PX4 says its position is invalid


def test_the_page_reads_the_keys_the_service_writes() -> None:
    """The JSON the service builds from a flight's own snapshot, a leader estimate included, has every key
    the page reads (MQTT off; the signing relay's status aside, there only when it runs)."""
    import numpy as np

    from companion.config import Config
    from companion.estimation.estimate import RelativeEstimate, TrackState
    from companion.estimation.leader import TrackStatus
    from companion.kernel.camera import MountConfig
    from companion.kernel.clock import ManualClock
    from companion.perception.transform import CameraGeometry
    from companion.service.flight import FlightService
    from companion.service.health import HealthBoard
    from companion.service.latency import LatencyStats
    from companion.service.reports import status_json
    from companion.service.sysinfo import SystemReading

    from .mission_harness import FakeAutopilot
    from .status_keys import keys_the_page_misses
    from .test_mission_runner import RecordingLink

    clock = ManualClock(20.0)
    ap = FakeAutopilot()
    ap.fly()
    cfg = Config()
    flight = FlightService(cfg, RecordingLink(ap, clock), clock)  # type: ignore[arg-type]
    est = RelativeEstimate(
        np.array([5.0, 1.0, -0.5]), np.array([0.5, 0.0, 0.0]), np.diag([0.1, 0.2, 0.3, 1.0, 1.0, 1.0]),
        np.eye(3), CameraGeometry.from_mount(MountConfig()),
    )  # fmt: skip
    flight.track = TrackState(19.9, TrackStatus.CONFIRMED, 1, est, 3.0, 19.8, 9, None)
    latency = LatencyStats()
    latency.record("detect", 12.0)
    status = status_json(
        cfg, flight.snapshot(), clock, started_s=0.0, stop_reason=None, transitions=3,
        latency_ms=latency.summary, frames=lambda: {"received": 10, "processed": 9, "dropped": 1},
        system=SystemReading(0.5, 20.0, (20.0, 21.0), 900.0, 7600.0, {"cpu-thermal": 48.0}),
        components=HealthBoard(clock).snapshot, mqtt=None, extra_status={},
    )  # fmt: skip
    text, missing = keys_the_page_misses(status)
    assert missing == {"mavlink_signing"}  # the signing relay's own status, there only when it runs
    assert "link" in keys_the_page_misses({k: v for k, v in status.items() if k != "link"})[1]
    rows = dict(line.split(None, 1) for line in text.splitlines() if line and not line.startswith(" "))
    assert rows["leader"].startswith("confirmed, rel NED")
    assert rows["frames"] == "10 received, 9 processed, 1 dropped"
