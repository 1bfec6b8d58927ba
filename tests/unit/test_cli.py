from __future__ import annotations

import argparse
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import pytest

from companion import cli
from companion.cli import build_parser as build_companion_parser
from companion.cli import main as companion_main
from companion.kernel.compat import ExceptionGroup
from companion.kernel.errors import ModelError
from sitl.cli import build_parser as build_sitl_parser
from sitl.cli import main as sitl_main


def run(*args: str, cwd: Path, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    full_env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2]), **(env or {})}
    return subprocess.run(
        [sys.executable, *args],
        cwd=cwd,
        env=full_env,
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )


def test_companion_help_lists_every_command(repo_root: Path) -> None:
    r = run("-m", "companion", "--help", cwd=repo_root)
    assert r.returncode == 0
    for cmd in ("run", "status", "health", "check-config", "sim", "bench", "detector", "replay", "record"):
        assert cmd in r.stdout


def test_sitl_help_lists_every_command(repo_root: Path) -> None:
    r = run("-m", "sitl", "--help", cwd=repo_root)
    assert r.returncode == 0
    for cmd in ("serve", "dataset", "bench", "bench-render", "contact-sheet"):
        assert cmd in r.stdout


def test_help_does_not_import_heavy_modules(repo_root: Path) -> None:
    code = (
        "import sys; from companion.cli import build_parser; from sitl.cli import build_parser as b2; "
        "build_parser(); b2(); heavy = [m for m in ('torch', 'cv2', 'mavsdk', 'jsbsim', 'moderngl') "
        "if m in sys.modules]; print(heavy); sys.exit(bool(heavy))"
    )
    r = run("-c", code, cwd=repo_root)
    assert r.returncode == 0, r.stdout + r.stderr


def test_check_config_ok(repo_root: Path) -> None:
    r = run("-m", "companion", "check-config", "config/wingman.toml", cwd=repo_root)
    assert r.returncode == 0, r.stderr
    assert 'url = "udpin://0.0.0.0:14541"' in r.stdout
    assert "system_id = 2" in r.stdout


def test_check_config_refuses_a_missing_or_corrupt_model(tmp_path: Path, repo_root: Path) -> None:
    for name in ("leader_detector.pt", "leader_detector.onnx", "leader_detector.sha256"):
        (tmp_path / name).write_bytes((repo_root / "models" / name).read_bytes())
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[detector]\nmodel_path = "{tmp_path / "leader_detector.pt"}"\n')
    assert run("-m", "companion", "check-config", str(cfg), cwd=repo_root).returncode == 0
    with (tmp_path / "leader_detector.onnx").open("ab") as f:
        f.write(b"\0")  # the file the ONNX runtime would load is corrupt
    r = run("-m", "companion", "check-config", str(cfg), cwd=repo_root)
    assert r.returncode == 2
    assert r.stderr.count("\n") == 1
    assert "detector.model_path: model file" in r.stderr
    assert "does not match its checksum" in r.stderr
    (tmp_path / "leader_detector.pt").unlink()
    r = run("-m", "companion", "check-config", str(cfg), cwd=repo_root)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()  # both files, in one pass
    assert (
        lines[0]
        == f"companion: {cfg}: detector.model_path: model file not found: {tmp_path}/leader_detector.pt"
    )
    assert "leader_detector.onnx does not match its checksum" in lines[1]


def test_check_config_errors_one_line_each(tmp_path: Path, repo_root: Path) -> None:
    p = tmp_path / "bad.toml"
    p.write_text('vehicle_id = "f1"\n[link]\nconnect_timeout_s = "x"\n[mqtt]\nportt = 1\n')
    r = run("-m", "companion", "check-config", str(p), cwd=repo_root)
    assert r.returncode == 2
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 2
    assert "link.connect_timeout_s" in lines[0]
    assert lines[1] == f"companion: {p}: mqtt.portt: unknown key (did you mean mqtt.port?)"


@pytest.mark.lab
def test_sim_without_weights_says_so_in_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The network detector is the default; with no weights nothing starts and one line says why."""
    missing = tmp_path / "none" / "leader_detector.pt"
    argv = [
        "sim",
        "--scenario",
        "all",
        "--out",
        str(tmp_path / "out"),
        "--set",
        f'detector.model_path="{missing}"',
    ]
    assert companion_main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1
    assert "no detector weights" in err[0]
    assert not (tmp_path / "out").exists()


def test_sitl_unknown_command_is_usage_error() -> None:
    with pytest.raises(SystemExit) as exc:
        sitl_main(["fly-to-the-moon"])
    assert exc.value.code == 2


def test_the_parsers_import_no_command_until_it_runs() -> None:
    """`companion --help` and `sitl --help` stay light: no torch, JSBSim, renderer or simulator loaded."""
    code = (
        "import sys\n"
        "from companion.cli import build_parser as c\n"
        "from sitl.cli import build_parser as s\n"
        "c(); s()\n"
        "heavy = ('torch', 'jsbsim', 'cv2', 'sitl.serve', 'sitl.render', 'companion.app')\n"
        "print(sorted(m for m in sys.modules if m.split('.')[0] in heavy or m.startswith(heavy)))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout


@pytest.mark.lab
def test_sim_all_prints_the_paper_table(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """`sim --scenario all` ends with the paper's table beside ours on stdout (the runs are stood in for)."""
    from companion.lab.evaluation import campaign

    report = {
        "outcome": "completed",
        "relative_position_rmse_m": 0.036,
        "relative_yaw_rmse_deg": 0.3,
        "formation_rmse_m": 0.08,
        "formation_max_deviation_m": 0.28,
        "min_separation_m": 4.7,
        "detection_recall": 0.9,
        "false_positive_rate": 0.0,
        "perception_latency_ms": {"p50": 5.0},
        "meets_targets": True,
    }

    def fake_run_many(specs: list, out_dir: Path, **_kw: object) -> dict:
        return {"reports": {s.scenario: report for s in specs}, "failed": [], "wall_s": 1.0}

    monkeypatch.setattr(campaign, "run_many", fake_run_many)
    argv = ["sim", "--scenario", "all", "--detector", "truth", "--out", str(tmp_path / "out")]
    assert companion_main(argv) == 0
    out = capsys.readouterr().out
    assert "# Wingman vs the paper" in out
    assert "| Straight line | 0.25 / 0.036 | 2.5 / 0.30 | 0.60 / 0.280 | completed | yes |" in out
    assert out.rstrip().endswith("/*/plots")


def _commands(parser: argparse.ArgumentParser, prefix: str) -> list[tuple[str, argparse.ArgumentParser]]:
    out = [(prefix, parser)]
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, sub in action.choices.items():
                out += _commands(sub, f"{prefix} {name}")
    return out


@pytest.mark.parametrize("build", [build_companion_parser, build_sitl_parser], ids=["companion", "sitl"])
def test_every_command_and_option_says_what_it_does(build: Callable[[], argparse.ArgumentParser]) -> None:
    silent = []
    for name, parser in _commands(build(), build().prog):
        if not parser.description:
            silent.append(f"{name}: no description")
        for action in parser._actions:
            if isinstance(action, argparse._SubParsersAction | argparse._HelpAction):
                continue
            if not action.help:
                silent.append(f"{name} {'/'.join(action.option_strings) or action.dest}: no help")
    assert silent == []


def test_check_config_lists_every_problem_in_one_pass(tmp_path: Path, repo_root: Path) -> None:
    """A bad URL, an unknown key and a missing model: all three, each with where it came from."""
    p = tmp_path / "bad.toml"
    p.write_text('[link]\nurl = "foo"\n[detector]\nthreshhold = 3\nmodel_path = "nope/x.pt"\n')
    r = run("-m", "companion", "check-config", str(p), cwd=tmp_path)  # from the config's own folder
    assert r.returncode == 2
    assert r.stderr.strip().splitlines() == [
        f"companion: {p}: link.url: expected one of udpin://, udpout://, tcpin://, tcpout://, serial://... "
        "(got 'foo')",
        f"companion: {p}: detector.threshhold: unknown key (did you mean detector.conf_threshold?)",
        f"companion: {p}: detector.model_path: model file not found: {tmp_path}/nope/x.pt ('nope/x.pt' taken "
        f"relative to the config file's folder {tmp_path}; not in the shipped files {repo_root} either)",
    ]
    r = run(
        "-m", "companion", "check-config", str(p), cwd=repo_root, env={"WINGMAN_LINK__URL": "udpin://h:1"}
    )
    assert "link.url" not in r.stderr  # the variable's value replaced the file's


def test_an_error_of_ours_inside_a_task_group_is_one_line(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """A flight's task group that failed on a missing model says so in one line, not a group traceback."""

    def fails(_: argparse.Namespace) -> int:
        raise ExceptionGroup("unhandled errors in a TaskGroup", [ModelError("model file not found: /x.pt")])

    def unrelated(_: argparse.Namespace) -> int:
        raise ExceptionGroup("unhandled errors in a TaskGroup", [ValueError("a bug")])

    for handler in (fails, unrelated):
        parser = argparse.ArgumentParser()
        parser.set_defaults(handler=handler)
        monkeypatch.setattr(cli, "build_parser", lambda p=parser: p)
        if handler is fails:
            assert cli.main([]) == ModelError("").exit_code
            assert capsys.readouterr().err.strip().splitlines() == ["companion: model file not found: /x.pt"]
        else:
            with pytest.raises(ExceptionGroup):  # not ours: the traceback stays
                cli.main([])
