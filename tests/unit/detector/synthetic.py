"""Tiny synthetic detection datasets for tests: quad-like shapes on sky/ground backgrounds, YOLO labels."""

from __future__ import annotations

import csv
from pathlib import Path

import cv2
import numpy as np

from companion.perception.detector.dataset import format_yolo_labels

FOCAL_PX = 457.0
SPAN_M = 0.45


def draw_quad(
    img: np.ndarray, cx: float, cy: float, span_px: float, rng: np.random.Generator
) -> tuple[float, ...]:
    """Draw a quad-X silhouette; returns its tight box (x0, y0, x1, y1)."""
    colour = tuple(int(c) for c in rng.integers(0, 90, 3))
    half = span_px / 2
    pts = []
    for ang in (45, 135, 225, 315):
        a = np.radians(ang + rng.uniform(-8, 8))
        x, y = cx + half * np.cos(a), cy + 0.45 * half * np.sin(a)
        cv2.line(img, (int(cx), int(cy)), (int(x), int(y)), colour, max(1, int(span_px / 25)))
        r = max(1, int(span_px / 7))
        cv2.ellipse(img, (int(x), int(y)), (r, max(1, r // 3)), 0, 0, 360, colour, -1)
        pts.append((x - r, y - r / 3, x + r, y + r / 3))
    bw, bh = max(1, int(span_px / 6)), max(1, int(span_px / 9))
    cv2.rectangle(img, (int(cx - bw), int(cy - bh)), (int(cx + bw), int(cy + bh)), colour, -1)
    p = np.asarray(pts)
    x0 = min(p[:, 0].min(), cx - bw)
    y0 = min(p[:, 1].min(), cy - bh)
    x1 = max(p[:, 2].max(), cx + bw)
    y1 = max(p[:, 3].max(), cy + bh)
    h, w = img.shape[:2]
    return (max(0.0, x0), max(0.0, y0), min(float(w), x1 + 1), min(float(h), y1 + 1))


def background(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    top = rng.integers(120, 230, 3)
    bottom = rng.integers(40, 160, 3)
    t = np.linspace(0, 1, h)[:, None, None]
    img = (top * (1 - t) + bottom * t).repeat(w, 1)
    horizon = int(rng.uniform(0.55, 0.9) * h)
    img[horizon:] = rng.integers(30, 120, 3)
    img += rng.normal(0, 4, img.shape)
    return np.clip(img, 0, 255).astype(np.uint8)


def make_dataset(
    root: Path,
    counts: dict[str, int],
    *,
    seed: int = 0,
    size: tuple[int, int] = (320, 240),
    empty_fraction: float = 0.15,
    range_m: tuple[float, float] = (2.0, 15.0),
) -> Path:
    """Write ``root/images/SPLIT/*.png``, ``root/labels/SPLIT/*.txt`` and ``root/manifest.csv`` (range_m)."""
    rng = np.random.default_rng(seed)
    w, h = size
    rows = []
    for split, n in counts.items():
        (root / "images" / split).mkdir(parents=True, exist_ok=True)
        (root / "labels" / split).mkdir(parents=True, exist_ok=True)
        for i in range(n):
            name = f"{split}_{i:05d}"
            img = background(h, w, rng)
            boxes = np.zeros((0, 4), np.float32)
            rng_m = None
            if rng.random() >= empty_fraction:
                rng_m = float(rng.uniform(*range_m))
                span = FOCAL_PX * (w / 640) * SPAN_M / rng_m * 1.6
                cx, cy = rng.uniform(0.1, 0.9) * w, rng.uniform(0.1, 0.8) * h
                boxes = np.asarray([draw_quad(img, cx, cy, span, rng)], np.float32)
            cv2.imwrite(str(root / "images" / split / f"{name}.png"), img[..., ::-1])
            (root / "labels" / split / f"{name}.txt").write_text(format_yolo_labels(boxes, w, h))
            rows.append(
                {"image": f"{name}.png", "split": split, "range_m": "" if rng_m is None else f"{rng_m:.3f}"}
            )
    with (root / "manifest.csv").open("w", newline="") as f:
        wr = csv.DictWriter(f, fieldnames=["image", "split", "range_m"])
        wr.writeheader()
        wr.writerows(rows)
    return root
