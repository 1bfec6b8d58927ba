from __future__ import annotations

from pathlib import Path

import pytest

from companion.config import Config, load_config
from companion.kernel.config import env_overrides
from companion.kernel.errors import ConfigError
from sitl.config import load_sitl_config


def test_documented_default_matches_code_defaults(repo_root: Path) -> None:
    # The shipped file documents the defaults: it must load and equal the code's defaults exactly.
    assert load_config(repo_root / "config/wingman.toml", environ={}) == Config()


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
    assert exc.value.problems == ["formation.kp_xyz: unknown key"]


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
