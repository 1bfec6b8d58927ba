"""Where a file or folder named in the config is: one rule for every path key.

A relative path is taken relative to where it was written: the config file's folder for the file's keys
(and the defaults), the working folder for ``WINGMAN_*`` variables. One that is not there but is among the
shipped files (under the project root or its ``config/``, :mod:`companion.kernel.shipped`) is taken from
those, so the shipped config finds the shipped weights, and ``formations/v.toml`` the shipped plan, from
any folder. Absolute paths stay as given.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from companion.kernel.shipped import project_root

#: The config keys that name a file or folder (section, key).
PATH_KEYS: tuple[tuple[str, str], ...] = (
    ("detector", "model_path"),
    ("formation", "plan"),
    ("camera", "path"),
    ("link", "signing_key_file"),
    ("mqtt", "password_file"),
    ("mqtt", "ca_file"),
    ("mqtt", "cert_file"),
    ("mqtt", "key_file"),
    ("mqtt", "command_keys_file"),
    ("mqtt", "formation_keys_file"),
    ("status", "socket_path"),
    ("service", "state_dir"),
    ("autolabel", "out_dir"),
    ("viz", "log_dir"),
)


@dataclass(frozen=True, slots=True)
class ResolvedPath:
    """A path key's value as written and the path it stands for."""

    given: str
    path: Path
    #: What the relative value was taken against, in words (empty for an absolute value).
    base: str = ""
    #: The shipped-files folder also looked in (None: not looked in, or the path was found there).
    also_tried: Path | None = None

    def note(self) -> str:
        """How a relative value was resolved, for a message about a file that is not there."""
        if not self.base:
            return ""
        shipped = f"; not in the shipped files {self.also_tried} either" if self.also_tried else ""
        return f" ({self.given!r} taken relative to {self.base}{shipped})"


def resolve_path(
    given: str, base_dir: Path, base_words: str, shipped_root: Path | None = None
) -> ResolvedPath:
    """``given`` relative to ``base_dir``; falling back to the shipped files when it is not there."""
    p = Path(given).expanduser()
    if p.is_absolute():
        return ResolvedPath(given, p)
    here = (base_dir / p).absolute()
    if here.exists():
        return ResolvedPath(given, here, base_words)
    root = (project_root() if shipped_root is None else shipped_root).absolute()
    for shipped in (root / p, root / "config" / p):
        if shipped.exists():
            return ResolvedPath(given, shipped, f"the shipped files in {root}")
    return ResolvedPath(given, here, base_words, root if root != base_dir.absolute() else None)
