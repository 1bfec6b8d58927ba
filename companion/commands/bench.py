"""``companion bench``: per-stage perception latency (p50/p95/p99), torch and ONNX Runtime side by side."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from companion.commands._common import add_config_arg, load


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("bench", help="time perception per stage (p50/p95/p99)")
    add_config_arg(p)
    p.add_argument("--json", default=None, help="also write the figures to this JSON file")
    p.add_argument("--frames", type=int, default=200, help="frames timed per runtime (after 10 warm-up)")
    p.add_argument(
        "--runtimes",
        default="torch,onnx",
        help="comma list: torch, onnx (with their CUDA and TensorRT runtimes where present)",
    )
    p.add_argument(
        "--data",
        default=None,
        help="folder of 640x480 images to time on instead of synthetic frames; with YOLO labels (a "
        "dataset folder, --split), the +window runtime is focused on each frame's labelled leader",
    )
    p.add_argument("--split", default=None, help="dataset split under --data (e.g. test)")
    p.set_defaults(handler=_bench)


def _bench(args: argparse.Namespace) -> int:
    cfg = load(args)
    from companion.lab.bench import format_bench, gpu_network_ms, gpu_runtimes, run_bench
    from companion.perception.detector import load_detector, model_files
    from companion.perception.detector.roi import RoiDetector

    wanted = [r.strip() for r in args.runtimes.split(",") if r.strip()]
    detectors: dict[str, Any] = {}
    for name in wanted:
        if name not in ("torch", "onnx"):
            print(f"companion bench: unknown runtime {name!r}", file=sys.stderr)
            return 2
        key = "onnxruntime" if name == "onnx" else "torch"
        detectors[f"{key}-cpu"] = load_detector(cfg.detector, runtime=name)
        if name == "onnx" and cfg.detector.roi_enabled:
            detectors[f"{key}-cpu+window"] = RoiDetector(detectors[f"{key}-cpu"], cfg.detector)
    gpu = gpu_runtimes()
    if "torch" in wanted and gpu["torch-cuda"] and not gpu["torch-cuda"].startswith("absent"):
        detectors["torch-cuda"] = load_detector(cfg.detector, runtime="torch", device="cuda")
    if "onnx" in wanted:
        for name in ("cuda", "tensorrt"):
            if gpu[f"onnxruntime-{name}"] == "present":
                detectors[f"onnxruntime-{name}"] = load_detector(cfg.detector, runtime="onnx", device=name)
    frames = _frames(args, cfg)
    result = run_bench(cfg, detectors, frames, pose_filter=pose_filter_stages)
    result["gpu"] = {"runtimes": gpu}
    if "torch-cuda" in detectors:
        weights = model_files(cfg.detector)[0]
        result["gpu"]["torch_cuda_network"] = gpu_network_ms(weights, frames, cfg.detector.input_size_px)
    print(format_bench(result))
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(result, indent=2))
    return 0


def pose_filter_stages(cfg: Any) -> tuple[Any, Any]:
    """The pose and filter stages ``companion bench`` times: a fresh estimation pipeline's."""
    from companion.estimation.pipeline import PerceptionPipeline

    pipeline = PerceptionPipeline.from_config(cfg, guard_brake_m_s2=None)  # the depth guard is not timed
    return pipeline.measure, pipeline.track


def _frames(args: argparse.Namespace, cfg: Any) -> list[Any]:
    from companion.lab.bench import synthetic_frames

    if args.data is None:
        return synthetic_frames(args.frames)
    import numpy as np

    from companion.kernel.camera import GroundTruth, Intrinsics, RgbdFrame
    from companion.perception.detector.dataset import find_samples, read_labels, read_rgb

    samples = find_samples(Path(args.data), args.split)[: args.frames]
    synth = synthetic_frames(len(samples))
    frames = []
    for i, (sample, s) in enumerate(zip(samples, synth, strict=True)):
        rgb = read_rgb(sample.image_path)
        h, w = rgb.shape[:2]
        depth = s.depth_m if (h, w) == s.depth_m.shape else np.zeros((h, w), np.float32)
        boxes = read_labels(sample, w, h)
        truth = None
        if len(boxes):
            b = boxes[0]
            truth = GroundTruth((float(b[0]), float(b[1]), float(b[2]), float(b[3])), 1.0, np.zeros(3), 0.0)
        frames.append(
            RgbdFrame(rgb, depth, Intrinsics.from_hfov(w, h, 69.0), stamp_s=i / 30.0, seq=i, truth=truth)
        )
    return frames
