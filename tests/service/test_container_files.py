"""Static checks of the Dockerfile and compose file (the test suite runs without a Docker engine)."""

from __future__ import annotations

import os
import re
import shlex
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def dockerfile_instructions() -> list[tuple[str, str]]:
    text = (ROOT / "Dockerfile").read_text().replace("\\\n", " ")
    out = []
    for raw in text.splitlines():
        line = raw.strip()
        if line and not line.startswith("#"):
            op, _, rest = line.partition(" ")
            out.append((op.upper(), rest.strip()))
    return out


def test_copy_sources_exist_and_cmd_is_executable() -> None:
    ins = dockerfile_instructions()
    assert ins[0][0] == "FROM"
    for op, rest in ins:
        if op == "COPY":
            *sources, _dest = shlex.split(rest)
            for src in sources:
                assert (ROOT / src).exists(), src
    cmd = next(rest for op, rest in ins if op == "CMD")
    script = ROOT / re.findall(r'"([^"]+)"', cmd)[0]
    assert os.access(script, os.X_OK)


def test_image_has_what_the_tests_need() -> None:
    run = " ".join(rest for op, rest in dockerfile_instructions() if op == "RUN")
    for pkg in ("mosquitto", "systemd", "libegl1", "libusb-1.0-0"):
        assert pkg in run
    assert "download.pytorch.org/whl/cpu" in run  # never PyPI's CUDA build
    assert ("USER", "tester") in dockerfile_instructions()


@pytest.mark.parametrize("name", [".venv", ".git", "runs"])
def test_dockerignore_keeps_the_context_small(name: str) -> None:
    assert name in (ROOT / ".dockerignore").read_text().split()


def test_compose_services_use_existing_scripts() -> None:
    text = (ROOT / "compose.yaml").read_text()
    assert re.search(r"^  tests:$", text, re.M)
    assert re.search(r"^  sitl-tests:$", text, re.M)
    for script in re.findall(r'"(scripts/[a-z]+)"', text):
        assert os.access(ROOT / script, os.X_OK), script
