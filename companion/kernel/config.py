"""Configuration loading shared by the service and the simulator: frozen sections, TOML files, overrides.

Each program defines its own sections on :class:`Section` and loads them once at its CLI edge. Overrides come
from ``WINGMAN_*`` variables, double underscores between levels and TOML literals as values, e.g.
``WINGMAN_LINK__URL=udpin://0.0.0.0:14541``.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, ValidationError

from companion.kernel.compat import tomllib
from companion.kernel.errors import ConfigError

ENV_PREFIX = "WINGMAN_"


class Section(BaseModel):
    """Base of every config section: immutable, and unknown keys are errors (typos must not pass)."""

    model_config = ConfigDict(frozen=True, extra="forbid")


def format_validation_error(exc: ValidationError) -> list[str]:
    """One line per problem: ``dotted.key: what is wrong (got <value>)``."""
    lines = []
    for err in exc.errors():
        key = ".".join(str(p) for p in err["loc"])
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
        if not key:
            lines.append(msg)  # a rule across sections: its message names the keys
            continue
        got = err.get("input")
        shown = "" if err["type"] in ("extra_forbidden", "missing") else f" (got {got!r})"
        lines.append(f"{key}: {msg}{shown}")
    return lines


def env_overrides(environ: Mapping[str, str], prefix: str = ENV_PREFIX) -> dict[str, Any]:
    """Nested dict from ``PREFIX_SECTION__KEY=value`` variables; values parse as TOML literals or strings."""
    out: dict[str, Any] = {}
    for name, raw in environ.items():
        if not name.startswith(prefix) or name == f"{prefix}CONFIG":
            continue
        path = [p.lower() for p in name[len(prefix) :].split("__") if p]
        if not path:
            continue
        try:
            value: Any = tomllib.loads(f"v = {raw}")["v"]
        except tomllib.TOMLDecodeError:
            value = raw
        node = out
        for part in path[:-1]:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"${name}", [f"{'.'.join(path)}: conflicts with another override"])
        node[path[-1]] = value
    return out


def deep_merge(base: dict[str, Any], top: Mapping[str, Any]) -> dict[str, Any]:
    """Merge ``top`` into a copy of ``base``; tables merge key by key, other values replace."""
    merged = dict(base)
    for key, value in top.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), dict):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def read_toml(path: Path) -> dict[str, Any]:
    """Parse a TOML file, turning every failure into a one-line :class:`ConfigError`."""
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise ConfigError(str(path), ["file not found"]) from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(path), [f"not valid TOML: {exc}"]) from None
    except OSError as exc:
        raise ConfigError(str(path), [f"cannot read: {exc.strerror}"]) from None
