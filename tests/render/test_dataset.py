"""`sitl dataset` and `sitl contact-sheet` end to end: a real (small) rendered dataset on disk."""

from __future__ import annotations

import csv
import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

pytestmark = pytest.mark.render


def _run(repo: Path, *args: str) -> subprocess.CompletedProcess[str]:
    env = {**os.environ, "PYTHONPATH": str(repo)}
    return subprocess.run(
        [sys.executable, "-m", "sitl", *args],
        cwd=repo,
        env=env,
        capture_output=True,
        text=True,
        timeout=240,
        check=False,
    )


@pytest.fixture(scope="module")
def dataset(tmp_path_factory: pytest.TempPathFactory) -> Path:
    repo = Path(__file__).resolve().parents[2]
    out = tmp_path_factory.mktemp("ds")
    r = _run(repo, "dataset", "--out", str(out), "--count", "10", "--seq-len", "1", "--seed", "6")
    assert r.returncode == 0, r.stderr[-2000:]
    assert "wrote 10 frames" in r.stdout
    return out


def test_layout_and_labels(dataset: Path) -> None:
    rows = list(csv.DictReader((dataset / "manifest.csv").open()))
    assert len(rows) == 10
    for row in rows:
        img = cv2.imread(str(dataset / row["image"]))
        assert img is not None
        assert img.shape == (480, 640, 3)
        stem, split = Path(row["image"]).stem, row["split"]
        depth = cv2.imread(str(dataset / "depth" / split / f"{stem}.png"), cv2.IMREAD_UNCHANGED)
        assert depth is not None
        assert depth.dtype == np.uint16
        assert depth.shape == (480, 640)
        assert depth.max() <= 15_000  # mm: nothing whose true depth exceeds 10 m, plus noise
        lines = (dataset / "labels" / split / f"{stem}.txt").read_text().splitlines()
        assert len(lines) == int(row["labelled"])
        for line in lines:
            cls, *vals = line.split()
            assert cls == "0"
            cx, cy, w, h = map(float, vals)
            assert 0 < w <= 1
            assert 0 < h <= 1
            assert 0 <= cx <= 1
            assert 0 <= cy <= 1
        if row["labelled"] == "1":
            assert row["has_leader"] == "1"
            assert 0.9 <= float(row["range_m"]) <= 25.0


def test_splits_by_sequence_and_leader_free_frames(dataset: Path) -> None:
    rows = list(csv.DictReader((dataset / "manifest.csv").open()))
    split_of_seq: dict[str, set[str]] = {}
    for row in rows:
        split_of_seq.setdefault(row["sequence"], set()).add(row["split"])
    assert all(len(s) == 1 for s in split_of_seq.values())
    assert {s for ss in split_of_seq.values() for s in ss} == {"train", "val", "test"}
    unlabelled = sum(row["labelled"] == "0" for row in rows)
    assert unlabelled >= 1  # at least 10 % of frames show no (labellable) leader


def test_coco_matches_yolo(dataset: Path) -> None:
    rows = list(csv.DictReader((dataset / "manifest.csv").open()))
    n_boxes = 0
    for split in ("train", "val", "test"):
        coco = json.loads((dataset / "annotations" / f"instances_{split}.json").read_text())
        assert coco["categories"] == [{"id": 1, "name": "drone"}]
        names = {im["id"]: im["file_name"] for im in coco["images"]}
        for ann in coco["annotations"]:
            stem = Path(names[ann["image_id"]]).stem
            cx, _cy, w, _h = map(float, (dataset / "labels" / split / f"{stem}.txt").read_text().split()[1:])
            x, _y, bw, _bh = ann["bbox"]
            assert abs((x + bw / 2) / 640 - cx) < 1e-5
            assert abs(bw / 640 - w) < 1e-5
            n_boxes += 1
    assert n_boxes == sum(row["labelled"] == "1" for row in rows)


def test_contact_sheet(dataset: Path, tmp_path: Path) -> None:
    repo = Path(__file__).resolve().parents[2]
    out = tmp_path / "sheet.png"
    r = _run(repo, "contact-sheet", "--data", str(dataset), "--out", str(out), "--tile-px", "160")
    assert r.returncode == 0, r.stderr
    sheet = cv2.imread(str(out))
    assert sheet is not None
    assert sheet.shape == (3 * 120, 4 * 320, 3)  # 10 frames: rows of four colour + depth pairs


def test_contact_sheet_without_dataset_says_so(tmp_path: Path) -> None:
    repo = Path(__file__).resolve().parents[2]
    r = _run(repo, "contact-sheet", "--data", str(tmp_path), "--out", str(tmp_path / "x.png"))
    assert r.returncode == 2
    assert "manifest.csv" in r.stderr
