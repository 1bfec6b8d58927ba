"""Detection datasets on disk: a folder of images with YOLO labels, optional splits and per-image ranges.

Layouts understood (``split`` None means "all images"):

* ``DIR/images/*`` + ``DIR/labels/*.txt`` (e.g. the real-photo validation set);
* ``DIR/images/SPLIT/*`` + ``DIR/labels/SPLIT/*.txt`` (the usual YOLO layout);
* ``DIR/SPLIT/images/*`` + ``DIR/SPLIT/labels/*.txt``;
* ``DIR/SPLIT.txt`` listing image paths (relative to DIR), labels found by swapping ``images`` for ``labels``.

A label file holds ``class cx cy w h`` lines normalised to the image size; class 0 is the leader (other
classes are ignored). A missing or empty label file means no leader box. Per-image facts come from a
``manifest.csv`` or ``manifest.jsonl`` in DIR when it has an ``image``/``file`` column: ``range_m`` (leader
range, for recall by range bin), ``has_leader`` and ``visible_fraction``: a frame shows the leader when it
is in the scene with some of it visible. A frame can show a little of the leader and still have no box
(too few pixels to label); such a frame is not "leader-free" when false positives are counted. The
manifest's other text columns (e.g. ``distance_bin``, ``drone_type``, ``video``) are kept per image as
:attr:`Sample.attrs`, for evaluation by column and for holding out whole videos.
"""

from __future__ import annotations

import csv
import json
import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".webp")
LEADER_CLASS = 0

Boxes = NDArray[np.float32]  # (N, 4) x0 y0 x1 y1, px


@dataclass(frozen=True, slots=True)
class Sample:
    """One image of a dataset and its label file (None: no file).

    When the manifest says so: the leader's range (m) and whether any of the leader is visible.
    """

    image_path: Path
    label_path: Path | None
    range_m: float | None = None
    leader_visible: bool | None = None
    #: Text columns of the manifest row, (column, value) pairs.
    attrs: tuple[tuple[str, str], ...] = ()

    @property
    def key(self) -> str:
        return self.image_path.stem

    def attr(self, column: str) -> str | None:
        """The manifest's value of ``column`` for this image (None: no such column or no manifest row)."""
        for k, v in self.attrs:
            if k == column:
                return v
        return None

    @property
    def group(self) -> str:
        """The recording an image comes from.

        The manifest's ``video``/``sequence`` column, else the name without a trailing ``_f<frame>``.
        """
        for column in ("video", "sequence", "seq"):
            v = self.attr(column)
            if v:
                return v
        stem = self.key
        head, sep, tail = stem.rpartition("_")
        if sep and tail.lstrip("f").isdigit():
            return head
        return stem


def _images_in(folder: Path) -> list[Path]:
    return (
        sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES) if folder.is_dir() else []
    )


def _label_for(image: Path, images_dir: Path, labels_dir: Path) -> Path | None:
    label = labels_dir / image.relative_to(images_dir).with_suffix(".txt")
    return label if label.exists() else None


def _swap_images_for_labels(image: Path) -> Path | None:
    parts = list(image.parts)
    for i in range(len(parts) - 1, -1, -1):
        if parts[i] == "images":
            parts[i] = "labels"
            label = Path(*parts).with_suffix(".txt")
            return label if label.exists() else None
    return None


def list_splits(root: Path) -> list[str]:
    """Split names a dataset folder offers (e.g. ``["test", "train", "val"]``); empty for a flat folder."""
    names = set()
    if (root / "images").is_dir():
        names |= {p.name for p in (root / "images").iterdir() if p.is_dir()}
    names |= {p.name for p in root.iterdir() if p.is_dir() and (p / "images").is_dir()}
    names |= {p.stem for p in root.glob("*.txt") if p.stem in ("train", "val", "test")}
    return sorted(names)


def find_samples(root: Path, split: str | None = None) -> list[Sample]:
    """The samples of ``split`` in ``root`` (any layout of the module docstring); raises if there are none."""
    if not root.is_dir():
        raise FileNotFoundError(f"dataset folder not found: {root}")
    pairs: list[tuple[Path, Path | None]] = []
    if split is None:
        imgs = _images_in(root / "images")
        pairs = [(p, _label_for(p, root / "images", root / "labels")) for p in imgs]
    else:
        for images_dir, labels_dir in (
            (root / "images" / split, root / "labels" / split),
            (root / split / "images", root / split / "labels"),
        ):
            imgs = _images_in(images_dir)
            if imgs:
                pairs = [(p, _label_for(p, images_dir, labels_dir)) for p in imgs]
                break
        else:
            listing = root / f"{split}.txt"
            if listing.exists():
                for line in listing.read_text().splitlines():
                    if line.strip():
                        p = (root / line.strip()).resolve()
                        pairs.append((p, _swap_images_for_labels(p)))
    if not pairs:
        where = f"split '{split}' of " if split else ""
        raise FileNotFoundError(
            f"no images found in {where}{root} (see companion.perception.detector.dataset)"
        )
    facts = read_manifest(root)
    columns = read_manifest_columns(root)
    return [
        Sample(img, lab, *facts.get(img.stem, (None, None)), columns.get(img.stem, ())) for img, lab in pairs
    ]


def _number(v: object) -> float | None:
    try:
        x = float(str(v))
    except ValueError:
        return None
    return x if math.isfinite(x) else None


def _manifest_rows(root: Path) -> list[dict[str, object]]:
    if (root / "manifest.csv").exists():
        with (root / "manifest.csv").open(newline="") as f:
            return list(csv.DictReader(f))
    if (root / "manifest.jsonl").exists():
        return [
            json.loads(line) for line in (root / "manifest.jsonl").read_text().splitlines() if line.strip()
        ]
    return []


#: Manifest columns never kept as text attributes (numbers, names and per-box lists).
_NOT_ATTRS = frozenset({"image", "file", "file_name", "frame", "width", "height", "n_boxes", "box_wxh_px"})


def read_manifest_columns(root: Path) -> dict[str, tuple[tuple[str, str], ...]]:
    """Image stem -> the manifest row's text columns (values that are not numbers), as (column, value)."""
    out: dict[str, tuple[tuple[str, str], ...]] = {}
    for row in _manifest_rows(root):
        name = row.get("image") or row.get("file") or row.get("file_name")
        if name is None:
            continue
        attrs = tuple(
            (str(k), str(v))
            for k, v in row.items()
            if k not in _NOT_ATTRS and isinstance(v, str) and v != "" and _number(v) is None
        )
        out[Path(str(name)).stem] = attrs
    return out


def read_manifest(root: Path) -> dict[str, tuple[float | None, bool | None]]:
    """Image stem -> (leader range m, leader visible) from ``manifest.csv``/``.jsonl`` in ``root``."""
    out: dict[str, tuple[float | None, bool | None]] = {}
    rows: Iterable[dict[str, object]] = _manifest_rows(root)
    for row in rows:
        name = row.get("image") or row.get("file") or row.get("file_name")
        if name is None:
            continue
        rng = row.get("range_m")
        has, vis = row.get("has_leader"), row.get("visible_fraction")
        visible = None if has in (None, "") else bool(_number(has))
        if visible and vis not in (None, ""):
            visible = (_number(vis) or 0.0) > 0.0
        out[Path(str(name)).stem] = (None if rng in (None, "") else _number(rng), visible)
    return out


def parse_yolo_labels(text: str, w_px: int, h_px: int) -> Boxes:
    """Leader boxes (N, 4) in pixels from the text of a YOLO label file."""
    boxes = []
    for line in text.splitlines():
        parts = line.split()
        if len(parts) < 5 or int(float(parts[0])) != LEADER_CLASS:
            continue
        cx, cy, bw, bh = (float(v) for v in parts[1:5])
        boxes.append(((cx - bw / 2) * w_px, (cy - bh / 2) * h_px, (cx + bw / 2) * w_px, (cy + bh / 2) * h_px))
    return np.asarray(boxes, np.float32).reshape(-1, 4)


def format_yolo_labels(boxes: Boxes, w_px: int, h_px: int) -> str:
    """The text of a YOLO label file for leader boxes in pixels."""
    lines = []
    for x0, y0, x1, y1 in np.asarray(boxes, np.float64).reshape(-1, 4):
        lines.append(
            f"{LEADER_CLASS} {(x0 + x1) / 2 / w_px:.6f} {(y0 + y1) / 2 / h_px:.6f} "
            f"{(x1 - x0) / w_px:.6f} {(y1 - y0) / h_px:.6f}"
        )
    return "".join(f"{line}\n" for line in lines)


def read_labels(sample: Sample, w_px: int, h_px: int) -> Boxes:
    """Leader boxes of a sample in pixels (none when it has no label file)."""
    if sample.label_path is None:
        return np.zeros((0, 4), np.float32)
    return parse_yolo_labels(sample.label_path.read_text(), w_px, h_px)


def read_rgb(path: Path) -> NDArray[np.uint8]:
    """Decode an image file to HxWx3 uint8 RGB."""
    import cv2  # noqa: PLC0415  (cv2 stays off the CLI's import path)

    bgr = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if bgr is None:
        raise OSError(f"cannot decode image {path}")
    return np.ascontiguousarray(bgr[..., ::-1])


def split_keys(samples: Sequence[Sample]) -> set[str]:
    """Image stems of a list of samples."""
    return {s.key for s in samples}
