"""``companion detector train | eval | export``. Heavy imports (torch, cv2) happen inside the handlers."""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
from pathlib import Path
from typing import Any

from companion.commands._common import add_config_arg, load
from companion.kernel.errors import ModelError

log = logging.getLogger("companion.detector")


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("detector", help="train, evaluate and export the leader detector")
    dsub = p.add_subparsers(dest="detector_command", metavar="ACTION", required=True)

    t = dsub.add_parser(
        "train", help="train on one or more datasets mixed per batch (`sitl dataset` folders, real frames)"
    )
    add_config_arg(t)
    t.add_argument(
        "--data",
        required=True,
        action="append",
        metavar="[NAME=]DIR[:WEIGHT]",
        help="dataset folder, repeatable; WEIGHT is its share of every batch (e.g. real=DIR:0.5)",
    )
    t.add_argument(
        "--arch",
        choices=("shufflenetv2-fpn", "leadernet"),
        default="shufflenetv2-fpn",
        help="network (shufflenetv2-fpn: ShuffleNetV2 0.5x backbone + light FPN)",
    )
    t.add_argument(
        "--backbone", default="", help="pretrained ShuffleNetV2 0.5x state dict (shufflenetv2-fpn only)"
    )
    t.add_argument(
        "--holdout", type=float, default=0.1, help="share of recordings of a flat folder held out to validate"
    )
    t.add_argument("--epoch-images", type=int, default=0, help="images per epoch (0: all training images)")
    t.add_argument(
        "--augment",
        choices=("default", "real-camera", "real-camera-window"),
        default="real-camera",
        help="augmentation recipe (real-camera-window: also the tracking window's view of the leader)",
    )
    t.add_argument(
        "--paste-from",
        default="",
        metavar="NAME",
        help="copy-paste the labelled objects of this --data source onto training samples",
    )
    t.add_argument(
        "--paste-onto",
        default="",
        metavar="NAME[,NAME...]",
        help="the --data sources whose samples get pasted objects (default: all)",
    )
    t.add_argument(
        "--paste-p", type=float, default=0.3, help="share of samples that get a pasted object (default 0.3)"
    )
    t.add_argument(
        "--size-weight",
        action="append",
        default=[],
        metavar="NAME=W",
        help="weight (0-1) of the box size in the loss for this --data source's images: below 1 for loosely "
        "labelled sources (repeatable; default 1)",
    )
    t.add_argument("--out", default="runs/detector", help="run folder: checkpoints, history, weights")
    t.add_argument("--epochs", type=int, default=30, help="epochs in the learning-rate schedule (default 30)")
    t.add_argument("--batch-size", type=int, default=32, help="images per step (default 32)")
    t.add_argument(
        "--input-size",
        type=int,
        default=None,
        help="letterbox size the model is trained for, px (default: detector.input_size_px)",
    )
    t.add_argument(
        "--crop", type=int, default=None, help="training crop size, px (<= --input-size; default 0.8x it)"
    )
    t.add_argument("--lr", type=float, default=2e-3, help="peak learning rate (AdamW, default 0.002)")
    t.add_argument("--seed", type=int, default=0, help="seed of the sample order and augmentations")
    t.add_argument("--workers", type=int, default=1, help="augmentation worker processes")
    t.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    t.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    t.add_argument("--val-every", type=int, default=3, help="validate every N epochs")
    t.add_argument("--close-mosaic", type=int, default=5, help="last N epochs without mosaic")
    t.add_argument(
        "--stop-after", type=int, default=None, help="stop after N epochs of this call (resume later)"
    )
    t.add_argument("--resume", action="store_true", help="continue the run in --out from its last.pt")
    t.add_argument(
        "--init", default="", help="start from these weights (.pt weights or a run's checkpoint): fine-tuning"
    )
    t.add_argument("--no-progress", action="store_true", help="no progress bar")
    t.set_defaults(handler=_train)

    e = dsub.add_parser(
        "eval", help="precision, recall, mAP, false positives on folders of images with YOLO labels"
    )
    add_config_arg(e)
    e.add_argument(
        "--data",
        required=True,
        action="append",
        metavar="[NAME=]DIR",
        help="folder with images/ and labels/ (or a dataset with splits); repeatable, reported per source",
    )
    e.add_argument(
        "--split",
        default=None,
        help="split to evaluate (default: 'test' when the folder has splits; folders without splits: all)",
    )
    e.add_argument("--json", default=None, help="write the metrics to this JSON file")
    e.add_argument(
        "--by",
        default="distance_bin,drone_type,airframe,time_of_day",
        help="manifest columns reported per value (those a folder's manifest has)",
    )
    e.add_argument(
        "--sheet",
        default=None,
        help="write a contact sheet PNG of the worst misses and false positives here (NAME inserted "
        "before .png when there are several sources)",
    )
    e.add_argument(
        "--model", default=None, help="weights (.pt) or export (.onnx); default: detector.model_path"
    )
    e.add_argument(
        "--runtime", choices=("auto", "torch", "onnx"), default=None, help="override detector.runtime"
    )
    e.add_argument("--input-size", type=int, default=None, help="override detector.input_size_px")
    e.add_argument("--conf", type=float, default=None, help="override detector.conf_threshold")
    e.add_argument(
        "--size-oracle",
        default=None,
        metavar="COLUMN",
        help="also report mAP@0.5 with each value of this manifest column's boxes scaled by the factor best "
        "for it (a diagnostic of loose labels whose margin differs per video; it sees the labels)",
    )
    e.add_argument(
        "--window",
        action="store_true",
        help="also score the service's tracking window on each labelled leader (detector.roi_* settings)",
    )
    e.add_argument("--no-progress", action="store_true", help="no progress bar")
    e.set_defaults(handler=_eval)

    f = dsub.add_parser(
        "finetune",
        help="fine-tune the model in service on auto-labelled recordings; keep it only if it is better",
        description="Fine-tune the configured model on auto-labelled recordings (companion autolabel or "
        "[autolabel] in the service) mixed with a replay of its original data, export ONNX, and score old "
        "and new on held-out recordings. --install copies the new model over the configured one only when "
        "it beats it there.",
    )
    add_config_arg(f)
    f.add_argument("--data", required=True, action="append", metavar="DIR", help="a recording (repeatable)")
    f.add_argument(
        "--replay",
        action="append",
        default=[],
        metavar="NAME=DIR:WEIGHT",
        help="original training data to replay so the model does not forget (repeatable)",
    )
    f.add_argument(
        "--eval", required=True, action="append", metavar="DIR", help="held-out recording (repeatable)"
    )
    f.add_argument("--out", type=Path, required=True, help="run folder: weights, ONNX, finetune.json, card")
    f.add_argument("--epochs", type=int, default=10, help="epochs (default 10)")
    f.add_argument("--epoch-images", type=int, default=800, help="images per epoch (default 800)")
    f.add_argument("--lr", type=float, default=5e-4, help="peak learning rate (default 0.0005)")
    f.add_argument("--own-weight", type=float, default=0.5, help="share of every batch from --data")
    f.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    f.add_argument("--workers", type=int, default=1, help="augmentation worker processes")
    f.add_argument("--device", default="auto", help="auto | cpu | cuda")
    f.add_argument("--seed", type=int, default=0, help="seed of the sample order and augmentations")
    f.add_argument(
        "--install", action="store_true", help="copy the new model over the configured one if it was accepted"
    )
    f.set_defaults(handler=_finetune)

    x = dsub.add_parser("export", help="export weights to ONNX (opset >= 17) and update the checksum sidecar")
    add_config_arg(x)
    x.add_argument("--weights", default=None, help="weights .pt (default: detector.model_path)")
    x.add_argument("--out", default=None, help="ONNX path (default: beside the weights)")
    x.add_argument("--opset", type=int, default=17, help="ONNX opset (default 17)")
    x.set_defaults(handler=_export)


def _train(args: argparse.Namespace) -> int:
    service = load(args)
    from dataclasses import replace

    from companion.lab.training.augment import REAL_CAMERA, REAL_CAMERA_WINDOW, AugmentConfig
    from companion.lab.training.train import train
    from companion.lab.training.train_config import TrainConfig, default_crop_px, parse_source
    from companion.perception.detector.leadernet import ModelSpec
    from companion.perception.detector.shufflenet import ShuffleDetSpec

    # The network is trained for the input the service runs it at, unless told otherwise.
    input_size = service.detector.input_size_px if args.input_size is None else args.input_size
    crop = default_crop_px(input_size) if args.crop is None else args.crop
    if crop > input_size:
        print("companion detector train: --crop must be <= --input-size", file=sys.stderr)
        return 2
    if not 0.0 <= args.paste_p <= 1.0:
        print("companion detector train: --paste-p must be in [0, 1]", file=sys.stderr)
        return 2
    try:
        sources = tuple(parse_source(d) for d in args.data)
        size_weights = tuple(_name_weight(t) for t in args.size_weight)
    except ValueError as exc:
        print(f"companion detector train: {exc}", file=sys.stderr)
        return 2
    single = len(sources) == 1 and sources[0].weight == 1.0 and "=" not in args.data[0]
    cfg = TrainConfig(
        data=sources[0].path if single else "",
        sources=() if single else sources,
        holdout_fraction=args.holdout,
        epoch_images=args.epoch_images,
        backbone_weights=args.backbone,
        spec=ShuffleDetSpec() if args.arch == "shufflenetv2-fpn" else ModelSpec(),
        augment=replace(
            {"real-camera": REAL_CAMERA, "real-camera-window": REAL_CAMERA_WINDOW}.get(
                args.augment, AugmentConfig()
            ),
            paste_p=args.paste_p if args.paste_from else 0.0,
        ),
        paste_from=args.paste_from,
        paste_onto=tuple(n.strip() for n in args.paste_onto.split(",") if n.strip()),
        size_weights=size_weights,
        out=str(args.out),
        epochs=args.epochs,
        batch_size=args.batch_size,
        input_size_px=input_size,
        crop_px=crop,
        lr=args.lr,
        seed=args.seed,
        workers=args.workers,
        threads=args.threads,
        device=args.device,
        val_every=args.val_every,
        close_mosaic_epochs=args.close_mosaic,
        init_weights=args.init,
    )
    try:
        result = train(
            cfg, resume=args.resume, progress=not args.no_progress, stop_after_epochs=args.stop_after
        )
    except (FileNotFoundError, ValueError) as exc:
        print(f"companion detector train: {exc}", file=sys.stderr)
        return 2
    state = (
        "done" if result["finished"] else f"stopped after epoch {result['epochs_done']} (--resume to go on)"
    )
    print(f"{state}; best validation mAP@0.5 {result['best_val_map50']:.3f}; weights in {args.out}/best.pt")
    return 0


def _name_weight(text: str) -> tuple[str, float]:
    """``NAME=W`` -> (name, weight)."""
    name, sep, value = text.partition("=")
    try:
        weight = float(value)
    except ValueError:
        weight = math.nan
    if not sep or not name or not 0.0 <= weight <= 1.0:
        raise ValueError(f"--size-weight {text}: expected NAME=W with W in [0, 1]")
    return name, weight


def _finetune(args: argparse.Namespace) -> int:
    cfg = load(args)
    from companion.lab.training.finetune import FinetuneOptions, finetune, install
    from companion.lab.training.train_config import parse_source

    try:
        replay = [parse_source(r) for r in args.replay]
        opts = FinetuneOptions(
            epochs=args.epochs,
            epoch_images=args.epoch_images,
            lr=args.lr,
            own_weight=args.own_weight,
            threads=args.threads,
            workers=args.workers,
            device=args.device,
            seed=args.seed,
        )
        args.out.mkdir(parents=True, exist_ok=True)
        result = finetune(
            cfg.detector,
            [Path(d) for d in args.data],
            replay,
            [Path(d) for d in args.eval],
            out=args.out,
            opts=opts,
        )
    except (FileNotFoundError, ValueError, ModelError) as exc:
        print(f"companion detector finetune: {exc}", file=sys.stderr)
        return 2
    b, a = result["before"], result["after"]
    print(
        f"held-out recordings: mAP@0.5 {b['map50']} -> {a['map50']}, recall {b['recall']} -> {a['recall']}, "
        f"recall within 10 m {b['recall_within_10m']} -> {a['recall_within_10m']}; "
        f"trained in {result['train_wall_s'] / 60:.1f} min; "
        + ("accepted" if result["accepted"] else "refused: the model in service stays")
    )
    if args.install:
        try:
            path = install(args.out, Path(cfg.detector.model_path).parent)
        except ValueError as exc:
            print(f"companion detector finetune: {exc}", file=sys.stderr)
            return 3
        print(f"installed {path}")
    return 0


def _eval(args: argparse.Namespace) -> int:
    cfg = load(args)
    from companion.lab.training.evaluate import evaluate
    from companion.lab.training.metrics import format_summary
    from companion.perception.detector.dataset import find_samples, list_splits

    det_cfg = cfg.detector
    updates: dict[str, Any] = {}
    if args.model is not None:
        updates["model_path"] = args.model
        if Path(args.model).resolve() != Path(det_cfg.model_path).resolve():
            updates["model_sha256"] = ""
    if args.runtime is not None:
        updates["runtime"] = args.runtime
    elif args.model is not None and Path(args.model).suffix in (".pt", ".onnx"):
        updates["runtime"] = "onnx" if Path(args.model).suffix == ".onnx" else "torch"
    if args.input_size is not None:
        updates["input_size_px"] = args.input_size
    if args.conf is not None:
        updates["conf_threshold"] = args.conf
    det_cfg = det_cfg.model_copy(update=updates)
    sources: list[tuple[str, Path, str | None]] = []
    for text in args.data:
        name, sep, rest = text.partition("=")
        if not sep or "/" in name:
            name, rest = "", text
        data = Path(rest)
        splits = list_splits(data) if data.is_dir() else []
        split = args.split
        if split is None and "test" in splits:
            split = "test"
        elif split is not None and data.is_dir() and not splits:
            split = None  # a flat folder (e.g. real frames): all of its images
        sources.append((name or data.name, data, split))
    try:
        sample_sets = [find_samples(data, split) for _, data, split in sources]
    except FileNotFoundError as exc:
        print(f"companion detector eval: {exc}", file=sys.stderr)
        return 2
    detector = _load_unverified_ok(det_cfg)
    columns = [c.strip() for c in args.by.split(",") if c.strip()]
    results: dict[str, Any] = {}
    for (name, data, split), samples in zip(sources, sample_sets, strict=True):
        sheet = None
        if args.sheet:
            sheet = Path(args.sheet)
            if len(sources) > 1:
                sheet = sheet.with_name(f"{sheet.stem}_{name}{sheet.suffix or '.png'}")
        summary = evaluate(
            detector,
            samples,
            progress=not args.no_progress,
            columns=columns,
            sheet=sheet,
            size_oracle_by=args.size_oracle,
            window=det_cfg if args.window else None,
        )
        summary["data"] = str(data)
        summary["split"] = split
        summary["model"] = det_cfg.model_path
        results[name] = summary
        print(f"{data}{f' [{split}]' if split else ''}: {detector.runtime} at {detector.input_size_px} px")
        print(format_summary(summary))
        print(format_groups(summary["by_column"]))
        if summary["by_range_m"]:
            print(format_range_bins(summary["by_range_m"], summary.get("window", {}).get("by_range_m")))
        if "window" in summary:
            w = summary["window"]
            print(
                f"tracking window ({w['images']} labelled frames): recall {100 * w['recall']:.1f}% "
                f"(at IoU 0.25 {100 * w['recall_loose']:.1f}%), mAP@0.5 {100 * w['map50']:.1f}%"
            )
        if "size_oracle" in summary:
            o = summary["size_oracle"]
            print(
                f"size oracle by {o['column']}: mAP@0.5 {100 * o['map50']:.1f}% with each value's best box "
                f"scale ({min(o['scales'].values()):.2f}-{max(o['scales'].values()):.2f})"
            )
        if sheet is not None:
            print(f"contact sheet: {sheet}")
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        doc = next(iter(results.values())) if len(results) == 1 else {"sources": results}
        Path(args.json).write_text(json.dumps(_json_ready(doc), indent=2))
    return 0


def format_groups(by_column: dict[str, dict[str, dict[str, Any]]]) -> str:
    """Per manifest column and value: recall and mAP@0.5 on its boxes, false positives on its empty frames."""

    def pct(v: Any) -> str:
        return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{100 * v:.1f}%"

    lines = []
    for col, per in by_column.items():
        lines.append(f"by {col}:")
        for value, f in per.items():
            parts = [f"{f['images']} images"]
            if f["leader_boxes"]:
                parts.append(
                    f"recall {pct(f['recall'])}, mAP@0.5 {pct(f['map50'])} ({f['leader_boxes']} boxes)"
                )
                if f.get("box_scale_median") is not None:
                    parts.append(f"box/label {f['box_scale_median']:.2f}")
            if f["leader_free_images"]:
                parts.append(
                    f"false positives {pct(f['leader_free_fp_rate'])} of {f['leader_free_images']} empty"
                )
            lines.append(f"  {value:<16} " + "; ".join(parts))
    return "\n".join(lines)


def format_range_bins(whole: list[dict[str, Any]], window: list[dict[str, Any]] | None = None) -> str:
    """Recall and AP per range bin, whole frame (and in the tracking window), as a table."""

    def pct(v: Any) -> str:
        return "n/a" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{100 * v:.1f}"

    win = {tuple(b["range_m"]): b for b in window or []}
    head = "range m     boxes  recall  AP@0.5  AP@0.25"
    lines = ["by range (whole frame" + (" | window" if window is not None else "") + "):"]
    lines.append(f"  {head}" + ("  | recall  AP@0.5" if window is not None else ""))
    for b in whole:
        lo, hi = b["range_m"]
        row = f"  {lo:>4g}-{hi:<4g} {b['leader_boxes']:>7} {pct(b['recall']):>7} {pct(b['map50']):>7} "
        row += f"{pct(b['ap25']):>8}"
        if window is not None:
            w = win.get((lo, hi))
            row += f"  | {pct(w['recall']) if w else 'n/a':>6} {pct(w['map50']) if w else 'n/a':>7}"
        lines.append(row)
    return "\n".join(lines)


def _load_unverified_ok(det_cfg: Any) -> Any:
    """Load through the checksum check; a run's own weights (no sidecar yet) are loaded with a warning."""
    from companion.perception.detector import load_detector
    from companion.perception.detector.weights import sha256_file

    try:
        return load_detector(det_cfg)
    except ModelError as exc:
        if "no checksum" not in str(exc):
            raise
        digest = sha256_file(Path(det_cfg.model_path))
        log.warning(
            "%s has no recorded checksum; evaluating it as-is (sha256 %s)", det_cfg.model_path, digest
        )
        return load_detector(det_cfg.model_copy(update={"model_sha256": digest}))


def _json_ready(v: Any) -> Any:
    """NaN (no data for a figure) -> null, recursively; JSON has no NaN."""
    if isinstance(v, float) and math.isnan(v):
        return None
    if isinstance(v, dict):
        return {k: _json_ready(x) for k, x in v.items()}
    if isinstance(v, list | tuple):
        return [_json_ready(x) for x in v]
    return v


def _export(args: argparse.Namespace) -> int:
    cfg = load(args)
    from companion.lab.training.export import export_and_sign

    weights = Path(args.weights or Path(cfg.detector.model_path).with_suffix(".pt"))
    onnx_path, side = export_and_sign(weights, Path(args.out) if args.out else None, args.opset)
    print(f"wrote {onnx_path} (opset {args.opset}); checksums in {side}")
    return 0
