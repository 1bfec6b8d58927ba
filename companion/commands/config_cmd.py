"""``companion check-config PATH``: print the resolved config, or one line per error and exit 2.

Beyond the config's own rules it checks what ``run`` would refuse before it touches the vehicle: the detector
model file (present, and matching its checksum, for the runtime that would load it). The link URL's form is
one of the config's rules. systemd runs this as ``ExecStartPre``, so a bad deployment never starts.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

from companion.config import Config, load_config
from companion.kernel.errors import ConfigError, ModelError


def register(sub: Any) -> None:
    """Add this module's commands to the ``companion`` subparsers."""
    p = sub.add_parser("check-config", help="validate a config file and print the resolved config")
    p.add_argument("path", type=Path, help="config TOML")
    p.add_argument("--json", action="store_true", help="print the resolved config as JSON")
    p.set_defaults(handler=_check)


def _check(args: argparse.Namespace) -> int:
    cfg = load_config(args.path)
    problems = deployment_problems(cfg)
    if problems:
        raise ConfigError(str(args.path), problems)
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


def deployment_problems(cfg: Config) -> list[str]:
    """What ``companion run`` would refuse with this config, one line each (empty: none)."""
    if cfg.detector.runtime == "truth":
        return []
    from companion.perception.detector import choose_runtime, model_files

    problems = []
    named = model_files(cfg.detector)[0 if cfg.detector.model_path.endswith(".pt") else 1]
    _, loaded = choose_runtime(cfg.detector)
    try:
        verify_model_file(named, cfg.detector.model_sha256)
        if loaded != named:
            verify_model_file(loaded)
    except ModelError as exc:
        problems.append(f"detector.model_path: {exc}")
    return problems


def verify_model_file(path: Path, expected_sha256: str = "") -> None:
    """The detector's checksum check, imported only when a model is named."""
    from companion.perception.detector.weights import verify_model_file as verify

    verify(path, expected_sha256)
