"""``companion``: the command-line edge: parse arguments, load config, set up logging, map errors to exits.

Exit codes: 0 ok, 1 failure, unhealthy, or an operator command refused (the line says why), 2 bad usage,
config or model, 3 camera or link failure, 4 a link that carries only autopilots this
service must not fly, 5 no service answers on the status socket (``status``, ``start``, ``command``).
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from collections.abc import Callable, Sequence

from companion import __version__
from companion.commands import autolabel, bench, config_cmd, detector, deviation, replay, run, sim, status
from companion.kernel import compat
from companion.kernel.cli import describe_commands
from companion.kernel.errors import CompanionError, first_companion_error

log = logging.getLogger("companion")

#: The command modules, in --help order (each imports its heavy parts only when it runs).
COMMAND_MODULES = (run, status, config_cmd, sim, deviation, bench, detector, replay, autolabel)

Handler = Callable[[argparse.Namespace], int]


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser, with every command registered."""
    parser = argparse.ArgumentParser(
        prog="companion",
        description="Wingman: vision-based leader-follower companion service for PX4.",
    )
    parser.add_argument("--version", action="version", version=f"wingman {__version__}")
    parser.add_argument(
        "--log-format",
        choices=("human", "json"),
        default=None,
        help="log lines as text or JSON (overrides the config)",
    )
    parser.add_argument(
        "--log-level",
        choices=("DEBUG", "INFO", "WARNING", "ERROR"),
        default=None,
        help="least severe log level shown (overrides the config)",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for module in COMMAND_MODULES:
        module.register(sub)
    describe_commands(parser)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``companion`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    handler: Handler = args.handler
    try:
        return handler(args)
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:
        # The reader went away (``companion status | head``): not an error of ours. Point stdout at
        # /dev/null so the interpreter's final flush does not raise again.
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        return 0
    except CompanionError as exc:
        return _report(exc)
    except compat.BaseExceptionGroup as group:
        # A task group (a simulated flight's service, say) that failed on one of our own errors: its one
        # line, not the group's traceback.
        ours = first_companion_error(group)
        if ours is None:
            raise
        return _report(ours)


def _report(exc: CompanionError) -> int:
    for line in str(exc).splitlines() or [type(exc).__name__]:
        print(f"companion: {line}", file=sys.stderr)
    return exc.exit_code
