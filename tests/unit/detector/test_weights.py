from __future__ import annotations

from pathlib import Path

import pytest

from companion.kernel.errors import ModelError
from companion.perception.detector.weights import read_sidecar, sha256_file, verify_model_file, write_sidecar


def test_sidecar_round_trip_and_verify(tmp_path: Path) -> None:
    f = tmp_path / "m.pt"
    f.write_bytes(b"weights")
    write_sidecar(tmp_path / "m.sha256", [f])
    assert read_sidecar(tmp_path / "m.sha256") == {"m.pt": sha256_file(f)}
    assert verify_model_file(f) == sha256_file(f)
    assert verify_model_file(f, sha256_file(f).upper()) == sha256_file(f)


def test_corrupt_file_is_refused_with_one_line(tmp_path: Path) -> None:
    f = tmp_path / "m.pt"
    f.write_bytes(b"weights")
    write_sidecar(tmp_path / "m.sha256", [f])
    f.write_bytes(b"weightz")
    with pytest.raises(ModelError) as exc:
        verify_model_file(f)
    msg = str(exc.value)
    assert "\n" not in msg
    assert "does not match its checksum" in msg
    assert "m.sha256" in msg


def test_missing_file_and_missing_checksum(tmp_path: Path) -> None:
    with pytest.raises(ModelError, match="model file not found"):
        verify_model_file(tmp_path / "nope.pt", "0" * 64)
    f = tmp_path / "m.pt"
    f.write_bytes(b"x")
    with pytest.raises(ModelError, match="no checksum for"):
        verify_model_file(f)
    with pytest.raises(ModelError, match=r"detector\.model_sha256 says"):
        verify_model_file(f, "0" * 64)


def test_malformed_sidecar(tmp_path: Path) -> None:
    (tmp_path / "m.sha256").write_text("not a checksum line\n")
    with pytest.raises(ModelError, match=r"m.sha256:1"):
        read_sidecar(tmp_path / "m.sha256")
