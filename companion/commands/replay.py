"""``companion replay`` and ``companion record``.

See :mod:`companion.lab.replay` and :func:`companion.perception.record.run_record`. Heavy imports
(filterpy pulls in scipy) happen inside the handlers, so ``companion --help`` stays fast.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import io
import json
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from companion.commands._common import add_config_arg, load


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("replay", help="run perception on a recording and write per-frame estimates")
    add_config_arg(p)
    p.add_argument(
        "--source",
        required=True,
        help="file:PATH (a folder recording, a RealSense .bag or .db3, an .mcap flight log), sim (the "
        "simulator's camera socket, camera.path) or realsense (live); a live source runs until Ctrl-C or "
        "--frames",
    )
    p.add_argument("--frames", type=int, default=0, help="stop after N frames (0: the whole recording)")
    p.add_argument("--out", default=None, help="CSV of per-frame estimates and errors")
    p.add_argument("--json", default=None, help="also write the summary to this JSON file")
    p.add_argument(
        "--detector",
        choices=("network", "truth"),
        default="network",
        help="network: the configured detector (default); truth: the recording's ground-truth boxes "
        "(isolates pose + tracker), as in companion sim",
    )
    p.add_argument("--box-jitter-px", type=float, default=1.0, help="truth detector: box edge noise, px")
    p.add_argument("--miss-rate", type=float, default=0.0, help="truth detector: fraction of frames missed")
    p.add_argument("--seed", type=int, default=0, help="truth detector: noise seed")
    p.add_argument("--realtime", action="store_true", help="pace frames by their stamps")
    p.set_defaults(handler=_replay)
    r = sub.add_parser("record", help="record any frame source to the folder format (or a .bag)")
    add_config_arg(r)
    r.add_argument(
        "--source",
        required=True,
        help="file:PATH (a folder recording, a RealSense .bag or .db3, an .mcap flight log), sim (the "
        "simulator's camera socket, camera.path) or realsense (live)",
    )
    r.add_argument("--out", required=True, help="output folder, or a RealSense file ending in .bag")
    r.add_argument("--frames", type=int, default=0, help="stop after N frames (0: until Ctrl-C/end)")
    r.add_argument("--format", choices=("png", "jpg"), default="png", help="folder colour images")
    r.set_defaults(handler=_record)


@contextlib.contextmanager
def _open_out(path: str | None) -> Iterator[io.TextIOBase | None]:
    if path is None:
        yield None
        return
    with Path(path).open("w", newline="") as f:
        yield f


def _replay(args: argparse.Namespace) -> int:
    from companion.lab.replay import make_detect, run_replay

    cfg = load(args)
    stage = make_detect(
        args.detector, cfg, jitter_px=args.box_jitter_px, seed=args.seed, miss_rate=args.miss_rate
    )
    with _open_out(args.out) as out:
        summary = asyncio.run(
            run_replay(cfg, args.source, stage, out_csv=out, realtime=args.realtime, max_frames=args.frames)
        )
    for line in summary.lines():
        print(line)
    if args.json:
        # No NaN in the file (it is not JSON): what cannot be computed is null.
        text = json.dumps(summary.as_dict(), indent=2, default=float, allow_nan=False)
        Path(args.json).write_text(text + "\n")
    return 0 if summary.frames else 1


def _record(args: argparse.Namespace) -> int:
    from companion.perception.record import run_record

    cfg = load(args)
    result = asyncio.run(
        run_record(cfg, args.source, Path(args.out), max_frames=args.frames, image_format=args.format)
    )
    print(result.line(Path(args.out)), file=sys.stderr)
    return 0 if result.frames else 1
