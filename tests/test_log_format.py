"""hope_models/log_format.py: journald-native lines when stderr is the journal, the plain format
otherwise; the daemon, the webapp and the Celery worker all log through it.

"The journal" is faked the way systemd tells a process it is there: JOURNAL_STREAM holds the
device and inode of its stderr. Here stderr is a temp file and JOURNAL_STREAM names that file."""
from __future__ import annotations

import logging
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

from hope_models.log_format import JournalFormatter, stderr_is_journal, syslog_priority

REPO = Path(__file__).resolve().parents[1]
TIMESTAMP = re.compile(r"\d\d:\d\d:\d\d")
PRIORITY = re.compile(r"^<[0-7]>")

CHILD = """
import logging, sys
sys.path.insert(0, sys.argv[1])
from hope_models.log_format import configure_logging
configure_logging(logging.DEBUG)
log = logging.getLogger("hope.test")
log.debug("d"); log.info("i"); log.warning("w")
try:
    1 / 0
except ZeroDivisionError:
    log.exception("boom")
"""


def journal_env(path: Path, base: dict | None = None) -> dict:
    st = path.stat()
    env = dict(os.environ if base is None else base)
    env["JOURNAL_STREAM"] = f"{st.st_dev}:{st.st_ino}"
    return env


def run_child(tmp_path: Path, journal: str | None) -> list[str]:
    """CHILD with its stderr a file; journal: None (no JOURNAL_STREAM), "match" (the file's own
    dev:ino, as under systemd) or "other" (inherited from a parent whose stderr was the journal)."""
    err = tmp_path / "stderr.txt"
    err.touch()
    env = dict(os.environ)
    env.pop("JOURNAL_STREAM", None)
    if journal == "match":
        env = journal_env(err, env)
    elif journal == "other":
        env = journal_env(tmp_path, env)  # a real dev:ino, just not stderr's
    with open(err, "ab") as out:
        subprocess.run([sys.executable, "-c", CHILD, str(REPO)], stderr=out, env=env, timeout=60, check=True)
    return err.read_text().splitlines()


def test_journal_lines_carry_the_priority_and_no_timestamp(tmp_path):
    lines = run_child(tmp_path, "match")
    assert lines[:4] == ["<7>hope.test: d", "<6>hope.test: i", "<4>hope.test: w", "<3>hope.test: boom"], lines
    # journald makes one entry per line: every line of the traceback is an error too
    assert len(lines) > 5 and all(line.startswith("<3>") for line in lines[3:]), lines
    assert lines[-1] == "<3>ZeroDivisionError: division by zero"
    assert not any(TIMESTAMP.search(line) for line in lines), lines


def test_plain_lines_elsewhere(tmp_path):
    for journal in (None, "other"):
        (tmp_path / str(journal)).mkdir()
        lines = run_child(tmp_path / str(journal), journal)
        assert re.fullmatch(r"\d{4}-\d\d-\d\d \d\d:\d\d:\d\d,\d{3} INFO hope\.test: i", lines[1]), (journal, lines)
        assert re.fullmatch(r".* ERROR hope\.test: boom", lines[3]), (journal, lines)
        assert not any(PRIORITY.match(line) for line in lines), (journal, lines)


def test_detection_and_priorities(tmp_path):
    f = tmp_path / "err"
    f.touch()
    with open(f, "w") as stream:
        assert stderr_is_journal(stream, journal_env(f, {}))
        assert not stderr_is_journal(stream, journal_env(tmp_path, {}))
        assert not stderr_is_journal(stream, {})
        for bad in ("", "12", "a:b", ":", "1:2:3"):
            assert not stderr_is_journal(stream, {"JOURNAL_STREAM": bad}), bad
    assert not stderr_is_journal(object(), journal_env(f, {}))  # no fileno(): a test's capture
    assert [syslog_priority(n) for n in (50, 40, 30, 20, 10, 5)] == [2, 3, 4, 6, 7, 7]
    record = logging.LogRecord("x", logging.WARNING, __file__, 1, "a\nb", None, None)
    assert JournalFormatter().format(record) == "<4>x: a\n<4>b"


def test_config_error_is_an_error_on_the_journal(tmp_path):
    """Exit 2 (RestartPreventExitStatus=2) of each unit's command: its one line must be what
    `journalctl -p err` shows."""
    home = tmp_path / "home"
    home.mkdir(mode=0o700)
    (home / "config.toml").write_text("this is not toml =\n")
    err = tmp_path / "stderr.txt"
    for command, journal in [(c, j) for c in ("daemon", "webapp", "worker") for j in (True, False)]:
        err.write_text("")
        env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_") and k != "JOURNAL_STREAM"}
        env["HOPE_HOME"] = str(home)
        env = journal_env(err, env) if journal else env
        with open(err, "ab") as out:
            code = subprocess.run([sys.executable, str(REPO / "run_trainer.py"), command], stderr=out, env=env,
                                  stdout=subprocess.DEVNULL, timeout=120).returncode
        text = err.read_text()
        assert code == 2, (command, text)
        assert text.startswith("<3>error: " if journal else "error: "), (command, journal, text)


def test_celery_worker_logs_in_the_journal_format(tmp_path):
    """Celery's own lines (its "ready.") through our handler: a priority, not Celery's timestamped format."""
    from workers.cli import worker_command

    home = tmp_path / "home"
    home.mkdir(mode=0o700)
    err = tmp_path / "stderr.txt"
    err.touch()
    # no HOPE_REDIS_URL: the embedded broker under HOPE_HOME
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env["HOPE_HOME"] = str(home)
    env = journal_env(err, env)
    with open(err, "ab") as out:
        proc = subprocess.Popen(worker_command(None, "logtest"), stdout=subprocess.DEVNULL, stderr=out, env=env,
                                cwd=tmp_path, start_new_session=True)
    try:
        deadline = time.monotonic() + 90
        while "ready." not in err.read_text(errors="replace") and time.monotonic() < deadline:
            assert proc.poll() is None, err.read_text(errors="replace")
            time.sleep(0.2)
        lines = [line for line in err.read_text(errors="replace").splitlines() if line.strip()]
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    ready = [line for line in lines if line.endswith("ready.")]
    assert ready and ready[0].startswith("<6>"), lines
    assert not any(re.match(r"\[\d{4}-", line) for line in lines), lines  # Celery's own "[date: LEVEL/...]"
