"""A decoded-image cache for training: every image once, shrunk, in one memory-mapped file.

Decoding thousands of PNGs every epoch would cost more CPU than the augmentations; the cache decodes each
image once, shrinks it so its longer side is at most ``max_side_px`` (area interpolation, as at run time) and
keeps it in ``images.u8`` with an index (offsets, shapes, boxes in cached pixels). The cache folder's name is
a hash of the file list, sizes, modification times and ``max_side_px``, so a changed dataset gets a new one.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from companion.perception.detector.dataset import Boxes, Sample, read_labels, read_rgb
from companion.perception.detector.letterbox import resize_image


def cache_key(samples: Sequence[Sample], max_side_px: int) -> str:
    """Hash of what the cache depends on."""
    h = hashlib.sha1(usedforsecurity=False)
    h.update(f"v1 {max_side_px}\n".encode())
    for s in samples:
        st = s.image_path.stat()
        lab = s.label_path.stat().st_mtime_ns if s.label_path else 0
        h.update(f"{s.image_path}|{st.st_size}|{st.st_mtime_ns}|{lab}\n".encode())
    return h.hexdigest()[:16]


class ImageCache:
    """Images and leader boxes of a list of samples, decoded once (see module docstring)."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        index = np.load(folder / "index.npz")
        self.offsets: NDArray[np.int64] = index["offsets"]
        self.shapes: NDArray[np.int32] = index["shapes"]
        self.box_offsets: NDArray[np.int64] = index["box_offsets"]
        self.all_boxes: NDArray[np.float32] = index["boxes"]
        self.data = np.memmap(folder / "images.u8", dtype=np.uint8, mode="r")
        self.keys: list[str] = json.loads((folder / "keys.json").read_text())
        #: Indices of the images with at least one box (copy-paste donors).
        self.labelled: NDArray[np.int64] = np.flatnonzero(np.diff(self.box_offsets) > 0)

    def __len__(self) -> int:
        return len(self.shapes)

    def __getstate__(self) -> dict[str, str]:
        # Pickled (to a spawned loader worker) as its folder, and re-opened there: never the pixels.
        return {"folder": str(self.folder)}

    def __setstate__(self, state: dict[str, str]) -> None:
        self.__init__(Path(state["folder"]))  # type: ignore[misc]

    def image(self, i: int) -> NDArray[np.uint8]:
        """Cached image ``i`` (h, w, 3) RGB, a read-only view."""
        h, w = (int(v) for v in self.shapes[i])
        start = int(self.offsets[i])
        return self.data[start : start + h * w * 3].reshape(h, w, 3)

    def boxes(self, i: int) -> Boxes:
        """Leader boxes of image ``i`` in cached pixels (a copy)."""
        return self.all_boxes[self.box_offsets[i] : self.box_offsets[i + 1]].copy()

    @classmethod
    def build(
        cls, samples: Sequence[Sample], root: Path, max_side_px: int, progress: bool = True
    ) -> ImageCache:
        """Open the cache for ``samples`` under ``root``, building it first when it does not exist yet."""
        folder = root / cache_key(samples, max_side_px)
        if (folder / "index.npz").exists():
            return cls(folder)
        folder.mkdir(parents=True, exist_ok=True)
        offsets, shapes, box_offsets, boxes = [], [], [0], []
        pos = 0
        iterator: Sequence[Sample] = samples
        if progress:
            from tqdm import tqdm  # noqa: PLC0415

            iterator = tqdm(samples, desc="caching images", unit="img", leave=False)
        with (folder / "images.tmp").open("wb") as f:
            for s in iterator:
                rgb = read_rgb(s.image_path)
                h, w = rgb.shape[:2]
                b = read_labels(s, w, h)
                scale = min(1.0, max_side_px / max(h, w))
                if scale < 1.0:
                    nw, nh = max(1, round(w * scale)), max(1, round(h * scale))
                    rgb = resize_image(rgb, nw, nh)
                    b = b * np.array([nw / w, nh / h, nw / w, nh / h], np.float32)
                f.write(np.ascontiguousarray(rgb).tobytes())
                offsets.append(pos)
                shapes.append(rgb.shape[:2])
                pos += rgb.size
                boxes.append(b)
                box_offsets.append(box_offsets[-1] + len(b))
        (folder / "images.tmp").rename(folder / "images.u8")
        (folder / "keys.json").write_text(json.dumps([s.key for s in samples]))
        np.savez(
            folder / "index.npz",
            offsets=np.asarray(offsets, np.int64),
            shapes=np.asarray(shapes, np.int32).reshape(-1, 2),
            box_offsets=np.asarray(box_offsets, np.int64),
            boxes=np.concatenate(boxes).astype(np.float32) if boxes else np.zeros((0, 4), np.float32),
        )
        return cls(folder)
