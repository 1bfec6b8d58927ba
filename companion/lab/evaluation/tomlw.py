"""A small TOML writer for the files ``companion sim`` hands to ``sitl serve`` (tomllib only reads).

Covers what scenario and config models dump to: tables, arrays of tables, strings, numbers, booleans,
arrays and inline tables. ``None`` values are left out (TOML has no null; the models default them).
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any


def toml_value(v: Any) -> str:
    """One value as a TOML literal (dicts become inline tables)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        if not math.isfinite(v):
            raise ValueError(f"TOML here takes finite numbers only (got {v})")
        return repr(v)
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{_key(k)} = {toml_value(x)}" for k, x in v.items() if x is not None) + "}"
    if isinstance(v, list | tuple):
        return "[" + ", ".join(toml_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} as TOML")


def _key(k: str) -> str:
    return k if k.replace("_", "").replace("-", "").isalnum() else json.dumps(k)


def _is_table_array(v: Any) -> bool:
    return isinstance(v, list | tuple) and bool(v) and all(isinstance(x, Mapping) for x in v)


def dumps(data: Mapping[str, Any]) -> str:
    """A document: scalars first, then ``[tables]`` and ``[[arrays of tables]]``, recursively."""
    lines: list[str] = []
    _table(data, [], lines)
    return "\n".join(lines).strip() + "\n"


def _table(data: Mapping[str, Any], path: list[str], lines: list[str]) -> None:
    for k, v in data.items():
        if v is None or isinstance(v, Mapping) or _is_table_array(v):
            continue
        lines.append(f"{_key(k)} = {toml_value(v)}")
    for k, v in data.items():
        if isinstance(v, Mapping):
            lines += ["", f"[{'.'.join(_key(p) for p in [*path, k])}]"]
            _table(v, [*path, k], lines)
        elif _is_table_array(v):
            for item in v:
                lines += ["", f"[[{'.'.join(_key(p) for p in [*path, k])}]]"]
                _table(item, [*path, k], lines)
