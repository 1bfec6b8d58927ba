"""What the leader estimate brought to the acting moment costs a control tick.

Run: ``python -m companion.lab.control_bench``.

Per control tick, FOLLOW does two things with the leader estimate: brings it from its frame's capture to
when the setpoint will act (:meth:`~companion.mission.states.follow.FollowPhase.relative_now`, with
``formation.latency_compensation`` on; off, the estimate is flown as captured) and runs the formation
law on it. Both are timed on the same estimates (a leader 5 m ahead accelerating, 40-110 ms old, the
follower's velocity history at 50 Hz, a link measured at 12 ms one way), on and off in alternating blocks
so a machine's changing load hits both alike. Figures: p50 / p95 per tick in microseconds, and the
prediction's p50 as a share of the 20 Hz tick's 50 ms.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from typing import Any

import numpy as np

from companion.config import Config, FormationConfig
from companion.estimation.leader import LeaderEstimate, TrackStatus
from companion.kernel.flight import VehicleState
from companion.mission.machine import MissionMachine

#: The control tick's period at the shipped 20 Hz, s.
TICK_S = 0.05


def _machine(compensation: bool, now_s: float) -> MissionMachine:
    """A mission machine whose follower has flown 2 s at 2 m/s north (its velocity history, 50 Hz)."""
    m = MissionMachine(Config(formation=FormationConfig(latency_compensation=compensation)))
    m.c.now_s = now_s
    for k in range(100):
        t = now_s - 2.0 + 0.02 * k
        m.c.ego.push(t, np.array([2.0 + 0.1 * k / 100, 0.0, 0.0]))
    return m


def _estimates(n: int, now_s: float, seed: int) -> list[LeaderEstimate]:
    rng = np.random.default_rng(seed)
    out = []
    for _ in range(n):
        age = float(rng.uniform(0.04, 0.11))
        p = (5.0 + float(rng.normal(0, 0.05)), float(rng.normal(0, 0.05)), float(rng.normal(0, 0.05)))
        out.append(
            LeaderEstimate(
                stamp_s=now_s - age,
                status=TrackStatus.CONFIRMED,
                p_ned_rel_m=p,
                v_ned_rel_m_s=(0.1, 0.0, 0.0),
                last_measurement_s=now_s - age,
                a_ned_leader_m_s2=(1.0, 0.0, 0.0),
            )
        )
    return out


def _time_block(
    m: MissionMachine, veh: VehicleState, ests: list[LeaderEstimate]
) -> tuple[list[float], list[float]]:
    """Per estimate: the prediction's time and the prediction plus the law's, microseconds."""
    predict_us, tick_us = [], []
    follower = m.c.follower(veh, velocity_valid=True)
    clock = time.perf_counter_ns
    for est in ests:
        t0 = clock()
        p_rel, v_rel = m.follow.relative_now(est, veh)
        t1 = clock()
        m.c.law.velocity(p_rel, v_rel, follower, m.c.now_s, a_leader_ned_m_s2=est.a_ned_leader_m_s2)
        t2 = clock()
        predict_us.append((t1 - t0) / 1e3)
        tick_us.append((t2 - t0) / 1e3)
    return predict_us, tick_us


def run(blocks: int, per_block: int, seed: int = 0) -> dict[str, Any]:
    """Alternating blocks, compensation off then on; percentiles per variant (microseconds)."""
    now_s = 100.0
    veh = VehicleState(stamp_s=now_s, v_ned_m_s=(2.1, 0.0, 0.0), velocity_stamp_s=now_s, link_delay_s=0.012)
    samples: dict[str, dict[str, list[float]]] = {
        v: {"predict_us": [], "tick_us": []} for v in ("as_captured", "acting_moment")
    }
    machines = {"as_captured": _machine(False, now_s), "acting_moment": _machine(True, now_s)}
    for b in range(blocks):
        ests = _estimates(per_block, now_s, seed + b)
        for name, m in machines.items():
            m.c.law.reset()
            pred, tick = _time_block(m, veh, ests)
            samples[name]["predict_us"] += pred
            samples[name]["tick_us"] += tick
    result: dict[str, Any] = {"blocks": blocks, "per_block": per_block}
    for name, s in samples.items():
        result[name] = {
            k: {"p50": float(np.percentile(x, 50)), "p95": float(np.percentile(x, 95))} for k, x in s.items()
        }
    p50 = result["acting_moment"]["predict_us"]["p50"]
    result["prediction_share_of_tick"] = p50 / (TICK_S * 1e6)
    result["tick_ratio_p50"] = (
        result["acting_moment"]["tick_us"]["p50"] / result["as_captured"]["tick_us"]["p50"]
    )
    return result


def format_result(r: dict[str, Any]) -> str:
    """The figures as a Markdown table and one line of shares."""
    lines = [
        "| per control tick | prediction p50 / p95 (us) | prediction + law p50 / p95 (us) |",
        "|---|---|---|",
    ]
    for name in ("as_captured", "acting_moment"):
        p, t = r[name]["predict_us"], r[name]["tick_us"]
        lines.append(f"| {name} | {p['p50']:.1f} / {p['p95']:.1f} | {t['p50']:.1f} / {t['p95']:.1f} |")
    lines.append(
        f"prediction p50 = {100 * r['prediction_share_of_tick']:.3f} % of the 50 ms tick; "
        f"tick p50 ratio acting-moment / as-captured = {r['tick_ratio_p50']:.2f}"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """Time both variants and print (and optionally write) the figures."""
    ap = argparse.ArgumentParser(prog="python -m companion.lab.control_bench", description=__doc__)
    ap.add_argument("--blocks", type=int, default=20)
    ap.add_argument("--per-block", type=int, default=500)
    ap.add_argument("--json", default=None, help="also write the figures to this JSON file")
    args = ap.parse_args(argv)
    r = run(args.blocks, args.per_block)
    print(format_result(r))
    if args.json:
        with open(args.json, "w", encoding="utf-8") as f:
            json.dump(r, f, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
