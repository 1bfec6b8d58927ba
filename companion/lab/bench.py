"""Per-stage perception latency on 640x480 RGB-D frames: ``companion bench``.

Stages of one frame, each timed separately: decode (PNG -> array; file sources only, a camera delivers
arrays), preprocess (letterbox + normalise), inference, postprocess (threshold, box decoding, NMS), pose
(box + depth -> 3D) and filter (tracker step). Every runtime that is available here (torch and ONNX Runtime
on the CPU; CUDA when present) runs the *same* frames, interleaved frame by frame so that the load of a
shared machine hits them alike. Figures are p50 / p95 / p99 in ms; ``total`` is the per-frame sum from
preprocess to filter (the camera path). A ``+window`` runtime is the same network searching the window on a
tracked leader (:mod:`companion.perception.detector.roi`), focused on each frame's leader as the tracker
would be. The pose and filter stages come from the caller (``companion bench`` hands in the estimation's
:class:`~companion.estimation.pipeline.PerceptionPipeline`; perception does not import estimation); without
them, such a stage is reported as "not measured", never with a number.
"""

from __future__ import annotations

import logging
import platform
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import Config
from companion.kernel.camera import GroundTruth, Intrinsics, RgbdFrame
from companion.perception.types import Detection

log = logging.getLogger(__name__)

STAGES = ("decode", "preprocess", "inference", "postprocess", "pose", "filter")
CAMERA_STAGES = STAGES[1:]
NOT_MEASURED = "not measured"


def percentiles_ms(samples_ms: list[float]) -> dict[str, float]:
    """p50 / p95 / p99 / mean of a list of durations in ms."""
    a = np.asarray(samples_ms, np.float64)
    p50, p95, p99 = np.percentile(a, (50, 95, 99))
    return {
        "p50_ms": round(float(p50), 3),
        "p95_ms": round(float(p95), 3),
        "p99_ms": round(float(p99), 3),
        "mean_ms": round(float(a.mean()), 3),
        "n": len(a),
    }


def synthetic_frames(n: int, seed: int = 0, w_px: int = 640, h_px: int = 480) -> list[RgbdFrame]:
    """Deterministic 640x480 RGB-D frames: sky and ground, sensor noise, a dark quad-like leader at 3-12 m."""
    import cv2  # noqa: PLC0415

    rng = np.random.default_rng(seed)
    intr = Intrinsics.from_hfov(w_px, h_px, 69.0)
    frames = []
    for i in range(n):
        t = np.linspace(0.0, 1.0, h_px, dtype=np.float32)[:, None, None]
        sky = rng.uniform(120, 230, 3).astype(np.float32)
        rgb = (sky * (1 - 0.4 * t)).repeat(w_px, 1)
        horizon = int(rng.uniform(0.55, 0.85) * h_px)
        rgb[horizon:] = rng.uniform(40, 120, 3)
        rgb += rng.normal(0.0, 3.0, rgb.shape).astype(np.float32)
        img = np.clip(rgb, 0, 255).astype(np.uint8)
        depth = np.zeros((h_px, w_px), np.float32)
        depth[horizon:] = np.linspace(4.0, 25.0, h_px - horizon, dtype=np.float32)[::-1, None]
        range_m = float(rng.uniform(3.0, 12.0))
        span = intr.fx_px * 0.45 / range_m
        cx, cy = rng.uniform(0.2, 0.8) * w_px, rng.uniform(0.2, 0.6) * h_px
        for ang in (30, 150, 210, 330):
            a = np.radians(ang)
            x, y = int(cx + span / 2 * np.cos(a)), int(cy + span / 5 * np.sin(a))
            cv2.line(img, (int(cx), int(cy)), (x, y), (30, 30, 35), max(1, int(span / 20)))
            cv2.ellipse(
                img, (x, y), (max(1, int(span / 7)), max(1, int(span / 20))), 0, 0, 360, (40, 40, 40), -1
            )
        x0, y0, x1, y1 = int(cx - span / 2), int(cy - span / 5), int(cx + span / 2), int(cy + span / 5)
        depth[max(0, y0) : y1, max(0, x0) : x1] = range_m + rng.normal(
            0, 0.02, (y1 - max(0, y0), x1 - max(0, x0))
        )
        truth = GroundTruth(
            (float(max(0, x0)), float(max(0, y0)), float(min(w_px, x1)), float(min(h_px, y1))),
            1.0,
            np.array([0.0, 0.0, range_m]),
            0.0,
        )
        frames.append(RgbdFrame(img, depth, intr, stamp_s=i / 30.0, seq=i, truth=truth))
    return frames


@dataclass
class RuntimeRun:
    """Samples of one runtime, stage -> list of ms."""

    name: str
    samples: dict[str, list[float]] = field(default_factory=lambda: {s: [] for s in (*STAGES, "total")})
    detections: int = 0


#: The pose stage (frame, detections -> measurements) and the filter stage (stamp, measurements -> track).
PoseFilterStages = tuple[Callable[[RgbdFrame, list[Detection]], Any], Callable[[float, Any], Any]]


def run_bench(
    cfg: Config,
    detectors: dict[str, Any],
    frames: list[RgbdFrame],
    warmup: int = 10,
    *,
    pose_filter: Callable[[Config], PoseFilterStages] | None = None,
) -> dict[str, Any]:
    """Time every detector (name -> FrameDetector) and the perception stages over ``frames``.

    ``pose_filter`` builds a fresh pose and filter stage for each runtime (each keeps its own track); None:
    those stages are reported as not measured.
    """
    import cv2  # noqa: PLC0415

    encoded = [cv2.imencode(".png", f.rgb[..., ::-1])[1] for f in frames]
    runs = {name: RuntimeRun(name) for name in detectors}
    none: tuple[None, None] = (None, None)
    pose_fns = {name: none if pose_filter is None else pose_filter(cfg) for name in detectors}
    for i in range(-warmup, len(frames)):
        k = i % len(frames)
        frame = frames[k]
        for name, det in detectors.items():
            measure, track = pose_fns[name]
            t0 = time.perf_counter()
            decoded = cv2.imdecode(encoded[k], cv2.IMREAD_COLOR)
            t1 = time.perf_counter()
            if hasattr(det, "focus"):
                # Tracking mode: the window on the leader, as if the tracker had it in the frame before;
                # a frame without a known leader is searched whole.
                det.reset()
                if frame.truth is not None and frame.truth.box_xyxy_px is not None:
                    det.focus(frame.truth.box_xyxy_px)
            result = det.detect(frame.rgb)
            timing = result.timing
            pose_ms = filt_ms = float("nan")
            if measure is not None and track is not None:
                t2 = time.perf_counter()
                meas = measure(frame, result.detections)
                t3 = time.perf_counter()
                track((i + warmup) / 30.0, meas)  # strictly increasing per runtime, frames repeat
                t4 = time.perf_counter()
                pose_ms, filt_ms = (t3 - t2) * 1e3, (t4 - t3) * 1e3
            del decoded
            if i < 0:
                continue
            r = runs[name]
            r.detections += len(result.detections)
            r.samples["decode"].append((t1 - t0) * 1e3)
            r.samples["preprocess"].append(timing.preprocess_ms)
            r.samples["inference"].append(timing.inference_ms)
            r.samples["postprocess"].append(timing.postprocess_ms)
            total = timing.preprocess_ms + timing.inference_ms + timing.postprocess_ms
            if measure is not None:
                r.samples["pose"].append(pose_ms)
                r.samples["filter"].append(filt_ms)
                total += pose_ms + filt_ms
            r.samples["total"].append(total)
    perception_built = pose_fns and next(iter(pose_fns.values()))[0] is not None
    out: dict[str, Any] = {
        "frames": len(frames),
        "frame_size_px": [frames[0].intrinsics.width_px, frames[0].intrinsics.height_px],
        "input_size_px": cfg.detector.input_size_px,
        "threads": cfg.detector.threads,
        "machine": f"{platform.machine()}, {_cpu_count()} CPUs visible",
        # Other work on a shared machine inflates every figure (p95/p99 most): say how loaded it was.
        "load_average_1_5_15": _load_average(),
        "total_covers": list(CAMERA_STAGES if perception_built else CAMERA_STAGES[:3]),
        "runtimes": {},
    }
    for name, r in runs.items():
        stages: dict[str, Any] = {}
        for s in (*STAGES, "total"):
            stages[s] = percentiles_ms(r.samples[s]) if r.samples[s] else NOT_MEASURED
        stages["detector"] = percentiles_ms(
            [
                a + b + c
                for a, b, c in zip(
                    r.samples["preprocess"], r.samples["inference"], r.samples["postprocess"], strict=True
                )
            ]
        )
        stages["detections_per_frame"] = round(r.detections / max(1, len(frames)), 3)
        det = detectors[name]
        if hasattr(det, "window_frames"):
            # Cumulative over warm-up and timed frames: the share of windows that fell back to the frame.
            stages["window_fallback_fraction"] = round(det.fallback_frames / max(1, det.window_frames), 3)
        out["runtimes"][name] = stages
    return out


def gpu_runtimes() -> dict[str, str]:
    """Which GPU runtimes this machine has: name -> the device it runs on, or ``absent: why``.

    torch on CUDA, and ONNX Runtime's CUDA and TensorRT execution providers (the CPU build of
    onnxruntime has neither).
    """
    import importlib.util  # noqa: PLC0415

    out: dict[str, str] = {}
    if importlib.util.find_spec("torch") is None:
        out["torch-cuda"] = "absent: torch is not installed"
    else:
        import torch  # noqa: PLC0415

        ok = torch.cuda.is_available()
        out["torch-cuda"] = torch.cuda.get_device_name(0) if ok else "absent: torch sees no CUDA device"
    if importlib.util.find_spec("onnxruntime") is None:
        out["onnxruntime-cuda"] = out["onnxruntime-tensorrt"] = "absent: onnxruntime is not installed"
    else:
        import onnxruntime as ort  # noqa: PLC0415

        have = ort.get_available_providers()
        for name, provider in (("cuda", "CUDAExecutionProvider"), ("tensorrt", "TensorrtExecutionProvider")):
            out[f"onnxruntime-{name}"] = (
                "present" if provider in have else f"absent: this onnxruntime build has no {provider}"
            )
    return out


def gpu_network_ms(
    weights: Path, frames: list[RgbdFrame], input_size_px: int, warmup: int = 20
) -> dict[str, Any]:
    """The network's own time on the GPU (torch, CUDA events), per frame, input already on the device.

    What ``inference`` of the ``torch-cuda`` runtime adds to it is the copies to and from the GPU and the
    launch overhead the service pays per frame. fp32, batch 1, BatchNorm folded, as the service runs it.
    """
    import torch  # noqa: PLC0415

    from companion.perception.detector.letterbox import Letterboxer  # noqa: PLC0415
    from companion.perception.detector.torch_engine import TorchEngine  # noqa: PLC0415

    engine = TorchEngine(weights, threads=1, device="cuda")
    lb = Letterboxer(input_size_px)
    inputs = [torch.from_numpy(lb(f.rgb)[0].copy()).cuda() for f in frames]
    start = torch.cuda.Event(enable_timing=True)  # type: ignore[no-untyped-call]
    end = torch.cuda.Event(enable_timing=True)  # type: ignore[no-untyped-call]
    samples = []
    with torch.inference_mode():
        for i in range(-warmup, len(inputs)):
            x = inputs[i % len(inputs)]
            start.record()
            engine.net(x)
            end.record()
            end.synchronize()
            if i >= 0:
                samples.append(start.elapsed_time(end))
    return {
        "device": torch.cuda.get_device_name(0),
        "input_shape": list(inputs[0].shape),
        "network": percentiles_ms(samples),
    }


def _load_average() -> list[float] | None:
    import os  # noqa: PLC0415

    return [round(x, 2) for x in os.getloadavg()] if hasattr(os, "getloadavg") else None


def _cpu_count() -> int:
    import os  # noqa: PLC0415

    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 0)


def format_bench(result: dict[str, Any]) -> str:
    """The benchmark as a fixed-width table (ms)."""
    names = list(result["runtimes"])
    lines = [
        f"{result['frames']} frames {result['frame_size_px'][0]}x{result['frame_size_px'][1]}, input "
        f"{result['input_size_px']} px, {result['threads']} threads, {result['machine']}, "
        f"load average {result['load_average_1_5_15']}",
        f"{'stage':<22}" + "".join(f"{n:>28}" for n in names),
        f"{'':<22}" + "".join(f"{'p50 / p95 / p99 ms':>28}" for _ in names),
    ]
    for s in (*STAGES, "detector", "total"):
        cells = []
        for n in names:
            v = result["runtimes"][n][s]
            cells.append(
                f"{v:>28}"
                if isinstance(v, str)
                else f"{v['p50_ms']:>10.2f} /{v['p95_ms']:>6.2f} /{v['p99_ms']:>6.2f}"
            )
        label = {
            "decode": "decode (file src)",
            "total": "total (camera path)",
            "detector": "detector (pre+inf+post)",
        }.get(s, s)
        lines.append(f"{label:<22}" + "".join(cells))
    lines.append(f"total = {' + '.join(result['total_covers'])}")
    gpu = result.get("gpu")
    if gpu:
        for name, state in gpu["runtimes"].items():
            lines.append(f"{name}: {state}")
        net = gpu.get("torch_cuda_network")
        if net:
            v = net["network"]
            shape = "x".join(str(d) for d in net["input_shape"][2:])
            lines.append(
                f"network alone on {net['device']} (torch, CUDA events, input {shape}): "
                f"p50 {v['p50_ms']:.3f} / p95 {v['p95_ms']:.3f} / p99 {v['p99_ms']:.3f} ms"
            )
    for n in names:
        fb = result["runtimes"][n].get("window_fallback_fraction")
        if fb is not None:
            lines.append(
                f"{n}: the window found nothing and the whole frame was searched too on {fb:.0%} of frames"
            )
    return "\n".join(lines)


def onnx_input_shape(path: str) -> tuple[int, int] | None:
    """The fixed (H, W) input of an ONNX model, or None when H or W is dynamic."""
    import onnxruntime as ort  # noqa: PLC0415

    so = ort.SessionOptions()
    so.log_severity_level = 3
    shape = ort.InferenceSession(path, so, providers=["CPUExecutionProvider"]).get_inputs()[0].shape
    h, w = shape[2], shape[3]
    return (h, w) if isinstance(h, int) and isinstance(w, int) else None


def compare_onnx_models(
    models: dict[str, str],
    frames: list[RgbdFrame],
    input_size_px: int,
    threads: int = 2,
    warmup: int = 10,
) -> dict[str, Any]:
    """Inference time of several ONNX models (name -> path) on the same frames, interleaved frame by frame.

    A Wingman export (dynamic input) gets each frame letterboxed at ``input_size_px`` as at run time; a
    peer model with a fixed input (e.g. FastestDet, 352x352) gets the frame resized to that input. Only the
    ONNX Runtime call is timed (2 threads, no spinning, as :class:`OnnxEngine`).
    """
    import cv2  # noqa: PLC0415
    import onnxruntime as ort  # noqa: PLC0415

    from companion.perception.detector.letterbox import Letterboxer  # noqa: PLC0415
    from companion.perception.detector.runtime import session_options  # noqa: PLC0415

    sessions = {}
    for name, path in models.items():
        sess = ort.InferenceSession(path, session_options(threads), providers=["CPUExecutionProvider"])
        fixed = onnx_input_shape(path)
        sessions[name] = (sess, sess.get_inputs()[0].name, fixed, Letterboxer(input_size_px))
    samples: dict[str, list[float]] = {n: [] for n in models}
    shapes: dict[str, list[int]] = {}
    for i in range(-warmup, len(frames)):
        rgb = frames[i % len(frames)].rgb
        for name, (sess, input_name, fixed, lb) in sessions.items():
            if fixed is None:
                x, _ = lb(rgb)
            else:
                resized = cv2.resize(rgb[..., ::-1], (fixed[1], fixed[0]), interpolation=cv2.INTER_AREA)
                x = np.ascontiguousarray(resized.transpose(2, 0, 1)[None], np.float32) / np.float32(255.0)
            shapes[name] = list(x.shape)
            t0 = time.perf_counter()
            sess.run(None, {input_name: x})
            dt = (time.perf_counter() - t0) * 1e3
            if i >= 0:
                samples[name].append(dt)
    return {
        "frames": len(frames),
        "threads": threads,
        "load_average_1_5_15": _load_average(),
        "models": {
            n: {"path": models[n], "input_shape": shapes[n], "inference": percentiles_ms(samples[n])}
            for n in models
        },
    }


def format_comparison(result: dict[str, Any]) -> str:
    """The model comparison as lines of p50 / p95 / p99 ms."""
    lines = [
        f"ONNX Runtime inference, {result['frames']} frames, {result['threads']} threads, "
        f"load average {result['load_average_1_5_15']}"
    ]
    for name, m in result["models"].items():
        v = m["inference"]
        shape = "x".join(str(d) for d in m["input_shape"][2:])
        lines.append(
            f"{name:<24} input {shape:>8}  "
            f"p50 {v['p50_ms']:6.2f}  p95 {v['p95_ms']:6.2f}  p99 {v['p99_ms']:6.2f} ms"
        )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    """``python -m companion.lab.bench NAME=MODEL.onnx ...``: time ONNX models side by side."""
    import argparse  # noqa: PLC0415
    import json  # noqa: PLC0415

    p = argparse.ArgumentParser(prog="python -m companion.lab.bench", description=main.__doc__)
    p.add_argument("models", nargs="+", metavar="NAME=MODEL.onnx")
    p.add_argument("--frames", type=int, default=200)
    p.add_argument(
        "--input-size",
        type=int,
        default=None,
        help="letterbox size of Wingman exports, px (default: detector.input_size_px's default)",
    )
    p.add_argument("--threads", type=int, default=2)
    p.add_argument("--json", default=None)
    args = p.parse_args(argv)
    models = dict(m.split("=", 1) if "=" in m else (m, m) for m in args.models)
    if args.input_size is None:
        from companion.config import DetectorConfig  # noqa: PLC0415

        args.input_size = DetectorConfig().input_size_px
    result = compare_onnx_models(models, synthetic_frames(args.frames), args.input_size, args.threads)
    print(format_comparison(result))
    if args.json:
        with open(args.json, "w") as f:
            json.dump(result, f, indent=2)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
