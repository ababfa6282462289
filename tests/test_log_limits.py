"""Logs that cannot fill the SD card (hope_models/log_limits.py, webapp/socket_packets.py):

- a client's malformed Socket.IO / Engine.IO input is one WARNING line naming it, never a
  traceback, and a flood of them is folded into a count, in the file `serve` writes;
- a bug in our own code still logs its traceback;
- log files are rotated and capped at (log_backups + 1) * log_max_mb: what a process logs, what a
  child appends, what serve's worker child prints.
"""
from __future__ import annotations

import logging
import os
import re
import subprocess
import sys
import time
import types
from pathlib import Path

import pytest

from hostile_clients import LOG_FLOOD_BODIES, log_flood, wait_until
from test_server_hardening import Served

MB = 1024 * 1024


@pytest.fixture
def serve_logging(tmp_path):
    """serve's own logging (setup_logging: daemon.log, the rate limit), undone afterwards."""
    from hope_trainer.commands.serve import setup_logging

    root = logging.getLogger()
    before, level = list(root.handlers), root.level
    setup_logging(tmp_path / "logs-home", console_level=logging.CRITICAL)
    yield tmp_path / "logs-home" / "logs" / "daemon.log"
    for handler in root.handlers[:]:
        if handler not in before:
            root.removeHandler(handler)
            handler.close()
    root.setLevel(level)


def _settled(path, quiet_s: float = 0.5, timeout: float = 15.0) -> str:
    """The file's text once nothing was added for `quiet_s` (Socket.IO handlers run on their own threads)."""
    last, since, deadline = -1, time.monotonic(), time.monotonic() + timeout
    while time.monotonic() < deadline:
        size = path.stat().st_size if path.exists() else 0
        if size != last:
            last, since = size, time.monotonic()
        elif time.monotonic() - since >= quiet_s:
            break
        time.sleep(0.1)
    return path.read_text(encoding="utf-8", errors="replace") if path.exists() else ""


def test_a_flood_of_malformed_packets_is_a_few_warning_lines_with_a_count(tmp_path, serve_logging):
    from hope_models.log_limits import rate_limit

    s = Served(tmp_path / "s")
    try:
        s.guard._rate = s.guard._burst = 1000.0  # this test is about the log, not the session rate limit
        s.server.strikes.to_ban = 0  # nor the ban an address earns by its bad packets (test_strikes.py)
        statuses = log_flood(s.port, packets=500)
        assert sum(n for st, n in statuses.items() if st in (200, 400)) >= 450, statuses
        flood_text = _settled(serve_logging)
        limiter = rate_limit()
        real_clock = limiter.clock
        limiter.clock = lambda: real_clock() + 3600.0  # an hour later: the same lines come again
        try:
            log_flood(s.port, packets=2 * len(LOG_FLOOD_BODIES))
            text = _settled(serve_logging)
        finally:
            limiter.clock = real_clock
    finally:
        s.close()
    assert "Traceback" not in text
    flood_lines = [line for line in flood_text.splitlines() if "from 127.0.0.1" in line]
    assert flood_lines and all(" WARNING " in line for line in flood_lines), flood_text[-2000:]
    assert re.search(r"bad Engine\.IO POST from 127\.0\.0\.1:\d+ \(session \S+\): ValueError", text)
    assert re.search(r"Socket\.IO session \S+ from 127\.0\.0\.1:\d+ closed: it sent a malformed Socket\.IO packet",
                     text)
    counts = [int(n) for n in re.findall(r"\(and (\d+) more like it in the last 60 s\)", text)]
    assert counts and sum(counts) >= 200, text[-3000:]  # of ~300 lines, at most 10 a minute of each kind
    assert len(text.encode()) < 20_000, f"{len(text.encode())} bytes of log for 500 bad packets"


def test_a_real_serve_writes_a_few_lines_for_a_flood_of_bad_packets(tmp_path):
    """The files are the point: `serve`'s daemon.log and its terminal (the journal under systemd)."""
    from daemon_fixtures import REPO, Home, Proc

    home = Home(tmp_path / "home", extra_env={"HOPE_STRIKES_TO_BAN": "0"})  # every packet reaches the app
    out = home.path / "serve.out"
    proc = Proc("serve", [sys.executable, str(REPO / "run_trainer.py"), "serve", "--port", "0", "--no-worker"],
                home.env, out)
    try:
        found = wait_until(lambda: re.search(r"Robot Editor: http://127\.0\.0\.1:(\d+)/",
                                             out.read_text(errors="replace")), 60)
        assert found, out.read_text(errors="replace")
        daemon_log = home.path / "logs" / "daemon.log"
        start = (len(out.read_bytes()), daemon_log.stat().st_size)
        statuses = log_flood(int(found.group(1)), packets=500)
        assert sum(n for st, n in statuses.items() if st in (200, 400)) >= 250, statuses  # past the session limits
        _settled(daemon_log)
    finally:
        proc.stop()
        home.close()
    written = {"terminal": out.read_bytes()[start[0]:], "daemon.log": daemon_log.read_bytes()[start[1]:]}
    for name, text in written.items():
        assert b"Traceback" not in text, (name, text[-3000:])
        assert b" WARNING " in text, (name, text[-3000:])
        assert len(text) < 20_000, f"{name}: {len(text)} bytes for 500 bad packets"


def test_a_bug_in_our_own_code_still_logs_its_traceback(tmp_path, caplog):
    from hostile_clients import SocketIOClient

    s = Served(tmp_path / "s")
    try:
        def connect_with_a_bug(*_args):
            raise RuntimeError("a bug of ours")

        s.socketio.server._handle_connect = connect_with_a_bug  # what a valid CONNECT packet runs
        with caplog.at_level(logging.ERROR, logger="engineio.server"):
            client = SocketIOClient(s.port, s.token, timeout=3.0)
            assert wait_until(lambda: any(r.exc_info for r in caplog.records), timeout=10)
        client.close()
    finally:
        s.close()
    bug = next(r for r in caplog.records if r.exc_info)
    assert bug.levelno == logging.ERROR and "a bug of ours" in str(bug.exc_info[1])


def _sizes(directory, name):
    return {p.name: p.stat().st_size for p in directory.iterdir() if p.name.startswith(name)}


def test_rotation_caps_what_a_process_logs_and_what_a_child_writes(tmp_path):
    from hope_models.log_limits import PipeToLog, RateLimitFilter, rotate_if_over, rotating_file_handler

    settings = types.SimpleNamespace(log_max_mb=1, log_backups=2)
    cap = (settings.log_backups + 1) * settings.log_max_mb * MB
    logs = tmp_path / "logs"

    handler = rotating_file_handler(logs / "daemon.log", settings)
    handler.filters = [RateLimitFilter(burst=10**9)]  # every line distinct and wanted: rotation alone caps it
    logger = logging.getLogger("hope.test.rotation")
    logger.propagate, logger.level = False, logging.INFO
    logger.addHandler(handler)
    try:
        for i in range(50_000):  # ~5 MB
            logger.info("line %06d %s", i, "x" * 60)
    finally:
        logger.removeHandler(handler)
        handler.close()
    sizes = _sizes(logs, "daemon.log")
    assert set(sizes) == {"daemon.log", "daemon.log.1", "daemon.log.2"}, sizes
    assert sum(sizes.values()) <= cap
    assert "line 049999" in (logs / "daemon.log").read_text()

    # serve's worker: its whole output through a pipe, rotated the same way
    child = subprocess.Popen([sys.executable, "-c", "import sys\nfor i in range(60000): print('%06d' % i, 'y' * 80)"],
                             stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
    copier = PipeToLog(logs / "worker.log", settings).start(child.stdout)
    assert child.wait(60) == 0
    copier.join(30)
    sizes = _sizes(logs, "worker.log")
    assert set(sizes) == {"worker.log", "worker.log.1", "worker.log.2"}, sizes
    assert sum(sizes.values()) <= cap
    assert (logs / "worker.log").read_text().rstrip().endswith("059999 " + "y" * 80)

    # a file a child appends to (promote.log): rotated before the next child opens it
    promote = logs / "promote.log"
    for _ in range(6):
        rotate_if_over(promote, settings)
        with open(promote, "ab") as f:
            f.write(b"z" * (MB // 2 + 1))
    sizes = _sizes(logs, "promote.log")
    assert set(sizes) == {"promote.log", "promote.log.1", "promote.log.2"}, sizes
    assert sum(sizes.values()) <= cap + 2 * MB  # a child writes past the cap until the next rotation


def test_log_size_settings_come_from_the_environment(tmp_path):
    from hope_models.log_limits import limits_of
    from hope_models.settings import SettingsError, load_settings

    settings = load_settings(env={"HOPE_HOME": str(tmp_path), "HOPE_LOG_MAX_MB": "2", "HOPE_LOG_BACKUPS": "5"})
    assert limits_of(settings) == (2 * MB, 5)
    assert limits_of(load_settings(env={"HOPE_HOME": str(tmp_path)})) == (10 * MB, 3)
    with pytest.raises(SettingsError, match="log_max_mb"):
        load_settings(env={"HOPE_HOME": str(tmp_path), "HOPE_LOG_MAX_MB": "0"})


def test_the_rate_limit_counts_per_template_and_reports_the_count_once():
    from hope_models.log_limits import RateLimitFilter

    now = [0.0]
    limit = RateLimitFilter(window_s=60, burst=3, clock=lambda: now[0])

    def record(msg, *args):
        return logging.LogRecord("hope.test", logging.WARNING, __file__, 1, msg, args, None)

    passed = [limit.filter(record("client %s refused", i)) for i in range(100)]
    assert passed.count(True) == 3
    assert limit.filter(record("another line"))  # another template has its own count
    again = record("client %s refused", 1000)
    # the terminal's handler and the file's see one verdict, and the record is counted once
    assert limit.filter(again) is False and limit.filter(again) is False
    now[0] = 61.0
    later = record("client %s refused", 1001)
    assert limit.filter(later)
    assert later.getMessage() == "client 1001 refused (and 98 more like it in the last 60 s)"


JOURNAL_CHILD = """
import logging, sys, time
sys.path.insert(0, sys.argv[1])
from hope_models.log_format import configure_logging
from hope_models.log_limits import rate_limit
configure_logging(logging.INFO)
log = logging.getLogger("hope.test")
for i in range(200):
    log.warning("client %d refused", i)
rate_limit().clock = lambda: time.monotonic() + 61.0  # a minute later
log.warning("client %d refused", 200)
"""


def test_the_journal_gets_the_same_rate_limit_with_its_priorities(tmp_path):
    """configure_logging (the daemon, the webapp, the Celery worker under systemd): stderr is the
    journal when JOURNAL_STREAM names it, faked here with a file as tests/test_log_format.py does."""
    err = tmp_path / "stderr.txt"
    err.touch()
    st = err.stat()
    env = {**os.environ, "JOURNAL_STREAM": f"{st.st_dev}:{st.st_ino}"}
    repo = str(Path(__file__).resolve().parents[1])
    with open(err, "ab") as out:
        subprocess.run([sys.executable, "-c", JOURNAL_CHILD, repo], stderr=out, env=env, timeout=60, check=True)
    lines = err.read_text().splitlines()
    assert lines[:10] == [f"<4>hope.test: client {i} refused" for i in range(10)], lines
    assert lines[10:] == ["<4>hope.test: client 200 refused (and 190 more like it in the last 60 s)"], lines
