"""Detector datasets rendered by the simulated camera, and a contact sheet to look at them.

``sitl dataset --out DIR --count N --seed S [--seq-len L]`` renders N frames in sequences of L (default
6) with domain randomisation (see :mod:`sitl.render.randomize`) and writes::

    DIR/
      dataset.yaml                      YOLO data file: path, train/val/test image folders, names {0: drone}
      intrinsics.json                   fx_px, fy_px, cx_px, cy_px, width_px, height_px, depth_unit_m (0.001)
      manifest.csv                      one row per image (columns below)
      images/{train,val,test}/sSSSSSS_fFF.jpg     colour, JPEG (quality varies: part of the augmentation)
      labels/{train,val,test}/sSSSSSS_fFF.txt     YOLO: "0 cx cy w h", normalised; empty = no drone
      depth/{train,val,test}/sSSSSSS_fFF.png      uint16 depth in mm along the optical axis, 0 = invalid
      annotations/instances_{train,val,test}.json COCO detection json (file_name relative to DIR)

Splits are by sequence (``sSSSSSS``): the frames of one sequence are near-duplicates and always land in
the same split (about 80/10/10). ``manifest.csv`` columns: ``image`` (path relative to DIR), ``split``,
``sequence``, ``frame``, ``has_leader`` (1 if the leader is in the scene at all), ``labelled`` (1 if a box
was written: at least 12 visible pixels and a quarter of the leader visible), ``range_m`` (distance from
the camera to the leader's centre, empty without a leader: use it for recall by range bin),
``z_cam_m``, ``box_w_px``, ``box_h_px``, ``visible_fraction``, ``airframe``, ``span_m``,
``time_of_day``, ``cloud_cover``, ``fog_density_per_m``, ``distractors``. Boxes are tight around the
leader's visible pixels (rotor discs included), from the renderer's leader mask.

``sitl contact-sheet --data DIR --out PNG`` draws 16 random frames with their boxes beside their depth
in false colour (turbo, 0-10 m; black = invalid).
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray
from tqdm import tqdm

from companion.kernel.camera import Intrinsics
from sitl.render.config import CameraModel
from sitl.render.geometry import LeaderPose
from sitl.render.randomize import (
    SPLITS,
    Photometric,
    SequenceSpec,
    distractor_frame_vertices,
    sample_sequence,
)
from sitl.render.renderer import RenderedView, Renderer

U8 = NDArray[np.uint8]

#: A box is labelled when at least this many leader pixels and this fraction of the leader are visible.
MIN_VISIBLE_PX = 12.0
MIN_VISIBLE_FRACTION = 0.25

MANIFEST_COLUMNS = (
    "image",
    "split",
    "sequence",
    "frame",
    "has_leader",
    "labelled",
    "range_m",
    "z_cam_m",
    "box_w_px",
    "box_h_px",
    "visible_fraction",
    "airframe",
    "span_m",
    "time_of_day",
    "cloud_cover",
    "fog_density_per_m",
    "distractors",
)


def apply_photometric(rgb: U8, ph: Photometric) -> U8:
    """Gamma, saturation, defocus and resampling on a rendered RGB frame (JPEG comes at encoding)."""
    lut = np.clip(255.0 * (np.arange(256) / 255.0) ** ph.gamma + 0.5, 0, 255).astype(np.uint8)
    out = np.asarray(cv2.LUT(rgb, lut), dtype=np.uint8)
    if abs(ph.saturation - 1.0) > 1e-3:
        grey = cv2.cvtColor(out, cv2.COLOR_RGB2GRAY)[..., None].astype(np.float32)
        out = np.clip(grey + (out.astype(np.float32) - grey) * ph.saturation, 0, 255).astype(np.uint8)
    if ph.blur_sigma_px > 0:
        out = np.asarray(cv2.GaussianBlur(out, (0, 0), ph.blur_sigma_px), dtype=np.uint8)
    if ph.resample < 1.0:
        h, w = out.shape[:2]
        size = (max(1, round(w * ph.resample)), max(1, round(h * ph.resample)))
        small = cv2.resize(out, size, interpolation=cv2.INTER_AREA)
        out = np.asarray(cv2.resize(small, (w, h), interpolation=cv2.INTER_LINEAR), dtype=np.uint8)
    return out


def yolo_line(box: tuple[float, float, float, float], width_px: int, height_px: int) -> str:
    """A YOLO label line (class 0, normalised centre and size) for an edge-convention box."""
    x0, y0, x1, y1 = box
    cx, cy = (x0 + x1) / 2.0 / width_px, (y0 + y1) / 2.0 / height_px
    return f"0 {cx:.6f} {cy:.6f} {(x1 - x0) / width_px:.6f} {(y1 - y0) / height_px:.6f}\n"


@dataclass
class _Split:
    images: list[dict[str, Any]] = field(default_factory=list)
    annotations: list[dict[str, Any]] = field(default_factory=list)


class DatasetWriter:
    """Writes frames, labels, depth, the manifest and COCO files in the layout of the module docstring."""

    def __init__(self, out_dir: Path, intr: Intrinsics, seed: int) -> None:
        self.out_dir = out_dir
        self.intr = intr
        self.seed = seed
        for sub in ("images", "labels", "depth"):
            for split in SPLITS:
                (out_dir / sub / split).mkdir(parents=True, exist_ok=True)
        (out_dir / "annotations").mkdir(parents=True, exist_ok=True)
        self.splits = {s: _Split() for s in SPLITS}
        self.rows: list[dict[str, Any]] = []

    def add(self, spec: SequenceSpec, frame: dict[str, Any]) -> None:
        """Write one rendered frame of a sequence."""
        W, H = self.intr.width_px, self.intr.height_px
        view: RenderedView = frame["view"]
        i = frame["frame"]
        name = f"s{spec.index:06d}_f{i:02d}"
        ph = spec.photometric[i]
        rgb = apply_photometric(view.rgb, ph)
        img_rel = f"images/{spec.split}/{name}.jpg"
        bgr = cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR)
        cv2.imwrite(str(self.out_dir / img_rel), bgr, [cv2.IMWRITE_JPEG_QUALITY, ph.jpeg_quality])
        depth_mm = np.minimum(np.rint(view.depth_m * 1000.0), 65535).astype(np.uint16)
        cv2.imwrite(
            str(self.out_dir / f"depth/{spec.split}/{name}.png"), depth_mm, [cv2.IMWRITE_PNG_COMPRESSION, 1]
        )
        box = view.box_xyxy_px
        if box is not None and not (
            view.visible_px >= MIN_VISIBLE_PX and view.visible_fraction >= MIN_VISIBLE_FRACTION
        ):
            box = None
        split = self.splits[spec.split]
        image_id = len(self.rows) + 1
        split.images.append({"id": image_id, "file_name": img_rel, "width": W, "height": H})
        label = ""
        if box is not None:
            x0, y0, x1, y1 = box
            label = yolo_line(box, W, H)
            split.annotations.append(
                {
                    "id": len(split.annotations) + 1,
                    "image_id": image_id,
                    "category_id": 1,
                    "bbox": [x0, y0, x1 - x0, y1 - y0],
                    "area": (x1 - x0) * (y1 - y0),
                    "iscrowd": 0,
                    "range_m": frame.get("range_m"),
                    "visible_fraction": view.visible_fraction,
                }
            )
        (self.out_dir / f"labels/{spec.split}/{name}.txt").write_text(label)
        v = spec.visual
        self.rows.append(
            {
                "image": img_rel,
                "split": spec.split,
                "sequence": spec.index,
                "frame": i,
                "has_leader": int(spec.leaders is not None),
                "labelled": int(box is not None),
                "range_m": f"{frame['range_m']:.3f}" if "range_m" in frame else "",
                "z_cam_m": f"{frame['z_cam_m']:.3f}" if "z_cam_m" in frame else "",
                "box_w_px": f"{box[2] - box[0]:.0f}" if box else "",
                "box_h_px": f"{box[3] - box[1]:.0f}" if box else "",
                "visible_fraction": f"{view.visible_fraction:.3f}",
                "airframe": v.leader.airframe,
                "span_m": f"{v.leader.resolved_span_m:.3f}",
                "time_of_day": v.time_of_day,
                "cloud_cover": f"{v.cloud_cover:.2f}",
                "fog_density_per_m": f"{v.fog_density_per_m:.4f}",
                "distractors": len(spec.distractors),
            }
        )

    def close(self) -> dict[str, int]:
        """Write the manifest, COCO files, intrinsics and YOLO data file; frames per split."""
        with (self.out_dir / "manifest.csv").open("w", newline="") as f:
            w = csv.DictWriter(f, fieldnames=MANIFEST_COLUMNS)
            w.writeheader()
            w.writerows(self.rows)
        for name, sp in self.splits.items():
            coco = {
                "info": {"description": f"Wingman rendered drones, seed {self.seed}, split {name}"},
                "images": sp.images,
                "annotations": sp.annotations,
                "categories": [{"id": 1, "name": "drone"}],
            }
            (self.out_dir / f"annotations/instances_{name}.json").write_text(json.dumps(coco))
        intr = self.intr
        intrinsics = {
            "fx_px": intr.fx_px,
            "fy_px": intr.fy_px,
            "cx_px": intr.cx_px,
            "cy_px": intr.cy_px,
            "width_px": intr.width_px,
            "height_px": intr.height_px,
            "depth_unit_m": 0.001,
        }
        (self.out_dir / "intrinsics.json").write_text(json.dumps(intrinsics, indent=2))
        (self.out_dir / "dataset.yaml").write_text(
            f"path: {self.out_dir.resolve()}\ntrain: images/train\nval: images/val\ntest: images/test\n"
            "names:\n  0: drone\n"
        )
        return {name: len(sp.images) for name, sp in self.splits.items()}


def _render_sequence(renderer: Renderer, spec: SequenceSpec) -> list[dict[str, Any]]:
    """Render a sequence; per frame the view and the truth numbers the manifest wants."""
    renderer.set_visual(spec.visual)
    out: list[dict[str, Any]] = []
    for i, (cam, t) in enumerate(zip(spec.cameras, spec.times_s, strict=True)):
        leader = None if spec.leaders is None else LeaderPose(*spec.leaders[i])
        extra = distractor_frame_vertices(spec.distractors, t)
        if i == 0:  # let auto exposure settle on this scene before keeping frames
            renderer.render_view(cam, leader, t, extra_vertices=extra, truth=False)
        omega = spec.omegas_cam_rad_s[i]
        view = renderer.render_view(cam, leader, t, omega_cam_rad_s=omega, extra_vertices=extra)
        row: dict[str, Any] = {"view": view, "frame": i}
        if leader is not None:
            p_cam = cam.to_cam(leader.p_ned_m)
            row["range_m"] = float(np.linalg.norm(p_cam))
            row["z_cam_m"] = float(p_cam[2])
        out.append(row)
    return out


def generate(
    out_dir: Path,
    count: int,
    seed: int,
    *,
    seq_len: int = 6,
    camera: CameraModel | None = None,
    profile: str = "wide",
) -> dict[str, int]:
    """Render ``count`` frames into ``out_dir`` (layout in the module docstring); frames per split.

    ``profile`` picks the view distribution (:data:`sitl.render.randomize.PROFILES`).
    """
    camera = camera or CameraModel()
    intr = camera.intrinsics
    writer = DatasetWriter(out_dir, intr, seed)
    n_seq = math.ceil(count / seq_len)
    with (
        Renderer(camera, supersample=2, seed=seed) as renderer,
        tqdm(total=count, unit="frame", desc="sitl dataset") as bar,
    ):
        for s in range(n_seq):
            spec = sample_sequence(seed, s, min(seq_len, count - s * seq_len), intr, profile)
            for frame in _render_sequence(renderer, spec):
                writer.add(spec, frame)
                bar.update(1)
    return writer.close()


def merge(out_dir: Path, sources: list[Path]) -> dict[str, int]:
    """Join ``sitl dataset`` folders into ``out_dir`` by symbolic links (nothing is copied).

    Each source's files get its folder name as a prefix (``render_s1__s000001_f00.jpg``) so names never
    collide, splits stay as each source made them (by sequence), and the manifests are concatenated with
    the image paths rewritten. Returns images per split.
    """
    if not sources:
        raise ValueError("dataset-merge: give at least one source folder")
    names = [src.resolve().name for src in sources]
    if len(set(names)) != len(names):
        raise ValueError(f"dataset-merge: source folder names must differ (got {', '.join(names)})")
    rows: list[dict[str, Any]] = []
    counts = dict.fromkeys(SPLITS, 0)
    for src, prefix in zip(sources, names, strict=True):
        manifest = src / "manifest.csv"
        if not manifest.is_file():
            raise ValueError(f"dataset-merge: {src} has no manifest.csv (not a `sitl dataset` folder)")
        with manifest.open(newline="") as f:
            src_rows = list(csv.DictReader(f))
        for row in src_rows:
            rel = Path(row["image"])  # images/SPLIT/NAME.jpg
            split, stem = rel.parts[1], rel.stem
            links = {
                rel: Path("images") / split / f"{prefix}__{rel.name}",
                Path("labels") / split / f"{stem}.txt": Path("labels") / split / f"{prefix}__{stem}.txt",
                Path("depth") / split / f"{stem}.png": Path("depth") / split / f"{prefix}__{stem}.png",
            }
            for src_rel, dst_rel in links.items():
                target = (src / src_rel).resolve()
                if not target.exists():
                    continue
                dst = out_dir / dst_rel
                dst.parent.mkdir(parents=True, exist_ok=True)
                if dst.is_symlink() or dst.exists():
                    dst.unlink()
                dst.symlink_to(target)
            rows.append({**row, "image": str(links[rel])})
            counts[split] = counts.get(split, 0) + 1
    with (out_dir / "manifest.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=MANIFEST_COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    (out_dir / "intrinsics.json").write_text((sources[0] / "intrinsics.json").read_text())
    (out_dir / "dataset.yaml").write_text(
        f"path: {out_dir.resolve()}\ntrain: images/train\nval: images/val\ntest: images/test\n"
        "names:\n  0: drone\n"
    )
    (out_dir / "sources.txt").write_text("".join(f"{src.resolve()}\n" for src in sources))
    return counts


def depth_false_colour(depth_mm: NDArray[np.uint16], max_m: float = 10.0) -> U8:
    """Turbo false colour of a depth image (BGR), invalid pixels black."""
    scaled = np.clip(depth_mm.astype(np.float32) * (255.0 / (max_m * 1000.0)), 0, 255).astype(np.uint8)
    out: U8 = cv2.applyColorMap(scaled, cv2.COLORMAP_TURBO)
    out[depth_mm == 0] = 0
    return out


def contact_sheet(data_dir: Path, out_png: Path, seed: int = 0, n: int = 16, tile_px: int = 320) -> Path:
    """A PNG grid of n random frames: boxes drawn on colour, depth in false colour beside each."""
    with (data_dir / "manifest.csv").open() as f:
        rows = list(csv.DictReader(f))
    if not rows:
        raise ValueError(f"{data_dir}: manifest.csv has no rows")
    rng = np.random.default_rng(seed)
    pick = rng.choice(len(rows), size=min(n, len(rows)), replace=False)
    tiles: list[U8] = []
    for i in pick:
        row = rows[int(i)]
        stem = Path(row["image"]).stem
        bgr = cv2.imread(str(data_dir / row["image"]))
        depth = cv2.imread(str(data_dir / "depth" / row["split"] / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        if bgr is None or depth is None:
            raise ValueError(f"{data_dir}: cannot read {row['image']} or its depth")
        h, w = bgr.shape[:2]
        for line in (data_dir / "labels" / row["split"] / f"{stem}.txt").read_text().splitlines():
            _, cx, cy, bw, bh = (float(x) for x in line.split())
            x0, y0 = round((cx - bw / 2) * w), round((cy - bh / 2) * h)
            x1, y1 = round((cx + bw / 2) * w), round((cy + bh / 2) * h)
            cv2.rectangle(bgr, (x0 - 1, y0 - 1), (x1, y1), (0, 255, 0), 1)
        who = row["airframe"] if row["has_leader"] == "1" else "no leader"
        text = f"{row['split']} {row['range_m'] or '-'} m {who}"
        pair = np.hstack([bgr, depth_false_colour(np.asarray(depth, dtype=np.uint16))])
        scale = tile_px / w
        pair = cv2.resize(pair, (round(2 * w * scale), round(h * scale)), interpolation=cv2.INTER_AREA)
        for colour, thick in (((0, 0, 0), 3), ((255, 255, 255), 1)):
            cv2.putText(pair, text, (4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4, colour, thick, cv2.LINE_AA)
        tiles.append(np.asarray(pair, dtype=np.uint8))
    while len(tiles) % 4:
        tiles.append(np.zeros_like(tiles[0]))
    grid = (
        np.vstack([np.hstack(tiles[r : r + 4]) for r in range(0, len(tiles), 4)])
        if len(tiles) >= 4
        else np.hstack(tiles)
    )
    out_png.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(out_png), grid, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    return out_png


def main_dataset(args: argparse.Namespace) -> int:
    """``sitl dataset``."""
    if args.count <= 0:
        print("sitl dataset: --count must be positive", file=sys.stderr)
        return 2
    counts = generate(
        args.out,
        args.count,
        args.seed,
        seq_len=getattr(args, "seq_len", 6),
        profile=getattr(args, "profile", "wide"),
    )
    per_split = ", ".join(f"{k} {v}" for k, v in counts.items())
    print(f"sitl dataset: wrote {sum(counts.values())} frames to {args.out} ({per_split})")
    return 0


def main_merge(args: argparse.Namespace) -> int:
    """``sitl dataset-merge``."""
    try:
        counts = merge(args.out, list(args.sources))
    except ValueError as exc:
        print(f"sitl {exc}", file=sys.stderr)
        return 2
    per_split = ", ".join(f"{k} {v}" for k, v in counts.items())
    print(f"sitl dataset-merge: linked {sum(counts.values())} frames into {args.out} ({per_split})")
    return 0


def main_contact_sheet(args: argparse.Namespace) -> int:
    """``sitl contact-sheet``."""
    if not (args.data / "manifest.csv").is_file():
        print(
            f"sitl contact-sheet: {args.data} has no manifest.csv (make one with `sitl dataset`)",
            file=sys.stderr,
        )
        return 2
    path = contact_sheet(args.data, args.out, args.seed, tile_px=getattr(args, "tile_px", 320))
    print(f"sitl contact-sheet: wrote {path}")
    return 0
