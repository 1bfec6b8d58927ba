"""Static checks of the Dockerfile and compose file.

The suite runs without a container engine; `scripts/container test` builds the image and runs the SITL tests
in it (docs/container.md).
"""

from __future__ import annotations

import re
import shlex
import tomllib
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


def test_copy_sources_exist_in_a_checkout() -> None:
    ins = dockerfile_instructions()
    assert next(op for op, _ in ins if op != "ARG") == "FROM"
    for op, rest in ins:
        if op == "COPY" and "--from=" not in rest:
            *sources, _dest = [w for w in shlex.split(rest) if not w.startswith("--")]
            for src in sources:
                assert (ROOT / src).exists(), src


def test_the_image_runs_the_sitl_tests_as_a_user_from_its_venv() -> None:
    ins = dockerfile_instructions()
    run = " ".join(rest for op, rest in ins if op == "RUN")
    for pkg in ("mosquitto", "mosquitto-clients", "libegl1", "libgl1-mesa-dri"):
        assert pkg in run
    assert ("ARG", "BASE_IMAGE=python:3.11-slim-bookworm") in ins
    assert ("FROM", "${BASE_IMAGE}") in ins
    env = " ".join(rest for op, rest in ins if op == "ENV")
    assert "PATH=/opt/venv/bin:$PATH" in env
    assert ("USER", "wingman") in ins
    cmd = next(rest for op, rest in ins if op == "CMD")
    markers = {
        m.split(":")[0]
        for m in tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["pytest"]["ini_options"][
            "markers"
        ]
    }
    (selected,) = re.findall(r'"-m", "([^"]+)", "tests"', cmd)
    assert set(selected.split()) - {"or"} <= markers


@pytest.mark.parametrize("name", [".venv", ".venv310", ".git", "runs", "/build", "/dist"])
def test_dockerignore_keeps_the_context_small(name: str) -> None:
    assert name in (ROOT / ".dockerignore").read_text().split()


def test_compose_builds_one_image_and_sets_no_cpu_count() -> None:
    text = (ROOT / "compose.yaml").read_text()
    assert len(re.findall(r"^\s+build:", text, re.M)) == 1
    assert "cpus:" not in text
    for service in ("sitl-tests", "broker", "service", "sim"):
        assert re.search(rf"^  {service}:$", text, re.M), service
    assert re.findall(r"^\s+image: (\S+)", text, re.M) == ["wingman-sitl"]
