"""Helpers shared by command modules: the --config argument and loading it with logging set up."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

from companion.config import Config, load_config
from companion.kernel.logs import setup_logging
from companion.kernel.shipped import project_root

#: Relative to the project root (companion/kernel/shipped.py): the working folder, or the installed copy.
DEFAULT_CONFIG = Path("config/wingman.toml")


def add_config_arg(parser: argparse.ArgumentParser) -> None:
    """Add ``--config PATH`` (default: $WINGMAN_CONFIG, else config/wingman.toml)."""
    parser.add_argument(
        "--config",
        type=Path,
        default=None,
        help="service config TOML (default: $WINGMAN_CONFIG or config/wingman.toml)",
    )


def config_path(args: argparse.Namespace) -> Path:
    """The config path from the command line, the environment, or the default."""
    if args.config is not None:
        return Path(args.config)
    env = os.environ.get("WINGMAN_CONFIG")
    return Path(env) if env else project_root() / DEFAULT_CONFIG


def load(args: argparse.Namespace) -> Config:
    """Load the config and set up logging from it (command-line flags win)."""
    cfg = load_config(config_path(args))
    setup_logging(args.log_format or cfg.logging.format, args.log_level or cfg.logging.level)
    return cfg
