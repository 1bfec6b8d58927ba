from __future__ import annotations

import itertools
import json
from pathlib import Path

import pytest
import torch

from companion.lab.training.train import lr_at, train
from companion.lab.training.train_config import TrainConfig
from companion.perception.detector.leadernet import ModelSpec

SMALL = ModelSpec(widths=(16, 16, 24, 32, 48), neck_widths=(16, 24, 32), head_width=16)


def _cfg(data: Path, out: Path, **kw: object) -> TrainConfig:
    base = dict(
        data=str(data),
        out=str(out),
        epochs=2,
        batch_size=8,
        input_size_px=128,
        crop_px=96,
        workers=0,
        val_every=1,
        warmup_epochs=0.5,
        close_mosaic_epochs=1,
        spec=SMALL,
        seed=5,
        max_train_images=16,
        max_val_images=4,
    )
    base.update(kw)
    return TrainConfig(**base)  # type: ignore[arg-type]


def test_lr_schedule_warms_up_then_decays() -> None:
    cfg = TrainConfig(data="", out="", lr=1e-3, final_lr_fraction=0.1)
    lrs = [lr_at(s, 100, 10, cfg) for s in range(100)]
    assert lrs[0] == pytest.approx(1e-4)
    assert lrs[9] == pytest.approx(1e-3)
    assert all(a >= b for a, b in itertools.pairwise(lrs[10:]))
    assert lrs[-1] == pytest.approx(1e-4, rel=0.01)


def test_resume_and_worker_count_give_the_same_weights(tiny_dataset: Path, tmp_path: Path) -> None:
    # One augmentation worker process here, none in the sliced run: the weights must not care.
    straight = train(_cfg(tiny_dataset, tmp_path / "a", workers=1), progress=False)
    assert straight["finished"]
    assert len(straight["history"]) == 2
    for name in ("last.pt", "best.pt", "final.pt", "history.json", "config.json"):
        assert (tmp_path / "a" / name).exists()
    first = train(_cfg(tiny_dataset, tmp_path / "b"), progress=False, stop_after_epochs=1)
    assert not first["finished"]
    assert not (tmp_path / "b" / "final.pt").exists()
    resumed = train(_cfg(tiny_dataset, tmp_path / "b"), resume=True, progress=False)
    assert resumed["finished"]
    a = torch.load(tmp_path / "a" / "final.pt", weights_only=True)["state_dict"]
    b = torch.load(tmp_path / "b" / "final.pt", weights_only=True)["state_dict"]
    for k in a:
        torch.testing.assert_close(a[k], b[k], msg=f"{k} differs after resume")
    hist = json.loads((tmp_path / "b" / "history.json").read_text())
    assert [h["epoch"] for h in hist] == [1, 2]
    assert "val_map50" in hist[-1]


def test_resume_refuses_another_spec(tiny_dataset: Path, tmp_path: Path) -> None:
    train(_cfg(tiny_dataset, tmp_path / "c", epochs=1), progress=False)
    with pytest.raises(ValueError, match="another model spec"):
        train(_cfg(tiny_dataset, tmp_path / "c", epochs=1, spec=ModelSpec()), resume=True, progress=False)


def test_train_and_val_must_not_share_images(tiny_dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="both the train and val"):
        train(_cfg(tiny_dataset, tmp_path / "d", val_split="train"), progress=False)


def test_init_starts_a_new_run_from_other_weights(tiny_dataset: Path, tmp_path: Path) -> None:
    """``--init``: a new run starts from the source's weights (here its shipped ``final.pt``), so after an
    epoch it is much nearer them than a run from random weights with the same seed is."""
    train(_cfg(tiny_dataset, tmp_path / "src", epochs=1), progress=False)
    src = torch.load(tmp_path / "src" / "final.pt", weights_only=True)["state_dict"]
    init = str(tmp_path / "src" / "final.pt")
    train(_cfg(tiny_dataset, tmp_path / "ft", epochs=1, seed=6, init_weights=init), progress=False)
    train(_cfg(tiny_dataset, tmp_path / "fresh", epochs=1, seed=6), progress=False)
    assert json.loads((tmp_path / "ft" / "config.json").read_text())["init_weights"] == init

    def distance(run: str) -> float:
        ema = torch.load(tmp_path / run / "last.pt", weights_only=False)["ema"]
        return sum(float((ema[k] - v).abs().sum()) for k, v in src.items() if v.dtype.is_floating_point)

    d_ft, d_fresh = distance("ft"), distance("fresh")
    assert 0.0 < d_ft < 0.5 * d_fresh, (d_ft, d_fresh)


def test_init_refuses_a_file_that_is_not_weights(tiny_dataset: Path, tmp_path: Path) -> None:
    bad = tmp_path / "bad.pt"
    torch.save([1, 2, 3], bad)
    with pytest.raises(ValueError, match="neither detector weights nor a training checkpoint"):
        train(_cfg(tiny_dataset, tmp_path / "x", init_weights=str(bad)), progress=False)


def test_paste_from_must_name_a_source(tiny_dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="--paste-from real: no source of that name"):
        train(_cfg(tiny_dataset, tmp_path / "p", paste_from="real"), progress=False)


def test_paste_onto_must_name_sources(tiny_dataset: Path, tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="--paste-onto sky: no source of that name"):
        train(_cfg(tiny_dataset, tmp_path / "p", paste_onto=("sky",)), progress=False)
