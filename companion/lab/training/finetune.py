"""Fine-tuning the leader detector on a team's own auto-labelled flights, and the gate before it flies.

The recordings (:mod:`companion.perception.autolabel_writer` folders) are mixed with a replay of the data the
model was trained on, so it learns its own leader without forgetting the others: ``own_weight`` of every
batch comes from the recordings, the rest from the replay sources by their weights. The run starts from the
model in service, exports ONNX, and scores old and new on held-out recordings (other flights, never trained
on). The new model is *accepted* only if it beats the old one there (mAP@0.5, recall at the service's
threshold not lower); :func:`install` copies an accepted model over the service's, never a refused one.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from companion.config import DetectorConfig
from companion.lab.training.augment import REAL_CAMERA
from companion.lab.training.export import export_and_sign
from companion.lab.training.train import train
from companion.lab.training.train_config import DataSource, TrainConfig, default_crop_px
from companion.perception.detector.dataset import find_samples, list_splits
from companion.perception.detector.torch_engine import load_weights
from companion.perception.detector.weights import sha256_file


@dataclass(frozen=True, slots=True)
class FinetuneOptions:
    """The fine-tune's schedule: short and gentle (a low learning rate from the model in service)."""

    epochs: int = 10
    epoch_images: int = 800
    batch_size: int = 16
    lr: float = 5e-4
    #: Share of every batch from the team's own recordings; the rest replays the original data.
    own_weight: float = 0.5
    threads: int = 2
    workers: int = 1
    seed: int = 0
    device: str = "auto"


def sources_for(
    recordings: Sequence[Path], replay: Sequence[DataSource], own_weight: float
) -> list[DataSource]:
    """The training mix: each recording an equal part of ``own_weight``, the replay sources the rest."""
    if not recordings:
        raise ValueError("no recordings to fine-tune on")
    if replay and not 0.0 < own_weight < 1.0:
        raise ValueError("own_weight must be between 0 and 1 when original data is replayed")
    share = own_weight if replay else 1.0
    out = [DataSource(f"own{i}", str(p), share / len(recordings)) for i, p in enumerate(recordings)]
    total = sum(s.weight for s in replay)
    out += [DataSource(s.name, s.path, (1.0 - share) * s.weight / total) for s in replay]
    return out


def _score(det_cfg: DetectorConfig, weights: Path, eval_sets: Sequence[Path]) -> dict[str, Any]:
    """The ONNX export beside ``weights`` (pinned by its sidecar) on the held-out recordings."""
    from companion.lab.training.evaluate import evaluate  # noqa: PLC0415
    from companion.perception.detector import load_detector  # noqa: PLC0415 (runtimes)

    detector = load_detector(
        det_cfg.model_copy(update={"model_path": str(weights), "model_sha256": "", "runtime": "onnx"})
    )
    samples = []
    for d in eval_sets:  # every split of a dataset with splits; a recording (flat folder) whole
        splits: list[str | None] = list(list_splits(d)) or [None]
        samples += [s for split in splits for s in find_samples(d, split)]
    out = evaluate(detector, samples, progress=False, columns=())

    def num(v: Any) -> float | None:
        return None if v is None or math.isnan(float(v)) else round(float(v), 4)

    return {
        "images": int(out["images"]),
        "leader_boxes": int(out["leader_boxes"]),
        "map50": num(out["map50"]),
        "recall": num(out["recall"]),
        "recall_within_10m": num(out["recall_within_10m"]),
        "leader_free_fp_rate": num(out["leader_free_fp_rate"]),
    }


def finetune(
    det_cfg: DetectorConfig,
    recordings: Sequence[Path],
    replay: Sequence[DataSource],
    eval_sets: Sequence[Path],
    *,
    out: Path,
    opts: FinetuneOptions,
) -> dict[str, Any]:
    """Train, export, score old and new on ``eval_sets``; writes ``OUT/finetune.json`` and a card section."""
    if not eval_sets:
        raise ValueError("no held-out recordings to judge the new model on")
    held = {p.resolve() for p in eval_sets} & {p.resolve() for p in recordings}
    if held:
        raise ValueError(f"held-out recordings are also training data: {sorted(map(str, held))}")
    base = Path(det_cfg.model_path).with_suffix(".pt")
    net, input_size_px, _ = load_weights(base)
    cfg = TrainConfig(
        data="",
        sources=tuple(sources_for(recordings, replay, opts.own_weight)),
        holdout_fraction=0.0,
        epoch_images=opts.epoch_images,
        epochs=opts.epochs,
        batch_size=opts.batch_size,
        lr=opts.lr,
        warmup_epochs=1.0,
        close_mosaic_epochs=max(1, opts.epochs // 4),
        val_every=opts.epochs + 1,
        seed=opts.seed,
        workers=opts.workers,
        threads=opts.threads,
        device=opts.device,
        init_weights=str(base),
        spec=net.spec,
        input_size_px=input_size_px,
        crop_px=default_crop_px(input_size_px),
        augment=REAL_CAMERA,
        out=str(out / "run"),
    )
    t0 = time.perf_counter()
    train(cfg, progress=False)
    train_s = time.perf_counter() - t0
    new_pt = out / "leader_detector.pt"
    shutil.copyfile(out / "run" / "final.pt", new_pt)
    export_and_sign(new_pt)
    before = _score(det_cfg, base, eval_sets)
    after = _score(det_cfg, new_pt, eval_sets)
    accepted = accepts(before, after)
    result = {
        "base_model": str(base),
        "base_sha256": sha256_file(base),
        "recordings": [str(p) for p in recordings],
        "replay": [{"name": s.name, "path": s.path, "weight": s.weight} for s in replay],
        "eval_sets": [str(p) for p in eval_sets],
        "options": {k: getattr(opts, k) for k in opts.__dataclass_fields__},
        "train_wall_s": round(train_s, 1),
        "before": before,
        "after": after,
        "accepted": accepted,
    }
    (out / "finetune.json").write_text(json.dumps(result, indent=2))
    (out / "MODEL_CARD.md").write_text(card_section(result))
    return result


def accepts(before: dict[str, Any], after: dict[str, Any]) -> bool:
    """The gate: the new model's mAP@0.5 beats the old one's, and its recall is not lower (held-out sets)."""
    return bool(
        after["map50"] is not None
        and after["map50"] > (before["map50"] or 0.0)
        and (after["recall"] or 0.0) >= (before["recall"] or 0.0)
    )


def _pct(v: float | None) -> str:
    return "n/a" if v is None else f"{100 * v:.1f} %"


def card_section(r: dict[str, Any]) -> str:
    """The model card section of a fine-tuned model (what it is, what it was trained on, its figures)."""
    b, a = r["before"], r["after"]
    lines = [
        "## Fine-tuned on the team's own flights",
        "",
        f"Started from `{r['base_model']}` (SHA-256 `{r['base_sha256'][:16]}...`) and trained for "
        f"{r['options']['epochs']} epochs of {r['options']['epoch_images']} images "
        f"(lr {r['options']['lr']:g}, {r['train_wall_s'] / 60:.1f} minutes): "
        f"{100 * r['options']['own_weight']:.0f} % of every batch from the auto-labelled recordings "
        f"({', '.join(r['recordings'])}), the rest replaying "
        f"{', '.join(s['name'] for s in r['replay']) or 'nothing'}.",
        "",
        f"Held-out recordings ({', '.join(r['eval_sets'])}; {a['images']} images, {a['leader_boxes']} "
        "leader boxes), ONNX Runtime, the service's confidence threshold:",
        "",
        "| | mAP@0.5 | recall | recall within 10 m | false positives on leader-free frames |",
        "|---|---|---|---|---|",
        f"| before | {_pct(b['map50'])} | {_pct(b['recall'])} | {_pct(b['recall_within_10m'])} | "
        f"{_pct(b['leader_free_fp_rate'])} |",
        f"| after | {_pct(a['map50'])} | {_pct(a['recall'])} | {_pct(a['recall_within_10m'])} | "
        f"{_pct(a['leader_free_fp_rate'])} |",
        "",
        "Accepted: it beats the model in service on the held-out recordings."
        if r["accepted"]
        else "Refused: it does not beat the model in service on the held-out recordings; keep the old one.",
        "",
        "The labels come from the leader's shared position checked against depth, not from a person: "
        "check the recordings' contact sheets before flying a fine-tuned model.",
        "",
    ]
    return "\n".join(lines)


def install(result_dir: Path, models_dir: Path) -> Path:
    """Copy an accepted fine-tune over the service's model files; refuses a model that was not accepted."""
    result = json.loads((result_dir / "finetune.json").read_text())
    if not result["accepted"]:
        raise ValueError(f"{result_dir}: the fine-tuned model did not beat the one in service; not installed")
    for name in ("leader_detector.pt", "leader_detector.onnx", "leader_detector.sha256"):
        shutil.copyfile(result_dir / name, models_dir / name)
    return models_dir / "leader_detector.pt"
