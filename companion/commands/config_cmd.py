"""``companion check-config PATH``: print the resolved config, or one line per error and exit 2."""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from companion.config import load_config


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("check-config", help="validate a config file and print the resolved config")
    p.add_argument("path", type=Path, help="config TOML")
    p.add_argument("--json", action="store_true", help="print the resolved config as JSON")
    p.set_defaults(handler=_check)


def _check(args: argparse.Namespace) -> int:
    cfg = load_config(args.path)
    data = cfg.model_dump(mode="json")
    if args.json:
        print(json.dumps(data, indent=2))
    else:
        _print_toml_like(data)
    return 0


def _print_toml_like(data: dict[str, Any], prefix: str = "") -> None:
    scalars = {k: v for k, v in data.items() if not isinstance(v, dict)}
    tables = {k: v for k, v in data.items() if isinstance(v, dict)}
    if prefix:
        print(f"[{prefix}]")
    for key, value in scalars.items():
        print(f"{key} = {json.dumps(value)}")
    for key, value in tables.items():
        print()
        _print_toml_like(value, f"{prefix}.{key}" if prefix else key)
