"""Auto-labels in the lockstep harness, scored against the renderer's true boxes.

The labeller sees only what the service would: the follower's own telemetry (its EKF position and
attitude), the leader's shared position as the leader's own EKF publishes it (sampled at ``share_rate_hz``,
``share_latency_s`` old on arrival, extrapolated with its shared velocity), the camera mounting and the depth
image. The renderer's truth reaches only the score.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from companion.kernel.camera import RgbdFrame
from companion.kernel.flight import Vec3T, VehicleState
from companion.lab.evaluation.scoring import iou
from companion.mission.types import SharedLeaderPosition
from companion.perception.autolabel import AutoLabel, AutoLabelConfig, Verdict
from companion.perception.autolabel_writer import AutoLabelWriter
from companion.perception.transform import AttitudeHistory, CameraGeometry
from companion.service.autolabel_tap import SharedLeaderTrack, label_frame

#: IoU a label must reach against the true box to count as right.
GOOD_IOU = 0.7


@dataclass(slots=True)
class LeaderShare:
    """The leader's shared position as it reaches the follower: its own estimate, sampled and delayed.

    Positions are in the follower's local NED frame (the leader's local estimate moved by the offset
    between both EKF origins, as the service does with geodetic positions). What arrives goes into the
    service's own :class:`~companion.service.autolabel_tap.SharedLeaderTrack`.
    """

    rate_hz: float = 10.0
    latency_s: float = 0.1
    _pending: deque[tuple[float, SharedLeaderPosition]] = field(default_factory=deque)
    _next_s: float = 0.0

    def due(self, t_s: float) -> bool:
        """Whether a share is sent at ``t_s`` (``rate_hz``): look up the leader's estimate only then."""
        return t_s + 1e-9 >= self._next_s

    def sample(self, t_s: float, p_ned_m: Vec3T, valid: bool) -> None:
        """Send the leader's estimate at ``t_s`` when due; nothing while its GPS is not good."""
        if not self.due(t_s):
            return
        self._next_s = t_s + 1.0 / self.rate_hz
        if valid:
            self._pending.append((t_s + self.latency_s, SharedLeaderPosition(t_s, p_ned_m)))

    def arrived(self, t_s: float) -> list[SharedLeaderPosition]:
        """The shares that reached the follower by ``t_s``, oldest first."""
        out = []
        while self._pending and self._pending[0][0] <= t_s + 1e-9:
            out.append(self._pending.popleft()[1])
        return out


@dataclass(slots=True)
class _Score:
    frames: int = 0
    gated_out: int = 0
    labels: int = 0
    good: int = 0
    ious: list[float] = field(default_factory=list)
    false_labels: int = 0
    leader_free_frames: int = 0
    negatives: int = 0
    negatives_with_leader: int = 0
    rejected: int = 0
    rejected_visible: int = 0
    visible_frames: int = 0


class AutoLabelCheck:
    """Labels every delivered frame while GPS is good and the share fresh; scores it; writes it."""

    def __init__(
        self,
        out_dir: Path | None,
        cfg: AutoLabelConfig,
        geometry: CameraGeometry,
        sequence: str,
        truth_dir: Path | None = None,
    ):
        self.cfg = cfg
        self.geometry = geometry
        self.share = LeaderShare()
        self.leader = SharedLeaderTrack(max_age_s=0.5)
        self.score = _Score()
        self.writer = AutoLabelWriter(out_dir, sequence=sequence) if out_dir is not None else None
        #: Every frame with the renderer's own box (an evaluation set; never a training set for a product).
        self.truth_writer = (
            AutoLabelWriter(truth_dir, sequence=sequence, negative_every=1) if truth_dir is not None else None
        )

    def __enter__(self) -> AutoLabelCheck:
        for w in (self.writer, self.truth_writer):
            if w is not None:
                w.__enter__()
        return self

    def __exit__(self, *exc: object) -> None:
        for w in (self.writer, self.truth_writer):
            if w is not None:
                w.__exit__(*exc)

    def on_frame(
        self, t_s: float, frame: RgbdFrame, vehicle: VehicleState, attitude: AttitudeHistory
    ) -> None:
        sc = self.score
        sc.frames += 1
        if self.truth_writer is not None and frame.truth is not None:
            box = frame.truth.box_xyxy_px
            truth_label = (
                AutoLabel(Verdict.LABEL, "truth", box, 1.0)
                if box is not None
                else AutoLabel(Verdict.NEGATIVE, "truth")
            )
            self.truth_writer.offer(frame, truth_label)
        for position in self.share.arrived(t_s):
            self.leader.add(position)
        leader = self.leader.at(frame.stamp_s)
        label = label_frame(frame, vehicle, attitude, leader, geometry=self.geometry, cfg=self.cfg)
        if label is None:
            sc.gated_out += 1
            return
        truth = frame.truth
        true_box = None if truth is None else truth.box_xyxy_px
        if true_box is not None:
            sc.visible_frames += 1
        else:
            sc.leader_free_frames += 1
        if label.verdict is Verdict.LABEL:
            sc.labels += 1
            if true_box is None or label.box_xyxy_px is None:
                sc.false_labels += 1
            else:
                overlap = iou(label.box_xyxy_px, true_box)
                sc.ious.append(overlap)
                sc.good += overlap >= GOOD_IOU
        elif label.verdict is Verdict.NEGATIVE:
            sc.negatives += 1
            sc.negatives_with_leader += true_box is not None
        else:
            sc.rejected += 1
            sc.rejected_visible += true_box is not None
        if self.writer is not None:
            self.writer.offer(frame, label)

    def summary(self) -> dict[str, Any]:
        sc = self.score
        ious = np.asarray(sc.ious) if sc.ious else np.zeros(0)
        out: dict[str, Any] = {
            "frames": sc.frames,
            "gated_out": sc.gated_out,
            "visible_frames": sc.visible_frames,
            "leader_free_frames": sc.leader_free_frames,
            "labels": sc.labels,
            "labels_iou_ge_0_7": sc.good,
            "share_iou_ge_0_7": round(sc.good / sc.labels, 4) if sc.labels else None,
            "iou_p10_p50": [round(float(np.percentile(ious, q)), 3) for q in (10, 50)] if ious.size else None,
            "false_labels": sc.false_labels,
            "false_label_rate_on_leader_free": (
                round(sc.false_labels / sc.leader_free_frames, 4) if sc.leader_free_frames else None
            ),
            "negatives": sc.negatives,
            "negatives_with_leader_visible": sc.negatives_with_leader,
            "rejected": sc.rejected,
            "rejected_while_visible": sc.rejected_visible,
            "label_yield_on_visible": round(sc.labels / sc.visible_frames, 4) if sc.visible_frames else None,
        }
        if self.writer is not None:
            out["written"] = self.writer.counts.as_dict()
        if self.truth_writer is not None:
            out["truth_written"] = self.truth_writer.counts.as_dict()
        return out


def write_sheet(
    dataset_dir: Path, path: Path, *, tiles: int = 24, tile_px: int = 160, columns: int = 6
) -> int:
    """A contact sheet of a folder's auto-labels, the least sure first; returns the number of tiles.

    Crops around each label (green), the renderer's true box where the manifest has one (blue), the
    quality (and IoU with the truth) under each.
    """
    import csv  # noqa: PLC0415

    import cv2  # noqa: PLC0415

    with (dataset_dir / "manifest.csv").open(newline="") as f:
        rows = [r for r in csv.DictReader(f) if r["verdict"] == "label"]
    rows.sort(key=lambda r: float(r["quality"]))
    half = tiles // 2
    step = max(1, (len(rows) - half) // max(1, tiles - half))
    picked = rows[:half] + rows[half::step][: tiles - half]
    out = []
    for r in picked:
        bgr = cv2.imread(str(dataset_dir / "images" / r["image"]))
        if bgr is None:
            continue
        h, w = bgr.shape[:2]
        text = (dataset_dir / "labels" / Path(r["image"]).with_suffix(".txt")).read_text().split()
        cx, cy, bw, bh = (float(v) for v in text[1:5])
        box = ((cx - bw / 2) * w, (cy - bh / 2) * h, (cx + bw / 2) * w, (cy + bh / 2) * h)
        side = max(64.0, 3.0 * max(box[2] - box[0], box[3] - box[1]))
        ax0 = int(np.clip((box[0] + box[2] - side) / 2, 0, max(0, w - side)))
        ay0 = int(np.clip((box[1] + box[3] - side) / 2, 0, max(0, h - side)))
        s = int(min(side, w, h))
        scale = tile_px / s
        big = cv2.resize(
            bgr[ay0 : ay0 + s, ax0 : ax0 + s], (tile_px, tile_px), interpolation=cv2.INTER_NEAREST
        )

        def rect(b: tuple[float, ...], colour: tuple[int, int, int], at: tuple[Any, ...]) -> None:
            img, ox, oy, k = at
            cv2.rectangle(
                img,
                (round((b[0] - ox) * k), round((b[1] - oy) * k)),
                (round((b[2] - ox) * k), round((b[3] - oy) * k)),
                colour,
                1,
            )

        at = (big, ax0, ay0, scale)
        caption = f"q {float(r['quality']):.2f}"
        if r["truth_box_xyxy_px"]:
            truth = tuple(float(v) for v in r["truth_box_xyxy_px"].split())
            rect(truth, (255, 80, 0), at)
            caption += f"  IoU {iou(box, truth):.2f}"
        rect(box, (0, 200, 0), at)
        canvas = np.full((tile_px + 16, tile_px, 3), 255, np.uint8)
        canvas[:tile_px] = big
        cv2.putText(canvas, caption, (2, tile_px + 12), 0, 0.38, (0, 0, 0), 1)
        out.append(canvas)
    if not out:
        return 0
    rows_img = []
    for i in range(0, len(out), columns):
        row = out[i : i + columns] + [np.full_like(out[0], 255)] * (columns - len(out[i : i + columns]))
        rows_img.append(np.concatenate(row, 1))
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.concatenate(rows_img, 0))
    return len(out)
