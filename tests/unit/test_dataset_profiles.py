"""Dataset view profiles (pure numpy samplers) and ``sitl dataset-merge`` (file links only, no rendering)."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest

from companion.perception.detector.dataset import find_samples
from sitl.render.config import CameraModel
from sitl.render.dataset import MANIFEST_COLUMNS, merge
from sitl.render.randomize import sample_sequence

INTR = CameraModel().intrinsics


def _pitch_deg(R_ned_cam: np.ndarray) -> float:
    """Elevation of the optical axis (camera z) above the horizon, deg."""
    z = R_ned_cam[:, 2]
    return math.degrees(math.asin(-float(z[2])))


def test_formation_profile_is_the_followers_view() -> None:
    ranges, pitches, centred = [], [], 0
    n_leader = 0
    for i in range(120):
        spec = sample_sequence(3, i, 1, INTR, profile="formation")
        cam = spec.cameras[0]
        pitches.append(_pitch_deg(cam.R_ned_cam))
        if spec.leaders is None:
            continue
        n_leader += 1
        p_cam = cam.to_cam(spec.leaders[0][1])
        ranges.append(float(np.linalg.norm(p_cam)))
        u = INTR.fx_px * p_cam[0] / p_cam[2] + INTR.cx_px
        centred += int(p_cam[2] > 0 and 0.15 * INTR.width_px < u < 0.85 * INTR.width_px)
    assert n_leader > 90  # about 14 % of sequences stay leader-free (false-positive training)
    assert min(ranges) >= 2.0 - 1e-6
    assert max(ranges) <= 15.0 + 1e-6
    assert max(abs(p) for p in pitches) <= 25.0  # mount tilt + attitude, with roll folded in
    assert centred >= 0.85 * n_leader


def test_clutter_profile_puts_a_structure_behind_the_leader() -> None:
    """Most clutter sequences stand a tree or building farther along the line of sight than the leader,
    its crown or facade spanning the leader's height where that line meets it."""
    n_leader = n_behind = 0
    for i in range(120):
        spec = sample_sequence(5, i, 1, INTR, profile="clutter")
        if spec.leaders is None:
            continue
        n_leader += 1
        cam = spec.cameras[0].p_ned_cam_m
        los = spec.leaders[0][1] - cam
        for occ in spec.visual.occluders:
            if occ.kind not in ("tree", "conifer", "building", "wall") or occ.size_m is None:
                continue
            base = np.array(occ.p_ned_m)
            # Where the line of sight passes the structure (horizontal projection), and its height there.
            h = los[:2] / np.linalg.norm(los[:2])
            along = float(np.dot(base[:2] - cam[:2], h))
            d = base[:2] - cam[:2]
            lateral = abs(float(h[0] * d[1] - h[1] * d[0]))
            frac = along / float(np.linalg.norm(los[:2]))
            alt_there = -float(cam[2] + los[2] * frac)
            if frac > 1.0 and lateral <= 0.5 * occ.size_m[0] and occ.size_m[2] >= alt_there:
                n_behind += 1
                break
    assert n_leader > 90
    assert 0.6 * n_leader <= n_behind <= 0.9 * n_leader  # 75 % drawn


def test_near_profile_keeps_the_leader_at_a_formation_slots_range() -> None:
    """Every frame of a near sequence has the leader 5-12 m away, near the image centre; formation's own
    sequences are not changed by the profile's existence (the same seed gives the same views)."""
    n_leader, ranges = 0, []
    for i in range(80):
        spec = sample_sequence(9, i, 3, INTR, profile="near")
        if spec.leaders is None:
            continue
        n_leader += 1
        for cam, (_, p_leader) in zip(spec.cameras, spec.leaders, strict=True):
            ranges.append(float(np.linalg.norm(cam.to_cam(p_leader))))
    assert n_leader > 55
    assert min(ranges) >= 5.0 - 0.5  # the leader's altitude floor may pull a frame a little nearer
    assert max(ranges) <= 12.0 + 1e-6
    assert np.median(ranges) > 7.0
    with_backdrop = sum(
        1
        for i in range(80)
        if (spec := sample_sequence(9, i, 1, INTR, profile="near")).leaders is not None
        and any(o.kind in ("tree", "conifer", "building", "wall") for o in spec.visual.occluders)
    )
    assert 0.45 * n_leader <= with_backdrop <= 0.85 * n_leader  # 60 % drawn, a few occluders in front too


def test_wide_profile_is_the_default_and_unchanged_by_the_option() -> None:
    a = sample_sequence(1, 7, 3, INTR)
    b = sample_sequence(1, 7, 3, INTR, profile="wide")
    assert a.split == b.split
    for ca, cb in zip(a.cameras, b.cameras, strict=True):
        np.testing.assert_array_equal(ca.R_ned_cam, cb.R_ned_cam)
    with pytest.raises(ValueError, match="unknown dataset profile"):
        sample_sequence(1, 7, 3, INTR, profile="sideways")


def _fake_dataset(root: Path, n: int) -> None:
    rows = []
    for i in range(n):
        split = ("train", "val", "test")[i % 3]
        name = f"s{i:06d}_f00"
        for sub, ext, text in (("images", ".jpg", "jpg"), ("labels", ".txt", "0 0.5 0.5 0.1 0.1\n"),
                               ("depth", ".png", "png")):  # fmt: skip
            path = root / sub / split / f"{name}{ext}"
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_text(text)
        rows.append({"image": f"images/{split}/{name}.jpg", "split": split, "sequence": i, "range_m": "4.0"})
    with (root / "manifest.csv").open("w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=MANIFEST_COLUMNS, extrasaction="ignore")
        w.writeheader()
        w.writerows(rows)
    (root / "intrinsics.json").write_text("{}")


def test_merge_links_both_datasets_without_name_clashes(tmp_path: Path) -> None:
    _fake_dataset(tmp_path / "render_a", 6)
    _fake_dataset(tmp_path / "form_b", 3)  # the same file names as render_a's first three
    out = tmp_path / "mix"
    counts = merge(out, [tmp_path / "render_a", tmp_path / "form_b"])
    assert counts == {"train": 3, "val": 3, "test": 3}
    train = find_samples(out, "train")
    keys = sorted(s.key for s in train)
    assert keys == ["form_b__s000000_f00", "render_a__s000000_f00", "render_a__s000003_f00"]
    for s in train:
        assert s.image_path.is_symlink()
        assert s.label_path is not None
        assert s.label_path.read_text().startswith("0 ")
        assert s.range_m == pytest.approx(4.0)
    with (out / "manifest.csv").open() as f:
        assert len(list(csv.DictReader(f))) == 9


def test_merge_refuses_same_names_and_non_datasets(tmp_path: Path) -> None:
    _fake_dataset(tmp_path / "a" / "data", 2)
    _fake_dataset(tmp_path / "b" / "data", 2)
    with pytest.raises(ValueError, match="names must differ"):
        merge(tmp_path / "m", [tmp_path / "a" / "data", tmp_path / "b" / "data"])
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"no manifest\.csv"):
        merge(tmp_path / "m2", [tmp_path / "empty"])
