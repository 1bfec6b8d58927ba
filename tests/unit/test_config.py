from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import Config, load_config
from companion.kernel.config import env_overrides, read_toml
from companion.kernel.errors import ConfigError
from sitl.config import load_sitl_config


def test_documented_default_matches_code_defaults(repo_root: Path) -> None:
    # The shipped file documents the defaults: it must validate and equal the code's defaults exactly.
    assert Config.model_validate(read_toml(repo_root / "config/wingman.toml")) == Config()


def test_the_shipped_config_finds_the_shipped_model_from_any_folder(
    repo_root: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.chdir(tmp_path)  # no models/ here, nor beside config/wingman.toml: the shipped files
    cfg = load_config(repo_root / "config/wingman.toml", environ={})
    assert cfg.detector.model_path == str(repo_root / "models/leader_detector.pt")


def test_relative_paths_are_taken_from_the_config_files_folder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    (tmp_path / "deploy" / "weights").mkdir(parents=True)
    (tmp_path / "deploy" / "weights" / "m.pt").write_bytes(b"x")
    (tmp_path / "elsewhere").mkdir()
    p = tmp_path / "deploy" / "c.toml"
    p.write_text('[detector]\nmodel_path = "weights/m.pt"\n[status]\nsocket_path = "run/s.sock"\n')
    monkeypatch.chdir(tmp_path / "elsewhere")
    cfg = load_config(p, environ={})
    assert cfg.detector.model_path == str(tmp_path / "deploy" / "weights" / "m.pt")
    assert cfg.status.socket_path == str(tmp_path / "deploy" / "run" / "s.sock")  # not there yet: same rule
    # A variable's path is the shell's: relative to the working folder.
    cfg = load_config(p, environ={"WINGMAN_STATUS__SOCKET_PATH": "here.sock"})
    assert cfg.status.socket_path == str(tmp_path / "elsewhere" / "here.sock")


def test_a_plan_that_is_not_there_names_the_path_tried(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text('[formation]\nplan = "plans/zz.toml"\n')
    with pytest.raises(ConfigError) as exc:
        load_config(p, environ={})
    (line,) = exc.value.problems
    assert line.startswith(f"formation.plan: file not found: {tmp_path}/plans/zz.toml ('plans/zz.toml' taken")
    assert f"relative to the config file's folder {tmp_path}" in line


def test_every_problem_in_one_pass_with_its_source(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text('[link]\nurl = "udpin://0.0.0.0:99999"\n[detecter]\nx = 1\n[formation]\nkp_xyz = 1.0\n')
    with pytest.raises(ConfigError) as exc:
        load_config(p, environ={"WINGMAN_SAFETY__MIN_SEPARATION_M": "-1"})
    lines = sorted(str(exc.value).splitlines())
    assert lines == sorted(
        [
            f"{p}: link.url: udpin:// needs HOST:PORT with a port in 1-65535 (got '0.0.0.0:99999')",
            f"{p}: formation.kp_xyz: unknown key (did you mean formation.kp_xy?)",
            f"{p}: detecter: unknown key (did you mean detector?)",
            "$WINGMAN_SAFETY__MIN_SEPARATION_M: "
            "safety.min_separation_m: Input should be greater than 0 (got -1)",
        ]
    )


def test_a_bad_value_from_the_environment_names_the_variable(repo_root: Path) -> None:
    with pytest.raises(ConfigError) as exc:
        load_config(repo_root / "config/wingman.toml", environ={"WINGMAN_LINK__URL": "foo"})
    assert exc.value.sources == ["$WINGMAN_LINK__URL"]
    assert str(exc.value).startswith("$WINGMAN_LINK__URL: link.url: expected one of udpin://")


def test_sitl_default_loads(repo_root: Path) -> None:
    cfg = load_sitl_config(repo_root / "config/sitl.toml", environ={})
    assert [v.name for v in cfg.vehicles] == ["leader", "follower"]


def test_wrong_type_names_the_key(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text('[link]\nconnect_timeout_s = "soon"\n')
    with pytest.raises(ConfigError) as exc:
        load_config(p, environ={})
    (line,) = exc.value.problems
    assert line.startswith("link.connect_timeout_s: Input should be a valid number")
    assert line.endswith("(got 'soon')")


def test_unknown_key_is_an_error(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text("[formation]\nkp_xyz = 1.0\n")
    with pytest.raises(ConfigError) as exc:
        load_config(p, environ={})
    assert exc.value.problems == ["formation.kp_xyz: unknown key (did you mean formation.kp_xy?)"]


def test_env_override_parses_toml_values(tmp_path: Path) -> None:
    cfg = load_config(
        None,
        environ={
            "WINGMAN_LINK__URL": "udpin://0.0.0.0:14541",
            "WINGMAN_FORMATION__OFFSET_CAM_M": "[0.0, 0.5, 6.0]",
            "WINGMAN_MQTT__ENABLED": "true",
            "OTHER": "x",
        },
    )
    assert cfg.link.url == "udpin://0.0.0.0:14541"
    assert cfg.formation.offset_cam_m == (0.0, 0.5, 6.0)
    assert cfg.mqtt.enabled is True


def test_env_override_wins_over_file(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text("[safety]\nmax_speed_m_s = 3.0\n")
    cfg = load_config(p, environ={"WINGMAN_SAFETY__MAX_SPEED_M_S": "4.5"})
    assert cfg.safety.max_speed_m_s == 4.5


def test_env_override_bad_value_is_reported() -> None:
    with pytest.raises(ConfigError) as exc:
        load_config(None, environ={"WINGMAN_SAFETY__MIN_SEPARATION_M": "-1"})
    assert exc.value.problems[0].startswith("safety.min_separation_m: Input should be greater than 0")


def test_newer_schema_refused(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text("schema_version = 99\n")
    with pytest.raises(ConfigError, match="newer Wingman"):
        load_config(p, environ={})


def test_missing_and_broken_files(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="file not found"):
        load_config(tmp_path / "nope.toml", environ={})
    p = tmp_path / "bad.toml"
    p.write_text("[link\n")
    with pytest.raises(ConfigError, match="not valid TOML"):
        load_config(p, environ={})


def test_config_is_frozen() -> None:
    cfg = Config()
    with pytest.raises(ValueError, match="frozen"):
        cfg.link.url = "x"  # type: ignore[misc]


def test_env_overrides_nesting() -> None:
    assert env_overrides({"WINGMAN_CAMERA__MOUNT__PITCH_DEG": "10"}) == {
        "camera": {"mount": {"pitch_deg": 10}}
    }


def test_a_guard_range_beyond_its_maximum_is_one_clear_line(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text("[safety]\ndepth_guard_range_m = 6.0\ndepth_guard_max_range_m = 5.0\n")
    with pytest.raises(ConfigError) as exc:
        load_config(p, environ={})
    (line,) = exc.value.problems
    assert "depth_guard_max_range_m must be >= depth_guard_range_m" in line


def test_the_leaders_system_id_is_refused_for_the_link(tmp_path: Path) -> None:
    p = tmp_path / "c.toml"
    p.write_text("[link]\nsystem_id = 1\n[leader]\nmavlink_system_id = 1\n")
    with pytest.raises(ConfigError) as exc:
        load_config(p, environ={})
    assert exc.value.problems == [
        "link.system_id: 1 is the leader's (leader.mavlink_system_id); the service never commands the leader"
    ]


@pytest.mark.parametrize(
    "url",
    ["udp://0.0.0.0:14541", "udpin://0.0.0.0", "udpin://:14541", "udpin://h:99999", "serial://ttyTHS1", "x"],
)
def test_a_malformed_link_url_is_one_line(tmp_path: Path, url: str) -> None:
    p = tmp_path / "c.toml"
    p.write_text(f'[link]\nurl = "{url}"\n')
    with pytest.raises(ConfigError) as exc:
        load_config(p, environ={})
    (line,) = exc.value.problems
    assert line.startswith("link.url: ")


@pytest.mark.parametrize(
    "url",
    ["udpin://0.0.0.0:14541", "udpout://10.0.0.2:14550", "serial:///dev/ttyTHS1:921600", "tcpout://h:5760"],
)
def test_well_formed_link_urls_pass(url: str) -> None:
    assert Config.model_validate({"link": {"url": url}}).link.url == url
