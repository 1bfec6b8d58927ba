"""Model files on disk: checksums and the sidecar that lists them (no torch here).

A model is shipped as ``NAME.pt`` (torch weights), ``NAME.onnx`` (the same network, exported) and
``NAME.sha256`` (one ``<sha256>  <file name>`` line per file, the format ``sha256sum`` writes and checks).
A file that is missing, unreadable or does not match its checksum is refused with one :class:`ModelError`
line.
"""

from __future__ import annotations

import hashlib
from pathlib import Path

from companion.kernel.errors import ModelError

_CHUNK = 1 << 20


def sha256_file(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    try:
        with path.open("rb") as f:
            while chunk := f.read(_CHUNK):
                h.update(chunk)
    except FileNotFoundError:
        raise ModelError(f"model file not found: {path}") from None
    except OSError as exc:
        raise ModelError(f"cannot read model file {path}: {exc.strerror}") from None
    return h.hexdigest()


def sidecar_path(model_path: Path) -> Path:
    """``models/x.pt`` -> ``models/x.sha256``."""
    return model_path.with_suffix(".sha256")


def read_sidecar(path: Path) -> dict[str, str]:
    """File name -> hex digest from a ``sha256sum``-format file; empty when the file does not exist."""
    if not path.exists():
        return {}
    out: dict[str, str] = {}
    for n, line in enumerate(path.read_text().splitlines(), 1):
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        parts = line.split()
        if len(parts) != 2 or len(parts[0]) != 64:
            raise ModelError(f"{path}:{n}: expected '<sha256>  <file name>'")
        out[parts[1].lstrip("*")] = parts[0].lower()
    return out


def write_sidecar(path: Path, files: list[Path]) -> None:
    """Write the checksums of ``files`` (which must lie beside ``path``) in ``sha256sum`` format."""
    path.write_text("".join(f"{sha256_file(f)}  {f.name}\n" for f in files))


def verify_model_file(path: Path, expected_sha256: str = "") -> str:
    """Check ``path`` against ``expected_sha256``, or against its sidecar entry when that is empty.

    Returns the digest. Raises :class:`ModelError` (one line) when the file is missing or unreadable, when no
    checksum is known for it, or when it does not match: a corrupt or swapped model never reaches the loop.
    """
    actual = sha256_file(path)
    expected = expected_sha256.strip().lower()
    source = "detector.model_sha256"
    if not expected:
        side = sidecar_path(path)
        expected = read_sidecar(side).get(path.name, "")
        source = str(side)
        if not expected:
            raise ModelError(f"no checksum for {path}: set detector.model_sha256 or list it in {side}")
    if actual != expected:
        raise ModelError(
            f"model file {path} does not match its checksum ({source} says {expected[:12]}..., "
            f"file is {actual[:12]}...): corrupt or wrong file"
        )
    return actual
