"""``companion detector train | eval | export``."""

from __future__ import annotations

from typing import Any

from companion.cli import not_built


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("detector", help="train, evaluate and export the leader detector")
    dsub = p.add_subparsers(dest="detector_command", metavar="ACTION", required=True)
    t = dsub.add_parser("train", help="train on a `sitl dataset` folder")
    t.add_argument("--data", required=True, help="dataset folder")
    t.add_argument("--out", default="runs/detector", help="checkpoint folder")
    t.set_defaults(handler=not_built("detector train"))
    e = dsub.add_parser("eval", help="precision, recall, mAP on a folder of images with YOLO labels")
    e.add_argument("--data", required=True, help="folder with images/ and labels/")
    e.add_argument("--json", default=None, help="write the metrics to this JSON file")
    e.set_defaults(handler=not_built("detector eval"))
    x = dsub.add_parser("export", help="export the weights to ONNX")
    x.add_argument("--out", default=None, help="ONNX path")
    x.set_defaults(handler=not_built("detector export"))
