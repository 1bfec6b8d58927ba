"""Training data mined from real footage: hard negatives and drone-free background frames.

``python -m companion.lab.training.mine --data DIR --model MODEL.onnx --hard OUT [--background OUT]``

* **Hard negatives** (``--hard``): the frames of the training videos where the current detector fires
  away from every label (a bird, an aircraft, a cloud edge; at ``--conf``, below the service's threshold,
  so near misses count too). The output folder holds a ``train.txt`` listing those images by their path in
  ``--data`` (nothing is copied), so it trains as a source of its own with a larger share of each batch.
* **Background frames** (``--background``): for every frame with drones, the largest strip of the frame
  (left, right, above or below) that keeps a margin of a box size around every label, at its own place and
  scale in a frame of the original size, the rest grey (the letterbox's fill): more real drone-free frames
  from the same cameras, skies and tree lines.

Videos that training holds out for validation (the same rule and fraction as
:func:`companion.lab.training.train_data.source_splits`) give nothing, so validation stays unseen.
"""

from __future__ import annotations

import argparse
import csv
import os
import sys
from collections.abc import Sequence
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from companion.lab.training.train_data import held_out
from companion.perception.detector.dataset import Sample, find_samples, read_labels, read_rgb
from companion.perception.detector.letterbox import PAD_VALUE
from companion.perception.detector.postprocess import box_iou
from companion.perception.detector.runtime import FrameDetector

#: A detection overlapping a label by less than this IoU, with its centre outside the label grown by
#: :data:`LABEL_GROWTH`, fires away from every label (loose real labels: a found drone's box can miss
#: IoU 0.5 with its label).
AWAY_IOU = 0.1
LABEL_GROWTH = 1.5
#: Smallest background strip kept, as a share of the frame's area.
MIN_STRIP_FRACTION = 0.3


def false_alarms(
    boxes: NDArray[np.float32], scores: NDArray[np.float32], labels: NDArray[np.float32]
) -> NDArray[np.float32]:
    """Scores of the detections that lie away from every label (see :data:`AWAY_IOU`)."""
    if len(boxes) == 0 or len(labels) == 0:
        return scores
    near = box_iou(boxes, labels).max(1) >= AWAY_IOU
    c = (boxes[:, :2] + boxes[:, 2:]) / 2
    lc, half = (labels[:, :2] + labels[:, 2:]) / 2, (labels[:, 2:] - labels[:, :2]) * (LABEL_GROWTH / 2)
    inside = np.any(np.all(np.abs(c[:, None, :] - lc[None]) <= half[None], axis=-1), axis=1)
    away: NDArray[np.float32] = scores[~(near | inside)]
    return away


def background_strip(labels: NDArray[np.float32], w_px: int, h_px: int) -> tuple[int, int, int, int] | None:
    """The largest left/right/top/bottom strip (x0, y0, x1, y1) clear of every label by a box size."""
    size = np.maximum(labels[:, 2:] - labels[:, :2], 16.0)
    x0 = float((labels[:, 0] - size[:, 0]).min())
    y0 = float((labels[:, 1] - size[:, 1]).min())
    x1 = float((labels[:, 2] + size[:, 0]).max())
    y1 = float((labels[:, 3] + size[:, 1]).max())
    strips = [
        (0, 0, int(np.floor(x0)), h_px),
        (int(np.ceil(x1)), 0, w_px, h_px),
        (0, 0, w_px, int(np.floor(y0))),
        (0, int(np.ceil(y1)), w_px, h_px),
    ]
    best = max(strips, key=lambda s: max(0, s[2] - s[0]) * max(0, s[3] - s[1]))
    area = max(0, best[2] - best[0]) * max(0, best[3] - best[1])
    return best if area >= MIN_STRIP_FRACTION * w_px * h_px else None


def training_samples(root: Path, holdout_fraction: float) -> list[Sample]:
    """The samples of a flat real-footage folder that training trains on (held-out videos left out)."""
    return [s for s in find_samples(root, None) if not held_out(s.group, holdout_fraction)]


def mine_hard(
    detector: FrameDetector, samples: Sequence[Sample], out: Path, conf: float, progress: bool = True
) -> int:
    """Write ``out/train.txt`` (and ``out/mined.csv``: image, video, best false score); returns frames."""
    out.mkdir(parents=True, exist_ok=True)
    rows: list[tuple[Path, str, float]] = []
    iterator: Sequence[Sample] = samples
    if progress:
        from tqdm import tqdm  # noqa: PLC0415

        iterator = tqdm(samples, desc="mining", unit="img", leave=False)
    for s in iterator:
        rgb = read_rgb(s.image_path)
        boxes, scores = detector.raw(rgb, conf)
        away = false_alarms(boxes, scores, read_labels(s, rgb.shape[1], rgb.shape[0]))
        if len(away):
            rows.append((s.image_path, s.group, float(away.max())))
    lines = [os.path.relpath(p.resolve(), out.resolve()) for p, _, _ in rows]
    (out / "train.txt").write_text("".join(f"{line}\n" for line in lines))
    with (out / "mined.csv").open("w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["image", "video", "false_alarm_score"])
        w.writerows((p.stem, v, f"{sc:.3f}") for p, v, sc in rows)
    return len(rows)


def write_backgrounds(samples: Sequence[Sample], out: Path, every: int = 1) -> int:
    """Write a background frame (see the module docstring) per ``every``-th drone frame; returns frames."""
    import cv2  # noqa: PLC0415

    (out / "images").mkdir(parents=True, exist_ok=True)
    (out / "labels").mkdir(parents=True, exist_ok=True)
    rows = []
    drone_frames = [s for s in samples if s.label_path is not None and s.label_path.stat().st_size > 0]
    for s in drone_frames[:: max(1, every)]:
        rgb = read_rgb(s.image_path)
        h, w = rgb.shape[:2]
        labels = read_labels(s, w, h)
        strip = background_strip(labels, w, h) if len(labels) else None
        if strip is None:
            continue
        x0, y0, x1, y1 = strip
        frame = np.full_like(rgb, PAD_VALUE)
        frame[y0:y1, x0:x1] = rgb[y0:y1, x0:x1]
        name = f"{s.key}_bg"
        cv2.imwrite(str(out / "images" / f"{name}.jpg"), frame[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 95])
        (out / "labels" / f"{name}.txt").write_text("")
        rows.append((name, s.group, s.attr("drone_type") or ""))
    with (out / "manifest.csv").open("w", newline="") as f:
        wr = csv.writer(f)
        wr.writerow(["image", "video", "drone_type", "n_boxes"])
        wr.writerows((name, video, kind, 0) for name, video, kind in rows)
    return len(rows)


def main(argv: list[str] | None = None) -> int:
    """Command line: see the module docstring."""
    ap = argparse.ArgumentParser(prog="python -m companion.lab.training.mine", description=__doc__)
    ap.add_argument("--data", type=Path, required=True, help="flat real-footage folder (images/, labels/)")
    ap.add_argument("--model", type=Path, default=None, help="detector (.onnx or .pt) for --hard")
    ap.add_argument("--hard", type=Path, default=None, help="hard-negative source folder to write")
    ap.add_argument("--background", type=Path, default=None, help="background-frame folder to write")
    ap.add_argument("--conf", type=float, default=0.2, help="score of a false alarm worth training on")
    ap.add_argument("--input-size", type=int, default=416, help="detector input, px")
    ap.add_argument("--holdout", type=float, default=0.1, help="training's held-out share of the videos")
    ap.add_argument("--every", type=int, default=1, help="background: every N-th drone frame")
    args = ap.parse_args(argv)
    samples = training_samples(args.data, args.holdout)
    if args.hard is not None:
        if args.model is None:
            ap.error("--hard needs --model")
        detector = _detector(args.model, args.input_size)
        n = mine_hard(detector, samples, args.hard, args.conf, progress=sys.stderr.isatty())
        print(f"{args.hard}: {n} of {len(samples)} training frames with a false alarm >= {args.conf:g}")
    if args.background is not None:
        n = write_backgrounds(samples, args.background, args.every)
        print(f"{args.background}: {n} background frames")
    return 0


def _detector(model: Path, input_size_px: int) -> FrameDetector:
    """The model as the service runs it (threshold and NMS of the default config), without its checksum."""
    from companion.config import DetectorConfig  # noqa: PLC0415

    cfg = DetectorConfig()
    if model.suffix == ".onnx":
        from companion.perception.detector.runtime import OnnxEngine  # noqa: PLC0415

        engine: object = OnnxEngine(model, cfg.threads)
    else:
        from companion.perception.detector.torch_engine import TorchEngine  # noqa: PLC0415

        engine = TorchEngine(model, cfg.threads)
    return FrameDetector(engine, input_size_px, cfg.conf_threshold, cfg.nms_iou)  # type: ignore[arg-type]


if __name__ == "__main__":
    raise SystemExit(main())
