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


def test_loading_the_settings_makes_home_private(tmp_path, caplog):
    """$HOPE_HOME holds the registry and the API token: created 0700 whatever the umask, and a
    too-open one we own is tightened to 0700 with a warning (the state before this existed)."""
    import logging
    import os
    import stat

    previous = os.umask(0o022)
    try:
        fresh = tmp_path / "parent" / "home"
        load_settings(env={"HOPE_HOME": str(fresh)})
        assert stat.S_IMODE(fresh.stat().st_mode) == 0o700
        assert stat.S_IMODE(fresh.parent.stat().st_mode) == 0o755  # parents are not ours to lock down

        old = tmp_path / "old-home"
        old.mkdir(mode=0o755)
        with caplog.at_level(logging.WARNING, logger="hope_models.settings"):
            load_settings(env={"HOPE_HOME": str(old)})
        assert stat.S_IMODE(old.stat().st_mode) == 0o700
        assert [r.getMessage() for r in caplog.records] == [
            f"HOPE_HOME {old} was mode 0755 (other local users could read the registry and the API token); "
            "changed to 0700"]
        caplog.clear()
        with caplog.at_level(logging.WARNING, logger="hope_models.settings"):
            load_settings(env={"HOPE_HOME": str(old)})
        assert caplog.records == []  # said once, when it changed
    finally:
        os.umask(previous)


def test_private_umask_applies_to_what_the_process_writes(tmp_path):
    import os
    import stat

    from hope_models.settings import PRIVATE_UMASK, use_private_umask

    previous = os.umask(0o022)
    try:
        assert use_private_umask() == 0o022 and PRIVATE_UMASK == 0o077
        (tmp_path / "d").mkdir()
        (tmp_path / "d" / "f").write_text("x")
        assert stat.S_IMODE((tmp_path / "d").stat().st_mode) == 0o700
        assert stat.S_IMODE((tmp_path / "d" / "f").stat().st_mode) == 0o600
    finally:
        os.umask(previous)


def test_the_queue_cap_and_forcing_over_http(tmp_path):
    s = load_settings(env={"HOPE_HOME": str(tmp_path)})
    assert (s.max_queued_runs, s.allow_http_force) == (20, False)  # capped, and no forcing over HTTP
    s = load_settings(env={"HOPE_HOME": str(tmp_path), "HOPE_MAX_QUEUED_RUNS": "5", "HOPE_ALLOW_HTTP_FORCE": "1"})
    assert (s.max_queued_runs, s.allow_http_force) == (5, True)
    with pytest.raises(SettingsError, match="max_queued_runs"):
        load_settings(env={"HOPE_HOME": str(tmp_path), "HOPE_MAX_QUEUED_RUNS": "0"})


def test_the_upload_room_and_time(tmp_path):
    s = load_settings(env={"HOPE_HOME": str(tmp_path)})
    assert (s.upload_tmp_max_mb, s.upload_extract_s) == (3072, 30.0)
    s = load_settings(env={"HOPE_HOME": str(tmp_path), "HOPE_UPLOAD_TMP_MAX_MB": "64", "HOPE_UPLOAD_EXTRACT_S": "2.5"})
    assert (s.upload_tmp_max_mb, s.upload_extract_s) == (64, 2.5)
    for var, value, field in (("HOPE_UPLOAD_TMP_MAX_MB", "0", "upload_tmp_max_mb"),
                              ("HOPE_UPLOAD_EXTRACT_S", "0", "upload_extract_s")):
        with pytest.raises(SettingsError, match=field):
            load_settings(env={"HOPE_HOME": str(tmp_path), var: value})
