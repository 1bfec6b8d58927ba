"""What auto-labelling costs the flight loop: the per-frame path with and without it, side by side.

    python -m companion.lab.evaluation.autolabel_bench [--frames 300] [--config config/wingman.toml]

The flight loop's per-frame work (the configured detector, pose and tracker) runs over the same synthetic
frames (:func:`companion.lab.bench.synthetic_frames`) in alternating blocks, once alone and once
followed by the labeller and a hand-over to the running background writer (which encodes and writes the
JPEGs in its own thread, competing for the same cores). Reported: p50 / p95 per frame and frames per second
of each, and what the writer did. By default frames come at the camera's 30 per second, so the writer
encodes in the gaps as it does in flight; ``--rate-hz 0`` runs flat out (the worst case, where the writer
competes for every cycle).
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from companion.config import load_config
from companion.estimation.pipeline import PerceptionPipeline
from companion.kernel.camera import RgbdFrame
from companion.lab.bench import percentiles_ms, synthetic_frames
from companion.perception.autolabel import AutoLabelConfig, auto_label
from companion.perception.autolabel_writer import AutoLabelWriter


def _p_cam(frame: RgbdFrame) -> np.ndarray:
    """Where a shared position would put the synthetic leader (its box centre at its range)."""
    truth = frame.truth
    if truth is None or truth.box_xyxy_px is None:
        raise ValueError("a synthetic frame without its leader")
    x0, y0, x1, y1 = truth.box_xyxy_px
    r = float(truth.p_cam_leader_m[2])
    i = frame.intrinsics
    return np.array([((x0 + x1) / 2 - i.cx_px) / i.fx_px * r, ((y0 + y1) / 2 - i.cy_px) / i.fy_px * r, r])


def main(argv: list[str] | None = None) -> int:
    """Run both arms and print the figures (see the module docstring)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=300, help="frames per arm (default 300)")
    ap.add_argument("--block", type=int, default=20, help="frames per alternating block")
    ap.add_argument(
        "--rate-hz",
        type=float,
        default=30.0,
        help="frames offered per second, as a camera does (0: flat out)",
    )
    ap.add_argument("--config", default=None, help="service config (default: the shipped one)")
    ap.add_argument("--json", default=None, help="also write the figures here")
    args = ap.parse_args(argv)
    from companion.lab.evaluation.setup import DEFAULT_CONFIG, load_detect  # noqa: PLC0415 (the detector)

    cfg = load_config(Path(args.config) if args.config else DEFAULT_CONFIG)
    stage = load_detect(cfg, "network")
    pipeline = PerceptionPipeline.from_config(cfg, guard_brake_m_s2=None)  # the depth guard is not timed
    frames = synthetic_frames(args.block * 4, seed=3)
    p_cams = [_p_cam(f) for f in frames]
    label_cfg = AutoLabelConfig(leader_span_m=cfg.leader.span_m)
    times: dict[str, list[float]] = {"without": [], "with": []}
    with tempfile.TemporaryDirectory() as tmp, AutoLabelWriter(Path(tmp) / "ds", negative_every=1) as writer:
        for f in frames[:10]:  # warm-up
            pipeline.process(f, stage.detect(f).detections)
        k = 0
        next_s = time.perf_counter()
        while min(len(v) for v in times.values()) < args.frames:
            for arm in ("without", "with"):
                for _ in range(args.block):
                    i = k % len(frames)
                    k += 1
                    f = frames[i]
                    if args.rate_hz > 0:  # the camera's pace: the writer works in the gaps, as in flight
                        time.sleep(max(0.0, next_s - time.perf_counter()))
                        next_s = max(next_s + 1.0 / args.rate_hz, time.perf_counter())
                    t0 = time.perf_counter()
                    pipeline.process(f, stage.detect(f).detections)
                    if arm == "with":
                        writer.offer(f, auto_label(f.depth_m, f.intrinsics, p_cams[i], label_cfg))
                    times[arm].append((time.perf_counter() - t0) * 1e3)
    result = {
        arm: {**percentiles_ms(v[: args.frames]), "fps": round(1e3 / float(np.mean(v[: args.frames])), 1)}
        for arm, v in times.items()
    }
    result["writer"] = writer.counts.as_dict()
    result["rate_hz"] = args.rate_hz
    for arm in ("without", "with"):
        r = result[arm]
        print(
            f"{arm:8s} auto-labels: p50 {r['p50_ms']:.2f} ms, p95 {r['p95_ms']:.2f} ms per frame "
            f"(flat out {r['fps']} frames/s)"
        )
    w = result["writer"]
    print(
        f"writer: {w['labels']} labels, {w['negatives']} negatives, {w['rejected']} rejected, "
        f"{w['dropped']} dropped, {w['bytes_written'] / 1e6:.1f} MB"
    )
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
