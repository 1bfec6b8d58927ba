"""Configuration loading shared by the service and the simulator: frozen sections, TOML files, overrides.

Each program defines its own sections on :class:`Section` and loads them once at its CLI edge. Overrides come
from ``WINGMAN_*`` variables, double underscores between levels and TOML literals as values, e.g.
``WINGMAN_LINK__URL=udpin://0.0.0.0:14541``.
"""

from __future__ import annotations

import difflib
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


def validation_problems(
    exc: ValidationError, model: type[BaseModel] | None = None
) -> list[tuple[tuple[str, ...], str]]:
    """One ``(key path, line)`` per problem; the line reads ``dotted.key: what is wrong (got <value>)``.

    With ``model`` (the validated class), an unknown key names the closest known one ("did you mean").
    """
    out: list[tuple[tuple[str, ...], str]] = []
    for err in exc.errors():
        loc = tuple(str(p) for p in err["loc"])
        key = ".".join(loc)
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
            close = difflib.get_close_matches(loc[-1], _known_keys(model, loc[:-1]), n=1, cutoff=0.6)
            if close:
                msg += f" (did you mean {'.'.join((*loc[:-1], close[0]))}?)"
        if not key:
            # A rule across sections: its message names the keys ("link.system_id: ...").
            named = msg.partition(":")[0]
            out.append((tuple(named.split(".")) if " " not in named else (), msg))
            continue
        got = err.get("input")
        quiet = err["type"] in ("extra_forbidden", "missing") or "(got " in msg  # the message shows it
        shown = "" if quiet else f" (got {got!r})"
        out.append((loc, f"{key}: {msg}{shown}"))
    return out


def format_validation_error(exc: ValidationError, model: type[BaseModel] | None = None) -> list[str]:
    """One line per problem: ``dotted.key: what is wrong (got <value>)`` (see :func:`validation_problems`)."""
    return [line for _, line in validation_problems(exc, model)]


def _known_keys(model: type[BaseModel] | None, loc: tuple[str, ...]) -> list[str]:
    """The keys a table at ``loc`` of ``model`` may hold (empty when ``loc`` is not a table of it)."""
    for part in loc:
        if model is None:
            return []
        field = model.model_fields.get(part)
        ann = field.annotation if field is not None else None
        model = ann if isinstance(ann, type) and issubclass(ann, BaseModel) else None
    return list(model.model_fields) if model is not None else []


def env_sources(environ: Mapping[str, str], prefix: str = ENV_PREFIX) -> dict[tuple[str, ...], str]:
    """Key path -> the ``PREFIX_SECTION__KEY`` variable that sets it (see :func:`env_overrides`)."""
    out: dict[tuple[str, ...], str] = {}
    for name in environ:
        if not name.startswith(prefix) or name == f"{prefix}CONFIG":
            continue
        path = tuple(p.lower() for p in name[len(prefix) :].split("__") if p)
        if path:
            out[path] = name
    return out


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
