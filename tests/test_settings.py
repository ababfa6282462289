import pytest

from hope_models.settings import SettingsError, load_settings


def test_defaults_and_home_from_env(tmp_path):
    s = load_settings(env={"HOPE_HOME": str(tmp_path)})
    assert s.home == tmp_path
    assert (s.host, s.port, s.redis_url, s.memory_budget_mb) == ("127.0.0.1", 8765, None, 3072)
    assert s.runs_dir == tmp_path / "runs"


def test_config_file_then_env_override(tmp_path):
    (tmp_path / "config.toml").write_text('port = 9000\nmemory_budget_mb = 2048\nredis_url = "redis://127.0.0.1:6379/0"\n')
    s = load_settings(env={"HOPE_HOME": str(tmp_path), "HOPE_PORT": "9100"})
    assert s.port == 9100  # env wins
    assert s.memory_budget_mb == 2048
    assert s.redis_url == "redis://127.0.0.1:6379/0"


def test_unknown_key_in_config_names_it(tmp_path):
    (tmp_path / "config.toml").write_text("prot = 1\n")
    with pytest.raises(SettingsError, match="unknown setting 'prot'"):
        load_settings(env={"HOPE_HOME": str(tmp_path)})


def test_bad_env_value_names_the_variable(tmp_path):
    with pytest.raises(SettingsError, match="HOPE_PORT"):
        load_settings(env={"HOPE_HOME": str(tmp_path), "HOPE_PORT": "eighty"})
