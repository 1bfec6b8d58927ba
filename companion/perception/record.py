"""Write frames to the folder recording format (:mod:`companion.perception.sources.file`).

``companion record`` uses it to keep a field flight or a rendered sequence (with its ground truth and
the follower's attitude) so that ``companion replay`` can run perception on it later, frame-exact.
"""

from __future__ import annotations

import csv
import io
import json
from pathlib import Path
from types import TracebackType

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import Intrinsics, RgbdFrame
from companion.kernel.compat import Self
from companion.kernel.errors import CompanionError
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
