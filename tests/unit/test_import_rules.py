"""The import rules catch what they forbid: a planted service -> lab import breaks ``lint-imports``."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
LINT_IMPORTS = Path(sys.executable).parent / "lint-imports"


def _lint(root: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [str(LINT_IMPORTS), "--no-cache"],
        cwd=root,
        env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(root)},
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )


@pytest.mark.slow
@pytest.mark.lab  # the project's own tooling (import-linter in .venv), not the flight service on 3.10
def test_a_planted_service_to_lab_import_breaks_the_rules(tmp_path: Path) -> None:
    if not LINT_IMPORTS.exists():
        pytest.fail("import-linter is installed by scripts/setup")
    for name in ("companion", "sitl"):
        shutil.copytree(REPO / name, tmp_path / name, ignore=shutil.ignore_patterns("__pycache__", "models"))
    shutil.copy(REPO / "pyproject.toml", tmp_path / "pyproject.toml")
    kept = _lint(tmp_path)
    assert kept.returncode == 0, kept.stdout[-2000:]
    wiring = tmp_path / "companion" / "service" / "wiring.py"
    wiring.write_text(wiring.read_text() + "\nfrom companion.lab import perception_eval  # planted\n")
    broken = _lint(tmp_path)
    assert broken.returncode != 0
    assert "The flight service never imports the lab (companion.lab) or the simulator BROKEN" in broken.stdout
    assert "companion.service.wiring -> companion.lab.perception_eval" in broken.stdout
