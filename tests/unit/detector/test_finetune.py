"""Fine-tuning on recordings: the mix, the held-out gate, and install refusing a model that lost."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from companion.config import DetectorConfig
from companion.lab.training.finetune import FinetuneOptions, accepts, finetune, install, sources_for
from companion.lab.training.train_config import DataSource
from tests.unit.detector.synthetic import make_dataset


def test_the_mix_gives_the_recordings_their_share() -> None:
    replay = [DataSource("real", "r", 2.0), DataSource("renders", "s", 2.0)]
    mix = sources_for([Path("a"), Path("b")], replay, own_weight=0.5)
    assert [(s.name, s.weight) for s in mix] == [
        ("own0", 0.25),
        ("own1", 0.25),
        ("real", 0.25),
        ("renders", 0.25),
    ]
    assert [s.weight for s in sources_for([Path("a")], [], own_weight=0.5)] == [1.0]
    with pytest.raises(ValueError, match="no recordings"):
        sources_for([], replay, own_weight=0.5)


def test_a_fine_tune_is_accepted_only_when_it_beats_the_model_in_service() -> None:
    old = {"map50": 0.80, "recall": 0.90}
    assert accepts(old, {"map50": 0.85, "recall": 0.90})
    assert not accepts(old, {"map50": 0.80, "recall": 0.95})  # equal mAP is not better
    assert not accepts(old, {"map50": 0.90, "recall": 0.89})  # better mAP, lower recall
    assert not accepts(old, {"map50": None, "recall": 1.0})  # no boxes to judge on
    assert accepts(
        {"map50": None, "recall": None}, {"map50": 0.1, "recall": 0.0}
    )  # the old one found nothing


def test_finetune_scores_old_and_new_on_held_out_recordings(shipped_model: Path, tmp_path: Path) -> None:
    own = make_dataset(tmp_path / "own", {"train": 12}, seed=5, size=(160, 120))
    held = make_dataset(tmp_path / "held", {"test": 6}, seed=6, size=(160, 120))
    models = tmp_path / "models"
    shutil.copytree(shipped_model.parent, models)
    det = DetectorConfig(model_path=str(models / "leader_detector.pt"))
    opts = FinetuneOptions(epochs=1, epoch_images=8, batch_size=4, threads=1, workers=0, device="cpu")
    with pytest.raises(ValueError, match="also training data"):
        finetune(det, [own], [], [own], out=tmp_path / "bad", opts=opts)
    result = finetune(det, [own], [], [held], out=tmp_path / "run", opts=opts)
    for key in ("map50", "recall", "recall_within_10m"):
        assert key in result["before"]
        assert key in result["after"]
    assert result["before"]["images"] == result["after"]["images"] == 6
    assert result["accepted"] is accepts(result["before"], result["after"])
    assert (tmp_path / "run" / "leader_detector.onnx").is_file()
    assert "Fine-tuned on the team's own flights" in (tmp_path / "run" / "MODEL_CARD.md").read_text()
    # Installing follows the verdict: a refused model is never installed over the one in service.
    doc = json.loads((tmp_path / "run" / "finetune.json").read_text())
    doc["accepted"] = False
    (tmp_path / "run" / "finetune.json").write_text(json.dumps(doc))
    before = (models / "leader_detector.pt").read_bytes()
    with pytest.raises(ValueError, match="not installed"):
        install(tmp_path / "run", models)
    assert (models / "leader_detector.pt").read_bytes() == before
    doc["accepted"] = True
    (tmp_path / "run" / "finetune.json").write_text(json.dumps(doc))
    install(tmp_path / "run", models)
    assert (models / "leader_detector.pt").read_bytes() == (
        tmp_path / "run" / "leader_detector.pt"
    ).read_bytes()
