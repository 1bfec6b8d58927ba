"""Record a source to the folder recording format (:mod:`companion.perception.sources.file`) or a .bag.

``companion record`` (:func:`run_record`) uses it to keep a field flight or a rendered sequence (with its
ground truth and the follower's attitude) so that ``companion replay`` can run perception on it later,
frame-exact. :func:`run_record` copies any source (``sim``, ``realsense``, ``file:PATH``) to the folder
format, or to a RealSense ``.bag`` when the output ends in ``.bag``; a folder keeps the ground truth when
the source has some (a .bag has no place for it).
"""

from __future__ import annotations

import asyncio
import csv
import io
import json
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.config import Config
from companion.kernel import compat
from companion.kernel.camera import Intrinsics, RgbdFrame
from companion.kernel.compat import Self
from companion.kernel.errors import CompanionError
from companion.perception.sources import open_source, parse_source
from companion.perception.sources.file import (
    ATTITUDE_FILE,
    DEFAULT_DEPTH_SCALE_M,
    INDEX_FILE,
    INTRINSICS_FILE,
    TRUTH_FILE,
    depth_to_u16,
    intrinsics_to_json,
    truth_to_json,
)

#: Frames waiting for the writer (about 2 MB each at 640 x 480): a few seconds of a slow disk.
RECORD_QUEUE_FRAMES = 90


class RecordError(CompanionError):
    """The recording cannot be written (existing non-empty folder, disk full, changing intrinsics)."""


class FolderRecorder:
    """Writes frames to ``out_dir`` in the folder format. A context manager; ``write`` per frame.

    Args:
        out_dir: created if missing; must be empty if it exists (never overwrite a recording).
        image_format: "png" keeps colour lossless (frame-exact replays); "jpg" is ~10x smaller.
    """

    def __init__(self, out_dir: Path, *, image_format: str = "png", jpeg_quality: int = 95) -> None:
        if image_format not in ("png", "jpg"):
            raise ValueError(f"image_format must be png or jpg, got {image_format!r}")
        self.out_dir = out_dir
        self.image_format = image_format
        self.jpeg_quality = jpeg_quality
        self.scale_m = DEFAULT_DEPTH_SCALE_M
        self.frames_written = 0
        self._intr: Intrinsics | None = None
        self._index: io.TextIOWrapper | None = None
        self._index_csv: csv.DictWriter[str] | None = None
        self._truth: io.TextIOWrapper | None = None
        self._attitude: io.TextIOWrapper | None = None

    def __enter__(self) -> Self:
        if self.out_dir.exists() and (not self.out_dir.is_dir() or any(self.out_dir.iterdir())):
            raise RecordError(f"record: {self.out_dir} exists and is not an empty folder")
        try:
            (self.out_dir / "rgb").mkdir(parents=True, exist_ok=True)
            (self.out_dir / "depth").mkdir(exist_ok=True)
        except OSError as exc:
            raise RecordError(f"record: cannot create {self.out_dir}: {exc.strerror}") from None
        self._index = (self.out_dir / INDEX_FILE).open("w", newline="")
        self._index_csv = csv.DictWriter(self._index, fieldnames=["seq", "stamp_s", "rgb", "depth"])
        self._index_csv.writeheader()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        for f in (self._index, self._truth, self._attitude):
            if f is not None:
                f.close()
        self._index = self._truth = self._attitude = None

    def write(self, frame: RgbdFrame) -> None:
        """Append one frame (and its ground truth, when it has some)."""
        if self._index_csv is None:
            raise RecordError("record: write() outside `with FolderRecorder(...)`")
        if self._intr is None:
            self._intr = frame.intrinsics
            text = json.dumps(intrinsics_to_json(frame.intrinsics, self.scale_m), indent=2)
            (self.out_dir / INTRINSICS_FILE).write_text(text + "\n")
        elif frame.intrinsics != self._intr:
            raise RecordError(f"record: intrinsics changed at frame {frame.seq}; start a new recording")
        name = f"{frame.seq:06d}"
        rgb_rel = f"rgb/{name}.{self.image_format}"
        depth_rel = f"depth/{name}.png"
        bgr = np.ascontiguousarray(frame.rgb[..., ::-1])
        params = [cv2.IMWRITE_JPEG_QUALITY, self.jpeg_quality] if self.image_format == "jpg" else []
        ok = cv2.imwrite(str(self.out_dir / rgb_rel), bgr, params)
        # Stereo depth is noisy and compresses little: fast RLE keeps up with a 30 Hz camera.
        depth_params = [
            cv2.IMWRITE_PNG_COMPRESSION,
            1,
            cv2.IMWRITE_PNG_STRATEGY,
            cv2.IMWRITE_PNG_STRATEGY_RLE,
        ]
        ok = ok and cv2.imwrite(
            str(self.out_dir / depth_rel), depth_to_u16(frame.depth_m, self.scale_m), depth_params
        )
        if not ok:
            raise RecordError(f"record: cannot write frame {frame.seq} to {self.out_dir}")
        self._index_csv.writerow(
            {"seq": frame.seq, "stamp_s": repr(float(frame.stamp_s)), "rgb": rgb_rel, "depth": depth_rel}
        )
        if frame.truth is not None:
            if self._truth is None:
                self._truth = (self.out_dir / TRUTH_FILE).open("w")
            self._truth.write(json.dumps(truth_to_json(frame.seq, frame.truth)) + "\n")
        self.frames_written += 1

    def write_attitude(self, stamp_s: float, q_ned_body_wxyz: NDArray[np.float64]) -> None:
        """Append one follower attitude sample (from telemetry) to ``attitude.csv``."""
        if self._attitude is None:
            self._attitude = (self.out_dir / ATTITUDE_FILE).open("w", newline="")
            csv.writer(self._attitude).writerow(["stamp_s", "qw", "qx", "qy", "qz"])
        row = [repr(float(stamp_s)), *(repr(float(c)) for c in q_ned_body_wxyz)]
        csv.writer(self._attitude).writerow(row)


@dataclass(frozen=True, slots=True)
class RecordResult:
    """What ``record`` kept: frames written, and frames the source numbered but never delivered."""

    frames: int
    #: Gaps in the source's frame numbers: the camera (or the simulator's server, when the reader lags)
    #: dropped them before they reached the recorder.
    skipped_by_source: int
    largest_gap_s: float

    def line(self, out: Path) -> str:
        """One line for the operator."""
        if not self.skipped_by_source:
            return f"recorded {self.frames} frames to {out}, none skipped"
        return (
            f"recorded {self.frames} frames to {out}; the source skipped {self.skipped_by_source} "
            f"(gaps in its frame numbers, longest {self.largest_gap_s:.2f} s): the camera dropped them "
            "before they were read"
        )


async def run_record(
    cfg: Config, source_spec: str, out: Path, *, max_frames: int = 0, image_format: str = "png"
) -> RecordResult:
    """Copy frames from a source to a folder recording (or a RealSense .bag).

    The source is read by one task and frames are written by a worker thread behind a bounded queue, so
    a slow disk or PNG encoder never stalls the reading (a live source drops what is not read).
    """
    from companion.perception.sources.bag_writer import RealSenseBagWriter  # noqa: PLC0415

    camera = parse_source(source_spec, cfg.camera).model_copy(update={"loop": False})
    writer: FolderRecorder | RealSenseBagWriter
    if out.suffix.lower() == ".bag":
        writer = RealSenseBagWriter(out, fps=round(cfg.camera.fps))
    else:
        writer = FolderRecorder(out, image_format=image_format)
    queue: asyncio.Queue[RgbdFrame | None] = asyncio.Queue(maxsize=RECORD_QUEUE_FRAMES)
    n = skipped = 0
    largest_gap_s = 0.0

    async def write_all() -> None:
        while (frame := await queue.get()) is not None:
            await asyncio.to_thread(writer.write, frame)

    with writer:
        async with open_source(camera) as src, compat.TaskGroup() as tg:
            tg.create_task(write_all(), name="companion.record.writer")
            # A folder's own attitude.csv travels with it (truth-derived attitude is rebuilt on read).
            if isinstance(writer, FolderRecorder) and (Path(camera.path) / "attitude.csv").is_file():
                for stamp_s, q in getattr(src, "attitude", []):
                    writer.write_attitude(stamp_s, q)
            prev: RgbdFrame | None = None
            try:
                async for frame in src:
                    if prev is not None and frame.seq > prev.seq + 1:
                        skipped += frame.seq - prev.seq - 1
                        largest_gap_s = max(largest_gap_s, frame.stamp_s - prev.stamp_s)
                    prev = frame
                    await queue.put(frame)
                    n += 1
                    if max_frames and n >= max_frames:
                        break
            finally:
                await queue.put(None)
    return RecordResult(n, skipped, largest_gap_s)
