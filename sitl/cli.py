"""``sitl``: run the simulator, make datasets, benchmark. Heavy imports live inside the handlers."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path
from typing import Any

from companion import __version__
from companion.kernel.cli import describe_commands
from companion.kernel.errors import CompanionError

Handler = Callable[[argparse.Namespace], int]
#: An in-process component of ``sitl serve`` (called with a :class:`sitl.serve.server.SimHandle`).
Component = Callable[[Any], Awaitable[None]]


# Each command imports its module only when it runs: `sitl --help` stays light (no JSBSim, no renderer).


def _serve(args: argparse.Namespace) -> int:
    from sitl.serve.server import main  # noqa: PLC0415

    return main(args, args.components)


def _dataset(args: argparse.Namespace) -> int:
    from sitl.render.dataset import main_dataset  # noqa: PLC0415

    return main_dataset(args)


def _dataset_merge(args: argparse.Namespace) -> int:
    from sitl.render.dataset import main_merge  # noqa: PLC0415

    return main_merge(args)


def _contact_sheet(args: argparse.Namespace) -> int:
    from sitl.render.dataset import main_contact_sheet  # noqa: PLC0415

    return main_contact_sheet(args)


def _bench(args: argparse.Namespace) -> int:
    from sitl.world.bench import main  # noqa: PLC0415

    return main(args)


def _bench_render(args: argparse.Namespace) -> int:
    from sitl.render.bench import main  # noqa: PLC0415

    return main(args)


def build_parser() -> argparse.ArgumentParser:
    """The ``sitl`` argument parser."""
    parser = argparse.ArgumentParser(prog="sitl", description="Wingman's PX4-compatible JSBSim simulator.")
    parser.add_argument("--version", action="version", version=f"wingman-sitl {__version__}")
    parser.add_argument(
        "--log-format", choices=("human", "json"), default="human", help="log lines as text or JSON"
    )
    parser.add_argument(
        "--log-level",
        choices=("DEBUG", "INFO", "WARNING", "ERROR"),
        default="INFO",
        help="least severe log level shown (default INFO)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    s = sub.add_parser("serve", help="run N vehicles over MAVLink/UDP in real time (Ctrl-C stops)")
    s.add_argument(
        "--config",
        type=Path,
        default=None,
        help="simulator config (default: config/sitl.toml of the working folder or of the installed package)",
    )
    s.add_argument("--speed", type=float, default=None, help="speed factor (overrides the config)")
    s.add_argument(
        "--scenario",
        default=None,
        help="a scenario name (looked up in the config's folder, scenarios/NAME.toml) or a TOML path",
    )
    s.add_argument("--seed", type=int, default=None, help="random seed (default: scenario's, else config's)")
    s.add_argument(
        "--camera",
        type=Path,
        default=Path("/run/wingman/camera.sock"),
        metavar="SOCKET",
        help="the follower's rendered RGB-D camera on this Unix socket (default: %(default)s, the service's "
        "camera.path)",
    )
    s.add_argument("--no-camera", action="store_true", help="no camera (MAVLink only)")
    s.add_argument(
        "--autopilot",
        choices=("builtin", "px4"),
        default="builtin",
        help="builtin: the simulator's own PX4-like autopilot (default); px4: a real PX4 SITL process per "
        "vehicle with SIH physics ([px4] binary in the config, or SITL_PX4__BINARY)",
    )
    s.set_defaults(handler=_serve)

    d = sub.add_parser("dataset", help="render a detector dataset with YOLO labels and COCO json")
    d.add_argument("--out", type=Path, required=True, help="new dataset folder")
    d.add_argument("--count", type=int, required=True, help="frames to render")
    d.add_argument("--seed", type=int, default=0, help="random seed of the scenes (default 0)")
    d.add_argument("--seq-len", type=int, default=6, help="frames per sequence (splits are by sequence)")
    d.add_argument(
        "--profile",
        choices=("wide", "formation", "clutter", "near"),
        default="wide",
        help="wide: drones seen every way (default); formation: the follower's in-flight view of the leader; "
        "clutter: that view with a tree or building behind the leader; near: the formation view at 5-12 m, "
        "mostly with a structure behind the leader",
    )
    d.set_defaults(handler=_dataset)

    m = sub.add_parser(
        "dataset-merge", help="join `sitl dataset` folders into one by symbolic links (splits kept)"
    )
    m.add_argument("--out", type=Path, required=True, help="new merged dataset folder")
    m.add_argument("sources", type=Path, nargs="+", help="dataset folders (their names must differ)")
    m.set_defaults(handler=_dataset_merge)

    c = sub.add_parser(
        "contact-sheet", help="PNG of 16 random dataset frames with boxes and false-colour depth"
    )
    c.add_argument("--data", type=Path, required=True, help="a `sitl dataset` folder")
    c.add_argument("--out", type=Path, default=Path("runs/contact-sheet.png"), help="PNG to write")
    c.add_argument("--seed", type=int, default=0, help="which random frames (default 0)")
    c.add_argument("--tile-px", type=int, default=320, help="width of each colour/depth tile")
    c.set_defaults(handler=_contact_sheet)

    b = sub.add_parser("bench", help="lockstep real-time factor for 2 vehicles, without rendering")
    b.add_argument("--json", type=Path, default=None, help="also write the figures to this JSON file")
    b.add_argument("--sim-s", type=float, default=60.0, help="sim seconds per run (default 60)")
    b.add_argument("--repeats", type=int, default=3, help="runs; the median is reported (default 3)")
    b.set_defaults(handler=_bench)

    r = sub.add_parser("bench-render", help="rendered RGB-D frames per second at 640x480 with noise")
    r.add_argument("--json", type=Path, default=None, help="also write the figures to this JSON file")
    r.add_argument("--frames", type=int, default=300, help="frames to render (default 300)")
    r.set_defaults(handler=_bench_render)
    describe_commands(parser)
    return parser


def main(argv: Sequence[str] | None = None, *, components: Sequence[Component] = ()) -> int:
    """Entry point of the ``sitl`` console script.

    A program that hosts the simulator passes ``components``: async callables ``component(sim)`` that
    ``serve`` runs beside the simulation (:mod:`sitl.serve.server`).
    """
    args = build_parser().parse_args(argv)
    args.components = tuple(components)
    handler: Handler = args.handler
    try:
        return handler(args)
    except KeyboardInterrupt:
        return 130
    except CompanionError as exc:
        for line in str(exc).splitlines():
            print(f"sitl: {line}", file=sys.stderr)
        return exc.exit_code
