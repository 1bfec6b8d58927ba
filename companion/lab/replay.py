"""Replay perception over a recording: errors of the pose stage and the tracker against ground truth.

frames from ``--source`` -> detector -> pose -> tracker, one CSV row per frame (``--out``), and a summary
on stdout: position RMSE by range bin, bearing RMSE, the raw measurement's RMSE, the paper's centre-patch
depth on the same boxes, and per-stage time. ``--detector truth`` uses the recording's ground-truth boxes
(with ``--box-jitter-px``) to measure pose + tracker on their own. Recording a source is
:func:`companion.perception.record.run_record`.
"""

from __future__ import annotations

import csv
import io
import math
import time

import numpy as np

from companion.config import Config
from companion.estimation.estimate import TrackState
from companion.estimation.pipeline import PerceptionPipeline
from companion.kernel.camera import RgbdFrame
from companion.lab.perception_eval import (
    FrameError,
    Summary,
    angle_between_deg,
    paper_centre_depth_m,
)
from companion.perception.pose import back_project
from companion.perception.sources import open_source, parse_source
from companion.perception.transform import AttitudeHistory, CameraGeometry
from companion.perception.truth_detector import TruthDetector
from companion.perception.types import DetectorResult, DetectStage

CSV_FIELDS = [
    "seq",
    "stamp_s",
    "n_det",
    "status",
    "track_id",
    "meas_x_m",
    "meas_y_m",
    "meas_z_m",
    "meas_source",
    "meas_px",
    "est_x_m",
    "est_y_m",
    "est_z_m",
    "est_n_m",
    "est_e_m",
    "est_d_m",
    "est_vn_m_s",
    "est_ve_m_s",
    "est_vd_m_s",
    "sd_x_m",
    "sd_y_m",
    "sd_z_m",
    "az_deg",
    "el_deg",
    "truth_x_m",
    "truth_y_m",
    "truth_z_m",
    "truth_range_m",
    "err_m",
    "bearing_err_deg",
    "meas_err_m",
    "paper_err_m",
    "det_ms",
    "pose_ms",
    "track_ms",
]


def make_detect(
    kind: str, cfg: Config, *, jitter_px: float, seed: int, miss_rate: float = 0.0
) -> DetectStage:
    """The detection step for ``--detector``: the configured model, or ground-truth boxes."""
    if kind == "truth":
        oracle = TruthDetector(jitter_px=jitter_px, miss_rate=miss_rate, seed=seed)
        return DetectStage(oracle.detect_frame, description="ground-truth boxes")
    from companion.perception.detector import detect_stage  # noqa: PLC0415 (onnxruntime/torch: heavy)

    return detect_stage(cfg.detector)


def _fmt(x: float | None) -> str:
    return "" if x is None or not math.isfinite(x) else f"{x:.6g}"


def evaluate_frame(
    frame: RgbdFrame, state: TrackState, result: DetectorResult, summary: Summary
) -> dict[str, str]:
    """CSV row of one frame; adds its errors to ``summary`` when the track is usable and truth exists."""
    row: dict[str, str] = {k: "" for k in CSV_FIELDS}
    row.update(
        seq=str(frame.seq),
        stamp_s=repr(frame.stamp_s),
        n_det=str(len(result.detections)),
        status=state.status.value,
        track_id=str(state.track_id),
    )
    if state.usable:
        summary.frames_tracked += 1
    m = state.measurement
    if m is not None:
        row.update(
            meas_source=m.range_source,
            meas_px=str(m.n_depth_px),
            meas_x_m=_fmt(m.p_cam_leader_m[0]),
            meas_y_m=_fmt(m.p_cam_leader_m[1]),
            meas_z_m=_fmt(m.p_cam_leader_m[2]),
        )
    est = state.estimate
    if est is not None:
        sd = np.sqrt(np.diag(est.cov_cam_m2))
        row.update(
            est_x_m=_fmt(est.p_cam_leader_m[0]),
            est_y_m=_fmt(est.p_cam_leader_m[1]),
            est_z_m=_fmt(est.p_cam_leader_m[2]),
            est_n_m=_fmt(est.p_ned_rel_m[0]),
            est_e_m=_fmt(est.p_ned_rel_m[1]),
            est_d_m=_fmt(est.p_ned_rel_m[2]),
            est_vn_m_s=_fmt(est.v_ned_rel_m_s[0]),
            est_ve_m_s=_fmt(est.v_ned_rel_m_s[1]),
            est_vd_m_s=_fmt(est.v_ned_rel_m_s[2]),
            sd_x_m=_fmt(sd[0]),
            sd_y_m=_fmt(sd[1]),
            sd_z_m=_fmt(sd[2]),
            az_deg=_fmt(math.degrees(est.azimuth_rad)),
            el_deg=_fmt(math.degrees(est.elevation_rad)),
        )
    truth = frame.truth
    if truth is None:
        return row
    summary.frames_with_truth += 1
    if truth.box_xyxy_px is None:
        return row  # the leader out of view: nothing to compare with
    summary.frames_in_view += 1
    p_true = truth.p_cam_leader_m
    rng = float(np.linalg.norm(p_true))
    row.update(
        truth_x_m=_fmt(p_true[0]),
        truth_y_m=_fmt(p_true[1]),
        truth_z_m=_fmt(p_true[2]),
        truth_range_m=_fmt(rng),
    )
    meas_err = None if m is None else float(np.linalg.norm(m.p_cam_leader_m - p_true))
    paper_err = None
    if result.detections:
        best = max(result.detections, key=lambda d: d.score)
        z = paper_centre_depth_m(frame.depth_m, best)
        if z is not None:
            u, v = best.center_px
            paper_err = float(np.linalg.norm(back_project(u, v, z, frame.intrinsics) - p_true))
    row.update(meas_err_m=_fmt(meas_err), paper_err_m=_fmt(paper_err))
    if est is not None and state.usable:
        err = float(np.linalg.norm(est.p_cam_leader_m - p_true))
        brg = angle_between_deg(est.p_cam_leader_m, p_true)
        row.update(err_m=_fmt(err), bearing_err_deg=_fmt(brg))
        summary.frames_usable += 1
        summary.errors.append(FrameError(rng, err, brg, meas_err, paper_err))
    return row


async def run_replay(
    cfg: Config,
    source_spec: str,
    stage: DetectStage,
    *,
    out_csv: io.TextIOBase | None = None,
    realtime: bool = False,
    max_frames: int = 0,
) -> Summary:
    """Run perception over a source; write CSV rows to ``out_csv`` and return the summary.

    ``max_frames``: stop after that many frames (0: at the end of a recording; a live source, ``sim`` or
    ``realsense``, runs until interrupted).
    """
    camera = parse_source(source_spec, cfg.camera).model_copy(update={"realtime": realtime, "loop": False})
    source = open_source(camera)
    summary = Summary()
    writer = None
    if out_csv is not None:
        writer = csv.DictWriter(out_csv, fieldnames=CSV_FIELDS)
        writer.writeheader()
    async with source as src:
        samples = getattr(src, "attitude", [])
        pipeline = PerceptionPipeline(
            cfg.leader,
            cfg.pose,
            cfg.tracker,
            CameraGeometry.from_mount(cfg.camera.mount),
            AttitudeHistory(capacity=max(512, len(samples) + 2)),
        )
        for stamp_s, q in samples:
            pipeline.attitude.push(stamp_s, q)
        # A live source (the simulator's camera) has no attitude list: its frames carry the follower's
        # attitude in their ground truth, which a folder recording of them reads back as its attitude. Fed
        # here, live and recorded frames are scored the same; without it the tracker assumed a level,
        # unturning follower, and its errors were the follower's turns and tilts (ten times the recording's).
        from_frames = not samples
        summary.attitude = "recording" if samples else "none"
        async for frame in src:
            q_truth = None if frame.truth is None else frame.truth.q_ned_follower_wxyz
            if from_frames and q_truth is not None:
                pipeline.attitude.push(frame.stamp_s, q_truth)
                summary.attitude = "ground truth"
            t0 = time.perf_counter()
            result = stage.detect(frame)
            t1 = time.perf_counter()
            measurements = pipeline.measure(frame, result.detections)
            t2 = time.perf_counter()
            state = pipeline.track(frame.stamp_s, measurements)
            t3 = time.perf_counter()
            stage.after_track(state)
            summary.frames += 1
            summary.add_timing("detector", (t1 - t0) * 1e3)
            summary.add_timing("pose", (t2 - t1) * 1e3)
            summary.add_timing("track", (t3 - t2) * 1e3)
            summary.add_timing("pose+track", (t3 - t1) * 1e3)
            row = evaluate_frame(frame, state, result, summary)
            row.update(
                det_ms=_fmt((t1 - t0) * 1e3), pose_ms=_fmt((t2 - t1) * 1e3), track_ms=_fmt((t3 - t2) * 1e3)
            )
            if writer is not None:
                writer.writerow(row)
            if max_frames and summary.frames >= max_frames:
                break
    return summary
