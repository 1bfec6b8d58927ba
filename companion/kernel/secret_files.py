"""Reading secret files (keys, passwords): refused when other users may read or change them."""

from __future__ import annotations

import os
import stat
from pathlib import Path


def read_secret(path: str | os.PathLike[str]) -> bytes:
    """A secret file's bytes; OSError when it cannot be read, PermissionError when others may read it.

    A key or password that every local user can read is no secret: refused, as ssh refuses such a key.
    systemd credentials (``LoadCredential=``) arrive mode 0400, owned by the service's user.
    """
    p = Path(path)
    with p.open("rb") as f:
        mode = stat.S_IMODE(os.fstat(f.fileno()).st_mode)
        if mode & 0o077:
            raise PermissionError(f"{p} is readable or writable by others (mode {mode:04o}); chmod 600 it")
        return f.read()
