"""Training on several datasets: source parsing, per-batch shares, the mixed sampler, held-out recordings."""

from __future__ import annotations

import collections
from pathlib import Path

import pytest

from companion.lab.training.train_config import DataSource, TrainConfig, parse_source
from companion.lab.training.train_data import MixedBatchSampler, batch_shares, source_splits


def test_parse_source() -> None:
    assert parse_source("real=/d/real:0.5") == DataSource("real", "/d/real", 0.5)
    assert parse_source("/d/renders") == DataSource("renders", "/d/renders", 1.0)
    assert parse_source("/d/renders:2") == DataSource("renders", "/d/renders", 2.0)
    with pytest.raises(ValueError, match="weight"):
        parse_source("x=/d/x:0")


def test_batch_shares_follow_the_weights() -> None:
    assert batch_shares([0.5, 0.5], 16) == [8, 8]
    assert batch_shares([0.5, 0.2, 0.2, 0.1], 16) == [8, 3, 3, 2]
    assert sum(batch_shares([1, 1, 1], 16)) == 16
    assert min(batch_shares([100, 1], 8)) >= 1


def test_every_batch_has_each_sources_share_and_the_order_is_repeatable() -> None:
    s = MixedBatchSampler([50, 7], [0.5, 0.5], 8, 20, seed=3)
    batches = list(s)
    assert len(batches) == len(s) == 20
    for b in batches:
        assert collections.Counter(k[1] for k in b) == {0: 4, 1: 4}
    # The small source is walked again and again (each pass in a new order, told apart by the draw).
    small = [(k[2], k[3]) for b in batches for k in b if k[1] == 1]
    assert len(set(small)) == len(small) == 80
    assert {i for i, _ in small} == set(range(7))
    assert batches == list(MixedBatchSampler([50, 7], [0.5, 0.5], 8, 20, seed=3))
    s.epoch = 1
    assert list(s) != batches


def test_flat_folder_holds_out_whole_recordings(tmp_path: Path) -> None:
    root = tmp_path / "real"
    (root / "images").mkdir(parents=True)
    (root / "labels").mkdir()
    lines = ["image,video,frame,width,height,n_boxes,box_wxh_px,distance_bin,drone_type"]
    for v in range(30):
        for f in range(4):
            name = f"V_DRONE_{v:03d}_f{f:05d}"
            (root / "images" / f"{name}.jpg").write_bytes(b"")
            (root / "labels" / f"{name}.txt").write_text("0 0.5 0.5 0.1 0.1\n")
            lines.append(f"{name},V_DRONE_{v:03d},{f},640,512,1,30x20,MEDIUM,F450")
    (root / "manifest.csv").write_text("\n".join(lines) + "\n")
    cfg = TrainConfig(data="", out="", holdout_fraction=0.2)
    train, val = source_splits(DataSource("real", str(root)), cfg)
    assert len(train) + len(val) == 120
    assert val
    assert not {s.group for s in train} & {s.group for s in val}
    assert {s.attr("drone_type") for s in val} == {"F450"}
    assert len({s.group for s in val}) * 4 == len(val)
