"""`hope-trainer doctor`: one line per check with its fix, a fail exits non-zero, and it reads
state without changing it (no migration, no token made, no chmod, no $HOPE_HOME created).

The end-to-end runs go through `run_trainer.py doctor --json` in a subprocess with a temp
HOPE_HOME; only the ok-path run includes the torch and render children (the others --skip them).
"""
from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from hope_trainer.doctor import FAIL, OK, SKIP, WARN, Check, host, run_checks, state

REPO = Path(__file__).resolve().parent.parent
TOKEN = "t" * 43
QUICK = ("--skip", "torch", "--skip", "render")


def _env(home: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env.update(HOPE_HOME=str(home), **extra)
    return env


# The command line's main, then whether the doctor's own process imported torch (it must not:
# torch's build is read in a child, so a broken torch is a fail line, not a crash).
_PROBE = ("import sys; from run_trainer import main; rc = main(sys.argv[1:]); "
          "print('torch imported:', 'torch' in sys.modules, file=sys.stderr); sys.exit(rc)")


def _doctor(env: dict[str, str], *args: str) -> tuple[int, list[dict]]:
    proc = subprocess.run([sys.executable, "-c", _PROBE, "doctor", "--json", *args],
                          capture_output=True, text=True, env=env, timeout=300, cwd=REPO, check=False)
    assert proc.returncode in (0, 1), proc.stderr
    assert "torch imported: False" in proc.stderr, proc.stderr
    return proc.returncode, json.loads(proc.stdout)


def _by_name(lines: list[dict]) -> dict[str, dict]:
    assert all(set(d) == {"check", "status", "detail", "fix"} for d in lines), lines
    return {d["check"]: d for d in lines}


def _home(tmp_path: Path, *, token_mode: int = 0o600, migrate: bool = True) -> Path:
    from registry.db import migrate as migrate_db

    home = tmp_path / "home"
    home.mkdir(mode=0o700)
    token = home / "token"
    token.write_text(TOKEN + "\n")
    token.chmod(token_mode)
    if migrate:
        migrate_db(home / "hope.db")
    return home


def _snapshot(root: Path) -> dict[str, tuple]:
    """Every path under root (root included) with its mode, size, mtime and content hash."""
    out = {}
    for p in [root, *sorted(root.rglob("*"))]:
        st = p.lstat()
        digest = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else ""
        out[str(p.relative_to(root))] = (st.st_mode, st.st_size, st.st_mtime_ns, digest)
    return out


def test_ok_path_reports_every_check(tmp_path):
    home = _home(tmp_path)
    zone = tmp_path / "temp"
    zone.write_text("45000\n")
    vcgencmd = tmp_path / "vcgencmd"
    vcgencmd.write_text("#!/bin/sh\necho throttled=0x0\n")
    vcgencmd.chmod(0o755)
    # a small budget: the memory line is ok on any test machine, not only one with 3 GB free
    rc, lines = _doctor(_env(home, HOPE_THERMAL_ZONE=str(zone), HOPE_VCGENCMD=str(vcgencmd),
                             HOPE_MEMORY_BUDGET_MB="256"))
    got = _by_name(lines)
    for name in ("architecture", "python", "torch", "page-size", "memory", "disk", "home", "token",
                 "database", "broker", "thermal-zone", "vcgencmd"):
        assert got[name]["status"] == OK, got[name]
    assert got["thermal-zone"]["detail"].startswith("45.0 C")
    assert "throttled=0x0" in got["vcgencmd"]["detail"]
    assert "job budget 256 MB" in got["memory"]["detail"]
    assert "(head)" in got["database"]["detail"]
    assert "CPU build" in got["torch"]["detail"] or "CUDA" in got["torch"]["detail"]
    sim = importlib.util.find_spec("dm_control") and importlib.util.find_spec("mujoco")
    assert got["render"]["status"] == (OK if sim else SKIP), got["render"]
    assert rc == (1 if any(d["status"] == FAIL for d in lines) else 0)
    assert not (home / "broker").exists()  # the broker's dir is made on first use, not by the doctor


def test_bad_cases_are_flagged_and_nothing_is_changed(tmp_path):
    home = _home(tmp_path, token_mode=0o644)
    home.chmod(0o755)  # too open: a service start would tighten it, the doctor only says so
    before = _snapshot(home)
    env = _env(home, HOPE_DISK_FLOOR_MB=str(10**12), HOPE_THERMAL_ZONE=str(tmp_path / "no" / "zone"))
    rc, lines = _doctor(env, *QUICK)
    got = _by_name(lines)
    assert rc == 1
    assert got["token"]["status"] == FAIL and "0644" in got["token"]["detail"]
    assert got["token"]["fix"] == f"chmod 600 {home / 'token'}"
    assert got["disk"]["status"] == FAIL and got["disk"]["fix"]
    assert got["home"]["status"] == WARN and "0755" in got["home"]["detail"]
    if not host.is_raspberry_pi():  # on a dev machine a missing zone is a warning; on a Pi a fail
        assert got["thermal-zone"]["status"] == WARN and "no temperature" in got["thermal-zone"]["detail"]
    assert got["torch"]["status"] == SKIP and got["render"]["status"] == SKIP
    assert _snapshot(home) == before  # no chmod, no migration, no WAL/-shm file, no broker dir


def test_text_report_has_the_fix_under_each_problem(tmp_path):
    home = _home(tmp_path, token_mode=0o640, migrate=False)
    proc = subprocess.run([sys.executable, str(REPO / "run_trainer.py"), "doctor", *QUICK],
                          capture_output=True, text=True, env=_env(home), timeout=120, cwd=REPO, check=False)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    at = next(i for i, line in enumerate(lines) if line.split()[:2] == ["FAIL", "token"])
    assert "fix: chmod 600" in lines[at + 1]
    assert any(line.split()[:2] == ["WARN", "database"] for line in lines)  # not made yet
    assert not (home / "hope.db").exists()
    assert lines[-1].endswith("skipped") and "1 fail" in lines[-1]


def test_a_home_that_does_not_exist_is_not_created(tmp_path):
    home = tmp_path / "absent" / "home"
    _, lines = _doctor(_env(home), *QUICK)
    got = _by_name(lines)
    assert got["home"]["status"] == WARN and got["token"]["status"] == WARN and got["database"]["status"] == WARN
    assert got["broker"]["status"] == OK and "made on first use" in got["broker"]["detail"]
    assert not (tmp_path / "absent").exists()


def test_database_behind_or_ahead_of_head(tmp_path):
    from registry.db import migrate

    settings = type("S", (), {"home": tmp_path})()
    migrate(tmp_path / "hope.db", "0002")
    behind = state.check_database(settings)
    assert behind.status == WARN and "behind head" in behind.detail and "back up hope.db" in behind.fix
    import sqlite3

    with sqlite3.connect(tmp_path / "hope.db") as con:
        con.execute("UPDATE alembic_version SET version_num = '9999'")
    con.close()
    ahead = state.check_database(settings)
    assert ahead.status == FAIL and "newer than this code" in ahead.detail


def test_database_read_while_a_writer_holds_the_wal(tmp_path):
    import sqlite3

    from registry.db import migrate

    migrate(tmp_path / "hope.db")
    writer = sqlite3.connect(tmp_path / "hope.db")  # the daemon's open connection keeps hope.db-wal
    try:
        writer.execute("PRAGMA journal_mode=WAL")
        writer.execute("CREATE TABLE IF NOT EXISTS scratch (x)")
        writer.commit()
        assert (tmp_path / "hope.db-wal").exists()
        got = state.check_database(type("S", (), {"home": tmp_path})())
        assert got.status == OK and "(head)" in got.detail, got
    finally:
        writer.close()


def test_page_size_warns_only_with_redis(monkeypatch):
    monkeypatch.setattr(os, "sysconf", lambda name: 16384)
    with_redis = host.check_page_size(type("S", (), {"redis_url": "redis://localhost:6379/0"})())
    assert with_redis.status == WARN and "jemalloc" in with_redis.detail and "embedded broker" in with_redis.fix
    assert host.check_page_size(type("S", (), {"redis_url": None})()).status == OK


def test_memory_cgroup_off_says_how_to_turn_it_on(tmp_path, monkeypatch):
    controllers = tmp_path / "cgroup.controllers"
    controllers.write_text("cpuset cpu io pids\n")
    monkeypatch.setattr(host, "CGROUP_CONTROLLERS", controllers)
    off = host.check_memory_cgroup(None)
    assert off.status == WARN and "cgroup_enable=memory" in off.fix
    controllers.write_text("cpuset cpu io memory pids\n")
    assert host.check_memory_cgroup(None).status == OK


def test_under_voltage_is_flagged():
    from hope_models.train.thermal import parse_throttled

    line = host._vcgencmd_line("vcgencmd", parse_throttled("throttled=0x50005"), WARN)
    assert line.status == WARN and "under_voltage" in line.detail and "supply" in line.fix


def test_a_check_that_raises_is_its_own_fail_line(monkeypatch):
    from hope_trainer import doctor

    def broken(_settings):
        raise RuntimeError("boom")

    monkeypatch.setattr(doctor, "all_checks", lambda: [("one", broken), ("two", lambda s: Check("two", OK, "fine"))])
    got = run_checks(object())
    assert [(c.check, c.status) for c in got] == [("one", FAIL), ("two", OK)] and "boom" in got[0].detail


def test_unknown_status_is_refused():
    with pytest.raises(ValueError):
        Check("x", "maybe", "")


def test_default_disk_floor_follows_the_largest_checkpoint(tmp_path):
    step = tmp_path / "runs" / "r1" / "checkpoints" / "5"
    step.mkdir(parents=True)
    (step / "model.safetensors").write_bytes(b"\0" * (3 * host.MB))
    settings = type("S", (), {"home": tmp_path, "disk_floor_mb": 0})()
    floor, how = host.disk_floor_mb(settings)
    assert floor == 3 * (3 + 2) + 200 and "3 MB" in how
    settings.disk_floor_mb = 50
    assert host.disk_floor_mb(settings) == (50.0, "disk_floor_mb")


def test_services_failed_and_not_installed(tmp_path, monkeypatch):
    fake = tmp_path / "systemctl"  # answers `systemctl show` as systemd does for each unit
    fake.write_text('#!/bin/sh\ncase "$3" in\n hope-daemon.service) printf "LoadState=loaded\\nActiveState=failed\\n'
                    'SubState=failed\\n";;\n hope-webapp.service) printf "LoadState=loaded\\nActiveState=active\\n'
                    'SubState=running\\n";;\n *) printf "LoadState=not-found\\nActiveState=inactive\\nSubState=dead\\n";;'
                    '\nesac\n')
    fake.chmod(0o755)
    monkeypatch.setenv("PATH", f"{tmp_path}{os.pathsep}{os.environ['PATH']}")
    monkeypatch.setattr(state, "has_systemd", lambda: True)
    got = {c.check: c for c in state.check_services(None)}
    assert got["hope-daemon"].status == FAIL and "journalctl -u hope-daemon" in got["hope-daemon"].fix
    assert got["hope-webapp"].status == OK and got["hope-worker"].status == SKIP


def test_redis_that_does_not_answer_is_a_fail():
    import socket

    with socket.socket() as s:  # a port nothing listens on once this closes
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    got = state.check_broker(type("S", (), {"home": Path("/nonexistent"), "redis_url": f"redis://:pw@127.0.0.1:{port}/0"})())
    assert got.status == FAIL and "PING" in got.detail and "pw" not in got.detail
