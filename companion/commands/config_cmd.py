"""``companion check-config PATH``: print the resolved config, or every problem (one line each) and exit 2.

Beyond the config's own rules it checks what ``run`` would refuse before it touches the vehicle: the detector
model files (present, and matching their checksums, for the runtime that would load them). Each problem
names where its value came from: the file, or the ``WINGMAN_*`` variable that set it. Relative paths are
resolved against the config file's folder (companion/config/paths.py); the resolved config shows them
absolute. systemd runs this as ``ExecStartPre``, so a bad deployment never starts.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from companion.kernel.errors import CompanionError, ConfigError


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser(
        "check-config",
        help="validate a config file and print the resolved config",
        description="Validate a config file (with WINGMAN_* overrides) and the model files it names; print "
        "the resolved config, or every problem, one line each, naming where its value came from (exit 2).",
    )
    p.add_argument("path", type=Path, help="config TOML")
    p.add_argument(
        "--json", action="store_true", help="print JSON: the resolved config, or the problems (always JSON)"
    )
    p.set_defaults(handler=_check)


def _check(args: argparse.Namespace) -> int:
    from companion.service.health_checks import verify_config

    try:
        verdict = verify_config(args.path)
    except CompanionError as exc:  # unreadable or not TOML: nothing more can be checked
        if args.json:
            print(json.dumps({"ok": False, "problems": [{"source": str(args.path), "problem": str(exc)}]}))
            return exc.exit_code
        raise
    cfg = verdict.config
    if cfg is None:
        if args.json:
            found = [
                {"source": s, "problem": p} for s, p in zip(verdict.sources, verdict.problems, strict=True)
            ]
            print(json.dumps({"ok": False, "problems": found}, indent=2))
            return ConfigError.exit_code
        raise ConfigError(str(args.path), verdict.problems, verdict.sources)
    data = cfg.model_dump(mode="json")
    if args.json:
        print(json.dumps({"ok": True, "config": data}, indent=2))
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
