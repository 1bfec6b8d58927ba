"""The folder recording format, and the frame source that plays it back.

A recording is a folder::

    intrinsics.json   {"fx_px", "fy_px", "cx_px", "cy_px", "width_px", "height_px", "depth_scale_m"}
    frames.csv        seq,stamp_s,rgb,depth     (file paths relative to the folder)
    rgb/000000.png    colour, PNG or JPEG (any name)
    depth/000000.png  16-bit PNG, depth along the optical axis in depth_scale_m units (1 mm), 0 = invalid
    truth.jsonl       optional: one ground-truth object per frame, with its "seq" (rendered recordings)
    attitude.csv      optional: stamp_s,qw,qx,qy,qz  the follower's attitude q_ned_body (telemetry)

Without ``frames.csv``, colour files in ``rgb/`` pair with the same-named depth PNG in ``depth/`` in
name order, stamped at ``1 / fps`` intervals. Depth is aligned to the colour camera (same intrinsics).
Stamps are written with full float precision, so a recording reads back frame-exact.
"""

from __future__ import annotations

import asyncio
import csv
import json
import math
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from companion.kernel.camera import DepthImage, GroundTruth, Intrinsics, RgbdFrame, RgbImage
from companion.kernel.clock import Clock
from companion.kernel.compat import Self
from companion.kernel.errors import CameraError
from companion.perception.sources._pacing import Pacer

INTRINSICS_FILE = "intrinsics.json"
INDEX_FILE = "frames.csv"
TRUTH_FILE = "truth.jsonl"
ATTITUDE_FILE = "attitude.csv"
DEFAULT_DEPTH_SCALE_M = 0.001
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(frozen=True, slots=True)
class FrameEntry:
    """One line of ``frames.csv``."""

    seq: int
    stamp_s: float
    rgb_path: Path
    depth_path: Path


#: Largest value a 16-bit PNG holds; deeper pixels are written as invalid (0).
_U16_MAX = 65535


def depth_to_u16(depth_m: DepthImage, scale_m: float = DEFAULT_DEPTH_SCALE_M) -> NDArray[np.uint16]:
    """Depth in metres to 16-bit units of ``scale_m`` (rounded); invalid, NaN or out of range -> 0."""
    units: NDArray[np.float64] = np.rint(np.nan_to_num(depth_m, nan=0.0, posinf=0.0, neginf=0.0) / scale_m)
    units[(units < 0) | (units > _U16_MAX)] = 0
    out: NDArray[np.uint16] = units.astype(np.uint16)
    return out


def intrinsics_to_json(intr: Intrinsics, depth_scale_m: float) -> dict[str, Any]:
    """The ``intrinsics.json`` object."""
    return {
        "fx_px": intr.fx_px,
        "fy_px": intr.fy_px,
        "cx_px": intr.cx_px,
        "cy_px": intr.cy_px,
        "width_px": intr.width_px,
        "height_px": intr.height_px,
        "depth_scale_m": depth_scale_m,
    }


def _vec(v: Any) -> NDArray[np.float64] | None:
    return None if v is None else np.asarray(v, dtype=np.float64)


def truth_to_json(seq: int, truth: GroundTruth) -> dict[str, Any]:
    """One ``truth.jsonl`` object (floats keep full precision through ``json``)."""

    def lst(a: NDArray[np.float64] | None) -> list[float] | None:
        return None if a is None else [float(x) for x in a]

    return {
        "seq": seq,
        "box_xyxy_px": None if truth.box_xyxy_px is None else [float(x) for x in truth.box_xyxy_px],
        "visible_fraction": float(truth.visible_fraction),
        "p_cam_leader_m": lst(truth.p_cam_leader_m),
        "yaw_rel_rad": float(truth.yaw_rel_rad),
        "p_ned_follower_m": lst(truth.p_ned_follower_m),
        "p_ned_leader_m": lst(truth.p_ned_leader_m),
        "q_ned_follower_wxyz": lst(truth.q_ned_follower_wxyz),
    }


def truth_from_json(obj: dict[str, Any]) -> GroundTruth:
    """Inverse of :func:`truth_to_json`."""
    box = obj.get("box_xyxy_px")
    p_cam = _vec(obj["p_cam_leader_m"])
    if p_cam is None:
        raise ValueError("p_cam_leader_m is required")
    return GroundTruth(
        box_xyxy_px=None if box is None else (float(box[0]), float(box[1]), float(box[2]), float(box[3])),
        visible_fraction=float(obj.get("visible_fraction", 1.0)),
        p_cam_leader_m=p_cam,
        yaw_rel_rad=float(obj.get("yaw_rel_rad", 0.0)),
        p_ned_follower_m=_vec(obj.get("p_ned_follower_m")),
        p_ned_leader_m=_vec(obj.get("p_ned_leader_m")),
        q_ned_follower_wxyz=_vec(obj.get("q_ned_follower_wxyz")),
    )


def read_rgb(path: Path) -> RgbImage:
    """A colour image as RGB uint8 (OpenCV reads BGR)."""
    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise CameraError(f"{path}: cannot read the colour image")
    return np.ascontiguousarray(bgr[..., ::-1])


def read_depth(path: Path, scale_m: float) -> NDArray[np.float32]:
    """A 16-bit depth PNG as metres (float32, 0 = invalid)."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise CameraError(f"{path}: cannot read the depth image")
    if raw.dtype != np.uint16 or raw.ndim != 2:
        raise CameraError(f"{path}: depth must be a single-channel 16-bit PNG (got {raw.dtype}, {raw.shape})")
    return raw.astype(np.float32) * np.float32(scale_m)


def load_folder_index(
    root: Path, fps: float
) -> tuple[
    Intrinsics, float, list[FrameEntry], dict[int, GroundTruth], list[tuple[float, NDArray[np.float64]]]
]:
    """Intrinsics, depth scale, frame list, ground truth by seq and attitude samples of a recording.

    Raises:
        CameraError: with one line naming the missing or malformed part.
    """
    if not root.is_dir():
        raise CameraError(f"file source: {root} is not a folder (nor a .bag file)")
    try:
        meta = json.loads((root / INTRINSICS_FILE).read_text())
        intr = Intrinsics(
            float(meta["fx_px"]),
            float(meta["fy_px"]),
            float(meta["cx_px"]),
            float(meta["cy_px"]),
            int(meta["width_px"]),
            int(meta["height_px"]),
        )
        scale = float(meta.get("depth_scale_m", DEFAULT_DEPTH_SCALE_M))
    except FileNotFoundError:
        raise CameraError(f"file source: {root / INTRINSICS_FILE} is missing") from None
    except (ValueError, KeyError, TypeError) as exc:
        raise CameraError(f"file source: {root / INTRINSICS_FILE} is malformed ({exc!r})") from None

    entries: list[FrameEntry] = []
    index = root / INDEX_FILE
    if index.exists():
        with index.open(newline="") as f:
            try:
                for row in csv.DictReader(f):
                    entries.append(
                        FrameEntry(
                            int(row["seq"]), float(row["stamp_s"]), root / row["rgb"], root / row["depth"]
                        )
                    )
            except (KeyError, ValueError, TypeError) as exc:
                raise CameraError(f"file source: {index} is malformed ({exc!r})") from None
    else:
        rgbs = sorted(p for p in (root / "rgb").glob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
        for i, rgb in enumerate(rgbs):
            depth = root / "depth" / f"{rgb.stem}.png"
            if depth.exists():
                entries.append(FrameEntry(i, i / fps, rgb, depth))
    if not entries:
        raise CameraError(f"file source: {root} holds no frames ({INDEX_FILE}, or rgb/ + depth/ pairs)")

    truth: dict[int, GroundTruth] = {}
    tpath = root / TRUTH_FILE
    if tpath.exists():
        try:
            for line in tpath.read_text().splitlines():
                if line.strip():
                    obj = json.loads(line)
                    truth[int(obj["seq"])] = truth_from_json(obj)
        except (ValueError, KeyError, TypeError) as exc:
            raise CameraError(f"file source: {tpath} is malformed ({exc!r})") from None

    attitude: list[tuple[float, NDArray[np.float64]]] = []
    apath = root / ATTITUDE_FILE
    if apath.exists():
        with apath.open(newline="") as f:
            try:
                for row in csv.DictReader(f):
                    q = np.array([float(row[k]) for k in ("qw", "qx", "qy", "qz")])
                    attitude.append((float(row["stamp_s"]), q))
            except (KeyError, ValueError, TypeError) as exc:
                raise CameraError(f"file source: {apath} is malformed ({exc!r})") from None
    return intr, scale, entries, truth, attitude


class FolderSource:
    """Plays a folder recording (see the module docstring) as a :class:`FrameSource`.

    ``attitude`` holds the recording's follower attitude samples (from ``attitude.csv``, else from the
    ground truth), for replays to feed the attitude history. When looping, stamps and seq keep
    increasing (each pass is shifted by the recording's length plus one frame interval).
    """

    def __init__(
        self,
        path: Path,
        *,
        realtime: bool = False,
        loop: bool = False,
        fps: float = 30.0,
        clock: Clock | None = None,
    ) -> None:
        self.path = path
        self.loop = loop
        self.fps = fps
        self._pacer = Pacer(realtime=realtime, clock=clock)
        self._entries: list[FrameEntry] = []
        self._truth: dict[int, GroundTruth] = {}
        self._scale_m = DEFAULT_DEPTH_SCALE_M
        self.intrinsics: Intrinsics | None = None
        self.attitude: list[tuple[float, NDArray[np.float64]]] = []

    async def __aenter__(self) -> Self:
        intr, scale, entries, truth, attitude = await asyncio.to_thread(
            load_folder_index, self.path, self.fps
        )
        self.intrinsics, self._scale_m, self._entries, self._truth = intr, scale, entries, truth
        if not attitude:
            attitude = [
                (e.stamp_s, t.q_ned_follower_wxyz)
                for e in entries
                if (t := truth.get(e.seq)) is not None and t.q_ned_follower_wxyz is not None
            ]
        self.attitude = attitude
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        return None

    def __len__(self) -> int:
        return len(self._entries)

    def __aiter__(self) -> AsyncIterator[RgbdFrame]:
        return self._frames()

    def _load(self, entry: FrameEntry, seq: int, stamp_s: float) -> RgbdFrame:
        intr = self.intrinsics
        if intr is None:
            raise CameraError("file source: iterated before it was opened (use `async with`)")
        rgb = read_rgb(entry.rgb_path)
        depth = read_depth(entry.depth_path, self._scale_m)
        shape = (intr.height_px, intr.width_px)
        if rgb.shape[:2] != shape or depth.shape != shape:
            raise CameraError(
                f"file source: frame {entry.seq} is {rgb.shape[1]}x{rgb.shape[0]} colour, "
                f"{depth.shape[1]}x{depth.shape[0]} depth; intrinsics say {shape[1]}x{shape[0]}"
            )
        return RgbdFrame(rgb, depth, intr, stamp_s, seq, self._truth.get(entry.seq))

    async def _frames(self) -> AsyncIterator[RgbdFrame]:
        entries = self._entries
        if not entries:
            raise CameraError("file source: iterated before it was opened (use `async with`)")
        first, last = entries[0], entries[-1]
        period_s = (last.stamp_s - first.stamp_s) / (len(entries) - 1) if len(entries) > 1 else 1.0 / self.fps
        span_s = (
            last.stamp_s - first.stamp_s + (period_s if period_s > 0 and math.isfinite(period_s) else 0.0)
        )
        seq_span = last.seq - first.seq + 1
        lap = 0
        while True:
            for entry in entries:
                stamp_s = entry.stamp_s + lap * span_s
                frame = await asyncio.to_thread(self._load, entry, entry.seq + lap * seq_span, stamp_s)
                await self._pacer.wait(stamp_s)
                yield frame
            if not self.loop:
                return
            lap += 1
