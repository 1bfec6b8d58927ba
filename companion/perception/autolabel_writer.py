"""Writes auto-labelled frames as a detector dataset, behind a queue so the flight loop never waits.

Layout (what ``companion detector train --data`` and ``eval`` read): ``images/NAME.jpg``,
``labels/NAME.txt`` (YOLO, empty for a negative), ``manifest.csv`` with one row per written frame (verdict,
quality, the expected range and ``range_m``, which is the true range in the simulator, and there the
renderer's true box too). Rejected frames are counted, never written.

The queue is bounded: when the disk or the encoder falls behind, frames are dropped and counted, not
waited for. Writing stops at ``max_bytes`` (counted as ``over_budget``).
"""

from __future__ import annotations

import contextlib
import csv
import logging
import os
import queue
import threading
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from companion.kernel.camera import RgbdFrame
from companion.perception.autolabel import AutoLabel, Verdict
from companion.perception.detector.dataset import format_yolo_labels

log = logging.getLogger(__name__)

#: The writer thread's nice value (0 = as the flight loop, 19 = lowest).
WRITER_NICE = 10

MANIFEST_COLUMNS = (
    "image",
    "sequence",
    "stamp_s",
    "verdict",
    "quality",
    "expected_range_m",
    "range_m",
    "truth_box_xyxy_px",
    "truth_visible_fraction",
)


@dataclass(slots=True)
class AutoLabelCounts:
    """What became of every frame offered to the writer."""

    labels: int = 0
    negatives: int = 0
    rejected: int = 0
    dropped: int = 0
    over_budget: int = 0
    bytes_written: int = 0
    reasons: dict[str, int] = field(default_factory=dict)

    def as_dict(self) -> dict[str, Any]:
        return {
            "labels": self.labels,
            "negatives": self.negatives,
            "rejected": self.rejected,
            "dropped": self.dropped,
            "over_budget": self.over_budget,
            "bytes_written": self.bytes_written,
            "rejected_by_reason": dict(sorted(self.reasons.items())),
        }


class AutoLabelWriter:
    """Background writer of auto-labelled frames (see the module docstring). Use as a context manager.

    Args:
        out_dir: an empty or new folder.
        sequence: recorded in the manifest (which flight the frames come from).
        max_bytes: stop writing beyond this many bytes of images and labels.
        queue_frames: frames waiting to be encoded before new ones are dropped.
        negative_every: keep one negative frame in this many (drone-free frames are plentiful).
    """

    def __init__(
        self,
        out_dir: Path,
        *,
        sequence: str = "0",
        max_bytes: int = 2_000_000_000,
        queue_frames: int = 32,
        negative_every: int = 5,
        jpeg_quality: int = 92,
    ) -> None:
        self.out_dir = Path(out_dir)
        self.sequence = sequence
        self.max_bytes = max_bytes
        self.negative_every = max(1, negative_every)
        self.jpeg_quality = jpeg_quality
        self.counts = AutoLabelCounts()
        self._negatives_seen = 0
        self._queue: queue.Queue[tuple[RgbdFrame, AutoLabel] | None] = queue.Queue(maxsize=queue_frames)
        self._thread: threading.Thread | None = None
        self._manifest: Any = None
        self._rows: Any = None
        self._lock = threading.Lock()

    def __enter__(self) -> AutoLabelWriter:
        if self.out_dir.exists() and any(self.out_dir.iterdir()):
            raise FileExistsError(f"auto-label folder is not empty: {self.out_dir}")
        (self.out_dir / "images").mkdir(parents=True, exist_ok=True)
        (self.out_dir / "labels").mkdir(parents=True, exist_ok=True)
        self._manifest = (self.out_dir / "manifest.csv").open("w", newline="")
        self._rows = csv.writer(self._manifest)
        self._rows.writerow(MANIFEST_COLUMNS)
        self._thread = threading.Thread(target=self._run, name="autolabel-writer", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *_: object) -> None:
        self._queue.put(None)
        if self._thread is not None:
            self._thread.join()
        if self._manifest is not None:
            self._manifest.close()

    def offer(self, frame: RgbdFrame, label: AutoLabel) -> None:
        """Hand one frame and its verdict over; never blocks (a full queue drops the frame)."""
        if label.verdict is Verdict.REJECTED:
            with self._lock:
                self.counts.rejected += 1
                key = (
                    label.reason.split(" ")[0]
                    if label.reason.startswith(("range", "blob", "quality"))
                    else label.reason
                )
                self.counts.reasons[key] = self.counts.reasons.get(key, 0) + 1
            return
        if label.verdict is Verdict.NEGATIVE:
            self._negatives_seen += 1
            if (self._negatives_seen - 1) % self.negative_every:
                return
        try:
            self._queue.put_nowait((frame, label))
        except queue.Full:
            with self._lock:
                self.counts.dropped += 1

    def _run(self) -> None:
        # Below the flight loop: on Linux a thread has its own nice value, so encoding yields the cores to
        # the detector whenever both want them.
        with contextlib.suppress(AttributeError, OSError):
            os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), WRITER_NICE)
        while True:
            item = self._queue.get()
            if item is None:
                return
            frame, label = item
            try:
                self._write(frame, label)
            except OSError as exc:  # a full or failing disk: count, say it once, keep the flight loop alive
                with self._lock:
                    self.counts.dropped += 1
                log.warning("auto-label writer: %s", exc)

    def _write(self, frame: RgbdFrame, label: AutoLabel) -> None:
        with self._lock:
            if self.counts.bytes_written >= self.max_bytes:
                self.counts.over_budget += 1
                return
        name = f"{self.sequence}_f{frame.seq:06d}"
        ok, buf = cv2.imencode(
            ".jpg", cv2.cvtColor(frame.rgb, cv2.COLOR_RGB2BGR), [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality]
        )
        if not ok:
            raise OSError(f"cannot encode frame {frame.seq}")
        (self.out_dir / "images" / f"{name}.jpg").write_bytes(buf.tobytes())
        w, h = frame.intrinsics.width_px, frame.intrinsics.height_px
        boxes = np.asarray([label.box_xyxy_px] if label.box_xyxy_px is not None else [], np.float32).reshape(
            -1, 4
        )
        text = format_yolo_labels(boxes, w, h)
        (self.out_dir / "labels" / f"{name}.txt").write_text(text)
        truth = frame.truth
        # The leader's range: the renderer's where it is known (simulator), else the expected one.
        range_m = f"{truth.p_cam_leader_m[2]:.2f}" if truth is not None else f"{label.expected_range_m:.2f}"
        truth_box = (
            ""
            if truth is None or truth.box_xyxy_px is None
            else " ".join(f"{v:.1f}" for v in truth.box_xyxy_px)
        )
        self._rows.writerow(
            (
                f"{name}.jpg",
                self.sequence,
                f"{frame.stamp_s:.4f}",
                label.verdict.value,
                f"{label.quality:.3f}",
                f"{label.expected_range_m:.2f}",
                range_m,
                truth_box,
                "" if truth is None else f"{truth.visible_fraction:.3f}",
            )
        )
        with self._lock:
            self.counts.bytes_written += len(buf) + len(text)
            if label.verdict is Verdict.LABEL:
                self.counts.labels += 1
            else:
                self.counts.negatives += 1
