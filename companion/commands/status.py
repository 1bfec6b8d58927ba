"""``companion status`` and ``companion health``."""

from __future__ import annotations

import argparse
import json
import math
import time
from pathlib import Path
from typing import Any

from companion.commands._common import add_config_arg, config_path, load
from companion.kernel.errors import CompanionError
from companion.service.operator import OPERATOR_COMMANDS, command_request

#: Exit codes of the commands that ask the running service (``status``, ``start``, ``command``).
EXIT_DONE = 0
#: The service refused (the line says why); for ``status``, never.
EXIT_REFUSED = 1
#: 2 is argparse's usage error and a bad config; 5 is companion.service.status.EXIT_NOT_RUNNING.
EXIT_CODES = (
    "exit codes: 0 done, 1 refused (the line says why), 2 usage or config error, "
    "5 no service answers on the status socket (not running)"
)
#: Seconds between rounds of ``companion health --wait``.
HEALTH_RETRY_S = 2.0
#: Operator commands and how many numbers each takes.
COMMAND_ARGS = {name: 3 if takes_offset else 0 for name, takes_offset in OPERATOR_COMMANDS.items()}


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("status", help="show the running service's state", epilog=EXIT_CODES)
    add_config_arg(p)
    p.add_argument(
        "--json", action="store_true", help="print the raw JSON snapshot (always JSON, errors included)"
    )
    p.set_defaults(handler=_status)
    h = sub.add_parser("health", help="run preflight checks; exit 0 healthy, 1 not")
    add_config_arg(h)
    h.add_argument("--json", action="store_true", help="print the checks as JSON")
    h.add_argument("--timeout", type=float, default=5.0, help="seconds per probe (default 5)")
    h.add_argument(
        "--wait",
        type=float,
        default=0.0,
        metavar="SECONDS",
        help="check again every 2 s until healthy or SECONDS have passed (GPS and home take a while after "
        "power-up); prints the last round only",
    )
    h.set_defaults(handler=_health)
    s = sub.add_parser(
        "start",
        help="ask the running service to start the mission (arm, take off, follow), or to resume it after "
        "a hold",
        description="Start the mission: from the ground, arm, take off and follow; in the air (after "
        "`companion command hold`, a pilot's mode change, or a restart in flight), take the vehicle back "
        "and follow again. Answers what the mission did, or why it refused.",
        epilog=EXIT_CODES,
    )
    add_config_arg(s)
    s.set_defaults(handler=_start)
    c = sub.add_parser(
        "command",
        help="send an operator command to the running service (checked by its mission machine)",
        description="land | hold | set_offset X Y Z: the service's mission machine checks each and "
        "answers in one line what it did or why it refused. After a hold, `companion start` resumes "
        "following.",
        epilog=EXIT_CODES,
    )
    add_config_arg(c)
    c.add_argument("name", choices=list(COMMAND_ARGS), help="the command")
    c.add_argument(
        "offset_cam_m",
        nargs="*",
        type=float,
        metavar="X Y Z",
        help="set_offset: the leader's slot in the camera frame, m (right, down, forward)",
    )
    c.set_defaults(handler=_command, usage_error=c.error)


def _ask(args: argparse.Namespace, request: str) -> int:
    """Send ``request`` to the running service and print its one-line answer; the exit code."""
    from companion.service.status import query_status

    cfg = load(args)
    reply = query_status(Path(cfg.status.socket_path), request)
    print(reply.get("detail", reply))
    return EXIT_DONE if reply.get("ok") else EXIT_REFUSED


def _start(args: argparse.Namespace) -> int:
    return _ask(args, "start")


def _command(args: argparse.Namespace) -> int:
    need = COMMAND_ARGS[args.name]
    if len(args.offset_cam_m) != need:
        # Checked here, before the service is asked: a usage error is one whether it runs or not.
        args.usage_error(
            f"{args.name} takes {'no numbers' if need == 0 else f'{need} numbers X Y Z (m)'}, "
            f"got {len(args.offset_cam_m)}"
        )
    offset: tuple[float, float, float] | None = None
    if need:
        x, y, z = (float(v) for v in args.offset_cam_m)
        offset = (x, y, z)
    return _ask(args, json.dumps(command_request(args.name, offset)))


def _status(args: argparse.Namespace) -> int:
    from companion.service.status import query_status

    try:
        cfg = load(args)
        snap = query_status(Path(cfg.status.socket_path), "status")
    except CompanionError as exc:
        if not args.json:
            raise
        print(json.dumps({"running": False, "error": str(exc), "exit_code": exc.exit_code}, indent=2))
        return exc.exit_code
    if args.json:
        print(json.dumps({"running": True, **snap}, indent=2))
    else:
        print(render_status(snap))
    return EXIT_DONE


def _health(args: argparse.Namespace) -> int:
    from companion.service.health_checks import run_health
    from companion.service.wiring import autopilot_probe

    deadline_s = time.monotonic() + max(0.0, args.wait)
    while True:
        report = run_health(config_path(args), probe_autopilot=autopilot_probe, timeout_s=args.timeout)
        if report.healthy or time.monotonic() + HEALTH_RETRY_S > deadline_s:
            break
        time.sleep(HEALTH_RETRY_S)
    if args.json:
        print(json.dumps(report.to_json(), indent=2))
    else:
        width = max(len(c.name) for c in report.checks)
        for c in report.checks:
            print(f"{'ok  ' if c.ok else 'FAIL'}  {c.name:<{width}}  {c.detail}")
        running = f"service running ({report.state})" if report.service_running else "service not running"
        print(f"{'healthy' if report.healthy else 'NOT healthy'}; {running}")
    return 0 if report.healthy else 1


def _fmt(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.2f}"
    if isinstance(value, list | tuple):
        return "[" + ", ".join(_fmt(v) for v in value) + "]"
    return str(value)


def render_status(s: dict[str, Any]) -> str:
    """The snapshot as a two-column table for a terminal."""
    rows: list[tuple[str, str]] = []
    m, link, gps = s.get("mission", {}), s.get("link", {}), s.get("gps", {})
    rows.append(("vehicle", f"{s.get('vehicle_id')}  (wingman {s.get('version')}, pid {s.get('pid')})"))
    rows.append(
        (
            "uptime",
            f"{_fmt(s.get('uptime_s'))} s" + (f"  STOPPING: {s['stopping']}" if s.get("stopping") else ""),
        )
    )
    rows.append(("state", f"{m.get('state')}  ({m.get('reason')}; {_fmt(m.get('state_age_s'))} s)"))
    err = m.get("formation_error_ned_m")
    if err is not None:
        norm = sum(c * c for c in err) ** 0.5
        rows.append(("formation", f"error {norm:.2f} m from the slot, NED {_fmt(err)} m"))
    share_age_s = m.get("leader_share_age_s")
    if share_age_s is not None:
        flown = (
            "flying on its position (camera missing the leader)"
            if m.get("on_leader_share_position")
            else "leading on its motion"
            if m.get("led_on_leader_share")
            else "not flown on"
        )
        rows.append(("share", f"leader's last share {1000 * share_age_s:.0f} ms old, {flown}"))
    pos, bat = s.get("position") or {}, s.get("battery") or {}
    rows.append(
        (
            "flight",
            f"altitude {_fmt(pos.get('altitude_m'))} m, battery "
            + (f"{100 * bat['remaining_frac']:.0f} %" if bat.get("remaining_frac") is not None else "-")
            + (f" ({bat['voltage_v']:.1f} V)" if bat.get("voltage_v") is not None else ""),
        )
    )
    rows.append(
        (
            "link",
            f"system {link.get('system_id') if link.get('system_id') is not None else '?'}, "
            f"{'up' if link.get('connected') else 'DOWN'}, "
            f"heartbeat {_fmt(link.get('heartbeat_age_s'))} s ago, "
            f"{link.get('flight_mode')}, {'armed' if link.get('armed') else 'disarmed'}, "
            f"{'in air' if link.get('in_air') else 'on ground'}, "
            f"offboard loss: {link.get('offboard_loss_failsafe') or 'unknown'}",
        )
    )
    rows.append(
        (
            "gps",
            f"fix {gps.get('fix_type')}, {gps.get('satellites')} sats, "
            f"position valid {gps.get('position_valid')}",
        )
    )
    ld = s.get("leader")
    if ld:
        cov = ld.get("cov_ned_m2")
        sd = "-" if not cov else "[" + ", ".join(f"{cov[i][i] ** 0.5:.2f}" for i in range(3)) + "] m"
        rows.append(
            (
                "leader",
                f"{ld.get('status')}, rel NED {_fmt(ld.get('p_rel_ned_m'))} m, "
                f"range {_fmt(ld.get('range_m'))} m, "
                f"1-sigma {sd}",
            )
        )
    else:
        rows.append(("leader", "no estimate"))
    fr = s.get("frames") or {}
    if fr:
        rows.append(
            (
                "frames",
                f"{fr.get('received')} received, {fr.get('processed')} processed, "
                f"{fr.get('dropped')} dropped",
            )
        )
    for stage, st in (s.get("latency_ms") or {}).items():
        rows.append(
            (
                f"  {stage}",
                f"p50 {st['p50_ms']:.1f} ms, p95 {st.get('p95_ms', math.nan):.1f} ms, "
                f"p99 {st['p99_ms']:.1f} ms ({st['count']} samples)",
            )
        )
    sysr = s.get("system") or {}
    if sysr:
        temps = (
            ", ".join(f"{k} {v:.0f} C" for k, v in (sysr.get("temperatures_c") or {}).items()) or "no sensors"
        )
        rows.append(
            (
                "machine",
                f"load {_fmt(sysr.get('load_1m'))}, cpu {_fmt(sysr.get('cpu_percent'))} %, "
                f"mem {_fmt(sysr.get('mem_used_mib'))}/{_fmt(sysr.get('mem_total_mib'))} MiB, {temps}",
            )
        )
    mq = s.get("mqtt") or {}
    if mq.get("enabled"):
        refused = mq.get("commands_rejected") or 0
        shares = sum((mq.get("shares_rejected") or {}).values())
        bad = f", refused {refused} commands and {shares} shares" if refused or shares else ""
        rows.append(
            (
                "mqtt",
                f"{'connected' if mq.get('connected') else 'DISCONNECTED'}, {mq.get('published')} sent, "
                f"{mq.get('buffered')} buffered, {mq.get('dropped')} dropped{bad}",
            )
        )
    sig = s.get("mavlink_signing")
    if sig:
        counters = sig.get("counters") or {}
        dropped = sum(
            v
            for k, v in counters.items()
            if k.startswith("in_") and k not in ("in_signed", "in_unsigned_passed")
        )
        impostors = sum((sig.get("impostors") or {}).values())
        strangers = counters.get("local_refused", 0) + counters.get("local_foreign", 0)
        rows.append(
            (
                "signing",
                f"{'autopilot signs' if sig.get('autopilot_signs') else 'AUTOPILOT DOES NOT SIGN'}, "
                f"{counters.get('in_signed', 0)} in, {counters.get('out_signed', 0)} out, {dropped} dropped"
                + (f", {impostors} IMPOSTOR frames" if impostors else "")
                + (f", {strangers} frames from LOCAL SENDERS that are not MAVSDK" if strangers else ""),
            )
        )
    for c in s.get("components", []):
        rows.append((f"  {c['name']}", f"{'ok' if c['ok'] else 'NOT OK'}: {c['detail']}"))
    width = max(len(k) for k, _ in rows)
    return "\n".join(f"{k:<{width}}  {v}" for k, v in rows)
