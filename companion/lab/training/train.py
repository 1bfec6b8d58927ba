"""Training: ``companion detector train --data [NAME=]DIR[:WEIGHT] ... --out DIR``.

Several datasets train together, each with a weight: every batch takes ``round(weight * batch)`` images of
each source (e.g. half real frames, half renders), whatever the sizes of the folders. A folder with
``train``/``val`` splits validates on its ``val`` split; a flat folder (real footage) holds out whole
recordings (the manifest's ``video`` column, or the image-name prefix) for validation, so the validation
figures are never on frames of a video that trained. Validation is reported per source; the best
checkpoint is the one with the highest mean mAP@0.5 over the sources.

AdamW with a linear warm-up and a cosine decay, an exponential moving average (EMA) of the weights (the EMA
is what gets evaluated and shipped), mixed precision on a CUDA GPU, a checkpoint every epoch (``last.pt``) and
the best one by validation mAP@0.5 (``best.pt``), exact resume with ``--resume``, and a progress bar.

Everything random is derived from ``seed``: the sample order of epoch ``e`` from ``(seed, e)`` and the
augmentation of sample ``i`` in epoch ``e`` from ``(seed, e, i)``, so a run is repeatable whatever the number
of loader workers, and a resumed run sees the same batches it would have seen. The run's settings are
:mod:`companion.lab.training.train_config`, its data :mod:`companion.lab.training.train_data`.
"""

from __future__ import annotations

import copy
import json
import logging
import math
import sys
import time
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn
from torch.utils.data import DataLoader

from companion.lab.training.cache import ImageCache
from companion.lab.training.loss import DetectionLoss
from companion.lab.training.metrics import DetectionStats
from companion.lab.training.train_config import TrainConfig
from companion.lab.training.train_data import (
    AugmentedSet,
    MixedBatchSampler,
    collate,
    source_splits,
    worker_init,
)
from companion.perception.detector.layers import count_parameters
from companion.perception.detector.letterbox import boxes_to_source, letterbox_geometry, letterbox_uint8
from companion.perception.detector.model import DetectorNet, arch_of, net_for_spec
from companion.perception.detector.postprocess import Decoder
from companion.perception.detector.shufflenet import ShuffleDet, load_backbone
from companion.perception.detector.torch_engine import save_weights

log = logging.getLogger(__name__)

CHECKPOINT_FORMAT = "wingman-detector-checkpoint/1"


class ModelEMA:
    """Exponential moving average of the weights; the decay ramps up over the first updates."""

    def __init__(self, model: nn.Module, decay: float, tau_updates: float = 500.0) -> None:
        self.ema = copy.deepcopy(model).eval()
        for p in self.ema.parameters():
            p.requires_grad_(False)
        self.decay = decay
        self.tau = tau_updates
        self.updates = 0

    @torch.no_grad()
    def update(self, model: nn.Module) -> None:
        self.updates += 1
        d = self.decay * (1 - math.exp(-self.updates / self.tau))
        msd = model.state_dict()
        for k, v in self.ema.state_dict().items():
            if v.dtype.is_floating_point:
                v.mul_(d).add_(msd[k].detach(), alpha=1 - d)
            else:
                v.copy_(msd[k])


def _init_from(model: DetectorNet, ema: ModelEMA, path: Path, device: torch.device) -> None:
    """Load the weights of ``path`` (weights file or checkpoint) into the model and its EMA."""
    blob = torch.load(path, map_location=device, weights_only=False)
    if not isinstance(blob, dict):
        raise ValueError(f"--init: {path} is neither detector weights nor a training checkpoint")
    if blob.get("format") == CHECKPOINT_FORMAT:
        state = blob["ema"]
    elif "state_dict" in blob:
        state = blob["state_dict"]
    else:
        raise ValueError(f"--init: {path} is neither detector weights nor a training checkpoint")
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        raise ValueError(f"--init: {path} does not fit the model spec: {str(exc).splitlines()[0]}") from None
    ema.ema.load_state_dict(state)
    log.info("initialised from %s", path)


def lr_at(step: int, total_steps: int, warmup_steps: int, cfg: TrainConfig) -> float:
    """Learning rate of an optimiser step: linear warm-up, then cosine down to ``final_lr_fraction``."""
    if step < warmup_steps:
        return cfg.lr * (step + 1) / warmup_steps
    t = (step - warmup_steps) / max(1, total_steps - warmup_steps)
    return cfg.lr * (cfg.final_lr_fraction + (1 - cfg.final_lr_fraction) * 0.5 * (1 + math.cos(math.pi * t)))


def make_optimizer(model: nn.Module, cfg: TrainConfig) -> torch.optim.Optimizer:
    """AdamW; no weight decay on BatchNorm weights and biases."""
    decay: list[nn.Parameter] = []
    no_decay: list[nn.Parameter] = []
    for name, p in model.named_parameters():
        (no_decay if p.ndim <= 1 or name.endswith(".bias") else decay).append(p)
    groups = [{"params": decay, "weight_decay": cfg.weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
    return torch.optim.AdamW(groups, lr=cfg.lr, betas=(0.9, 0.999))


def pick_device(name: str) -> torch.device:
    """``auto``: CUDA when present, else the CPU."""
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    return torch.device(name)


@torch.no_grad()
def validate(
    model: DetectorNet,
    cache: ImageCache,
    cfg: TrainConfig,
    device: torch.device,
    conf_threshold: float = 0.35,
) -> dict[str, Any]:
    """MAP, recall and false positives of ``model`` on cached validation images letterboxed as at run time."""
    model.eval()
    decoder = Decoder(model.spec.strides, model.spec.reg_max)
    stats = DetectionStats()
    for i in range(len(cache)):
        img = cache.image(i)
        geom = letterbox_geometry(img.shape[0], img.shape[1], cfg.input_size_px)
        x = torch.from_numpy(letterbox_uint8(np.asarray(img), geom)).permute(2, 0, 1)[None].to(device)
        levels = [o.float().cpu().numpy() for o in model(x.float() / 255.0)]
        boxes, scores = decoder(levels, 0.001, 0.5, max_det=20)
        boxes_to_source(boxes, geom)
        stats.add(boxes, scores, cache.boxes(i))
    return stats.summary(conf_threshold)


def batch_size_weights(
    cfg: TrainConfig, names: list[str], shares: list[int], device: torch.device
) -> torch.Tensor | None:
    """The box loss's size weight of each position of a batch (None: every source trusted, weight 1).

    A mixed batch holds ``shares[i]`` images of source ``i`` in source order (:class:`MixedBatchSampler`),
    so the weight of each position is fixed.
    """
    if not cfg.size_weights:
        return None
    given = dict(cfg.size_weights)
    unknown = sorted(set(given) - set(names))
    if unknown:
        raise ValueError(f"--size-weight {','.join(unknown)}: no source of that name ({', '.join(names)})")
    if any(not 0.0 <= w <= 1.0 for w in given.values()):
        raise ValueError("--size-weight: weights must be in [0, 1]")
    per_image = np.repeat([given.get(n, 1.0) for n in names], shares)
    return torch.as_tensor(per_image, dtype=torch.float32, device=device)


def save_checkpoint(path: Path, **state: Any) -> None:
    """Write atomically (a crash mid-write never destroys the previous checkpoint)."""
    tmp = path.with_suffix(".tmp")
    torch.save({"format": CHECKPOINT_FORMAT, **state}, tmp)
    tmp.replace(path)


def train(
    cfg: TrainConfig, resume: bool = False, progress: bool = True, stop_after_epochs: int | None = None
) -> dict[str, Any]:
    """Run (or resume) a training; returns the final summary. Writes everything under ``cfg.out``.

    ``stop_after_epochs`` ends this call after that many epochs (the schedule still spans ``cfg.epochs``),
    so a long run can be done in slices on a shared machine and continued with ``resume``.
    """
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    device = pick_device(cfg.device)
    torch.set_num_threads(cfg.threads)
    import cv2  # noqa: PLC0415

    cv2.setNumThreads(1)  # image work here is per sample; torch owns the cores
    torch.manual_seed(cfg.seed)
    sources = cfg.all_sources
    cache_root = out / "cache"
    train_caches: list[ImageCache] = []
    val_caches: list[tuple[str, ImageCache]] = []
    counts = []
    for src in sources:
        tr, va = source_splits(src, cfg)
        counts.append(f"{src.name}: {len(tr)} train / {len(va)} val (weight {src.weight:g})")
        train_caches.append(ImageCache.build(tr, cache_root, round(cfg.input_size_px * 1.25), progress))
        if va:
            val_caches.append((src.name, ImageCache.build(va, cache_root, cfg.input_size_px, progress)))
    log.info("data: %s", "; ".join(counts))

    # channels-last: about 15% faster convolutions and BatchNorm on the CPU, and the layout tensor cores want.
    model = net_for_spec(cfg.spec)
    if cfg.backbone_weights and not resume and not cfg.init_weights:
        if not isinstance(model, ShuffleDet):
            raise ValueError("--backbone needs the shufflenetv2-fpn architecture")
        load_backbone(model.backbone, cfg.backbone_weights)
        log.info("backbone initialised from %s", cfg.backbone_weights)
    model = model.to(device).to(memory_format=torch.channels_last)  # type: ignore[call-overload]
    ema = ModelEMA(model, cfg.ema_decay)
    opt = make_optimizer(model, cfg)
    use_amp = device.type == "cuda"
    scaler = torch.amp.GradScaler("cuda", enabled=use_amp)
    criterion = DetectionLoss(model, cfg.loss)
    names = [src.name for src in sources]
    if cfg.paste_from and cfg.paste_from not in names:
        raise ValueError(f"--paste-from {cfg.paste_from}: no source of that name ({', '.join(names)})")
    donor = names.index(cfg.paste_from) if cfg.paste_from else None
    unknown = [n for n in cfg.paste_onto if n not in names]
    if unknown:
        raise ValueError(f"--paste-onto {','.join(unknown)}: no source of that name ({', '.join(names)})")
    dataset = AugmentedSet(
        train_caches,
        cfg.crop_px,
        cfg.input_size_px,
        cfg.seed,
        cfg.augment,
        donor_source=donor,
        paste_onto=frozenset(names.index(n) for n in cfg.paste_onto) or None,
    )
    sizes = [len(c) for c in train_caches]
    n_images = cfg.epoch_images or sum(sizes)
    bs = min(cfg.batch_size, sum(sizes))
    sampler = MixedBatchSampler(sizes, [s.weight for s in sources], bs, max(1, n_images // bs), cfg.seed)
    size_weight = batch_size_weights(cfg, names, sampler.shares, device)
    loader = DataLoader(
        dataset,
        batch_sampler=sampler,
        num_workers=cfg.workers,
        collate_fn=collate,
        worker_init_fn=worker_init,
        # Spawned, not forked: a forked child can deadlock on locks that the parent's OpenMP or OpenCV
        # thread pools held at fork time (seen here: a worker stuck in a futex from its first sample).
        multiprocessing_context="spawn" if cfg.workers else None,
        persistent_workers=cfg.workers > 0,
        prefetch_factor=4 if cfg.workers else None,
        pin_memory=use_amp,
    )
    steps_per_epoch = len(loader)
    total_steps = steps_per_epoch * cfg.epochs
    warmup_steps = max(1, min(int(cfg.warmup_epochs * steps_per_epoch), total_steps // 3))

    start_epoch, best_map, history = 0, -1.0, []
    last = out / "last.pt"
    if resume:
        if not last.exists():
            raise FileNotFoundError(f"--resume: no checkpoint at {last}")
        ck = torch.load(last, map_location=device, weights_only=False)
        saved = [dict(x) for x in ck["config"].get("sources", ())]
        same_data = ck["config"]["data"] == cfg.data and saved == [asdict(x) for x in cfg.sources]
        same_spec = ck["config"]["spec"] == cfg.spec.to_dict() and ck["config"].get(
            "arch", "leadernet"
        ) == arch_of(cfg.spec)
        if not same_spec or not same_data:
            raise ValueError(f"--resume: {last} was trained with another model spec or data folder")
        model.load_state_dict(ck["model"])
        ema.ema.load_state_dict(ck["ema"])
        ema.updates = ck["ema_updates"]
        opt.load_state_dict(ck["optimizer"])
        scaler.load_state_dict(ck["scaler"])
        start_epoch, best_map, history = ck["epoch"] + 1, ck["best_map50"], ck["history"]
        log.info("resuming from epoch %d (best val mAP@0.5 %.3f)", start_epoch, best_map)
    else:
        if cfg.init_weights:
            _init_from(model, ema, Path(cfg.init_weights), device)
        (out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2))
    log.info(
        "training %d params on %s: %d train images in %d sources, %d epochs x %d steps",
        count_parameters(model),
        device,
        sum(sizes),
        len(sizes),
        cfg.epochs,
        steps_per_epoch,
    )

    end_epoch = cfg.epochs if stop_after_epochs is None else min(cfg.epochs, start_epoch + stop_after_epochs)
    for epoch in range(start_epoch, end_epoch):
        sampler.epoch = epoch
        sampler.mosaic = epoch < cfg.epochs - cfg.close_mosaic_epochs
        model.train()
        t0 = time.monotonic()
        sums = {"loss": 0.0, "box": 0.0, "cls": 0.0, "dfl": 0.0}
        bar = _progress(loader, progress, f"epoch {epoch + 1}/{cfg.epochs}")
        for k, (images, boxes, mask) in enumerate(bar):
            step = epoch * steps_per_epoch + k
            for g in opt.param_groups:
                g["lr"] = lr_at(step, total_steps, warmup_steps, cfg)
            x = (
                images.to(device, non_blocking=True)
                .float()
                .div_(255.0)
                .contiguous(memory_format=torch.channels_last)
            )
            with torch.autocast(device_type=device.type, dtype=torch.float16, enabled=use_amp):
                feats = model(x)
            loss, parts = criterion(feats, boxes.to(device), mask.to(device), size_weight)
            opt.zero_grad(set_to_none=True)
            scaler.scale(loss).backward()  # type: ignore[no-untyped-call]
            scaler.unscale_(opt)
            nn.utils.clip_grad_norm_(model.parameters(), 10.0)
            scaler.step(opt)
            scaler.update()
            ema.update(model)
            sums["loss"] += float(loss.detach())
            for key, v in parts.items():
                sums[key] += v
            if hasattr(bar, "set_postfix"):
                bar.set_postfix(
                    loss=f"{sums['loss'] / (k + 1):.3f}", lr=f"{opt.param_groups[0]['lr']:.2e}", refresh=False
                )
        row: dict[str, Any] = {"epoch": epoch + 1, "seconds": round(time.monotonic() - t0, 1)}
        row.update({k: round(v / max(1, steps_per_epoch), 4) for k, v in sums.items()})
        last_epoch = epoch == cfg.epochs - 1
        if ((epoch + 1) % cfg.val_every == 0 or last_epoch) and val_caches:
            maps = []
            for name, cache in val_caches:
                val = validate(ema.ema, cache, cfg, device)  # type: ignore[arg-type]
                prefix = "val" if len(val_caches) == 1 and not cfg.sources else f"val_{name}"
                row.update(
                    {
                        f"{prefix}_map50": _r(val["map50"]),
                        f"{prefix}_map50_95": _r(val["map50_95"]),
                        f"{prefix}_recall": _r(val["recall"]),
                        f"{prefix}_precision": _r(val["precision"]),
                        f"{prefix}_fp_rate": _r(val["leader_free_fp_rate"]),
                    }
                )
                if not math.isnan(val["map50"]):
                    maps.append(val["map50"])
            mean_map = float(np.mean(maps)) if maps else 0.0
            if len(val_caches) > 1 or cfg.sources:
                row["val_mean_map50"] = round(mean_map, 4)
            if mean_map > best_map:
                best_map = mean_map
                save_weights(out / "best.pt", ema.ema, cfg.input_size_px, _meta(cfg, row))  # type: ignore[arg-type]
        history.append(row)
        log.info("epoch %s", json.dumps(row))
        save_checkpoint(
            last,
            config=cfg.to_dict(),
            epoch=epoch,
            model=model.state_dict(),
            ema=ema.ema.state_dict(),
            ema_updates=ema.updates,
            optimizer=opt.state_dict(),
            scaler=scaler.state_dict(),
            best_map50=best_map,
            history=history,
        )
        (out / "history.json").write_text(json.dumps(history, indent=1))
    finished = end_epoch == cfg.epochs
    if finished:
        save_weights(out / "final.pt", ema.ema, cfg.input_size_px, _meta(cfg, history[-1] if history else {}))  # type: ignore[arg-type]
    return {"best_val_map50": best_map, "epochs_done": end_epoch, "finished": finished, "history": history}


def _r(v: float | None) -> float | None:
    return None if v is None or math.isnan(v) else round(v, 4)


def _meta(cfg: TrainConfig, row: dict[str, Any]) -> dict[str, Any]:
    return {"train_config": json.dumps(cfg.to_dict()), "epoch_stats": json.dumps(row)}


def _progress(loader: DataLoader[Any], enabled: bool, desc: str) -> Any:
    if not enabled:
        return loader
    from tqdm import tqdm  # noqa: PLC0415

    tty = sys.stderr.isatty()
    return tqdm(loader, desc=desc, unit="batch", leave=tty, mininterval=0.5 if tty else 60.0)
