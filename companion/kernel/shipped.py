"""Where the shipped configuration, scenarios and detector weights are found.

A *project root* is a folder with ``config/wingman.toml`` (and ``config/sitl.toml``, ``config/scenarios/``,
``models/``). In order: the working folder, when it is one (a checkout, or a deployment such as
``/opt/wingman``); else the copy installed with the package (the wheel carries ``config/`` and ``models/``
as ``companion/_shipped``); else the source checkout the package is imported from. Nothing is read here;
callers pass the root on as an argument.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

#: The file that marks a project root.
MARKER = Path("config") / "wingman.toml"


def project_root(cwd: Path | None = None) -> Path:
    """The folder whose ``config/`` and ``models/`` are used (the working folder when none is found)."""
    here = Path.cwd() if cwd is None else cwd
    if (here / MARKER).is_file():
        return here
    package = Path(str(files("companion")))
    for candidate in (package / "_shipped", package.parent):
        if (candidate / MARKER).is_file():
            return candidate
    return here


def resolve(path: str | Path, root: Path | None = None) -> Path:
    """``path`` as given when absolute or present under the working folder, else under the project root."""
    p = Path(path)
    if p.is_absolute() or p.exists():
        return p
    return (project_root() if root is None else root) / p
