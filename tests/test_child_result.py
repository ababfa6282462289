"""A child's result is the file it writes to its --result-file, never a line of its stdout.

Each parent (the sequential trainer, the daemon's auto-promoter, the webapp's ChildProcesses, the
demo) runs a fake `hope-trainer` child that prints JSON-looking lines on stdout before and after
writing its result (or prints nothing), or dies before writing it: the parent gets exactly the
written object, or an error naming the child's command and its exit code.
"""
from __future__ import annotations

import argparse
import json
import os
import stat
import sys
from pathlib import Path

import pytest

from hope_models.child_result import (
    MAX_RESULT_BYTES,
    ChildResultError,
    add_result_argument,
    read_result,
    result_argv,
    write_result,
)

REPO = Path(__file__).resolve().parents[1]
RESULT = {"ok": True, "outcome": "completed", "promoted": True, "component": "c", "version": "v1",
          "model_id": 7, "steps": 3, "answer": 42}

# A stand-in for `python -m hope_trainer <verb> ... --result-file PATH`: it takes whatever argv it is
# given and behaves as FAKE_CHILD_MODE says.
FAKE_CHILD = f"""#!{sys.executable}
import json, os, sys
sys.path.insert(0, {str(REPO)!r})
from hope_models.child_result import write_result

args = sys.argv[1:]
path = args[args.index("--result-file") + 1] if "--result-file" in args else None  # None: writes nothing
mode = os.environ["FAKE_CHILD_MODE"]
if mode != "silent":
    print('{{"ok": false, "error": "a decoy before", "outcome": "failed", "promoted": false}}', flush=True)
    print('{{"frame": {{"step": 1}}}}', flush=True)
if mode == "dies":
    print('{{"ok": true, "outcome": "completed", "promoted": true, "looks": "like a result"}}', flush=True)
    os._exit(7)
write_result(path, json.loads({json.dumps(RESULT)!r}))
if mode != "silent":
    print('{{"ok": false, "error": "a decoy after", "outcome": "failed", "promoted": false}}', flush=True)
sys.exit(0)
"""


@pytest.fixture
def fake_child(tmp_path) -> Path:
    path = tmp_path / "fake-hope-trainer"
    path.write_text(FAKE_CHILD)
    path.chmod(path.stat().st_mode | stat.S_IXUSR)
    return path


# -- the module itself -------------------------------------------------------------------------------

def test_written_result_reads_back_and_its_absence_names_the_command(tmp_path):
    parser = argparse.ArgumentParser()
    add_result_argument(parser)
    args = parser.parse_args(result_argv(tmp_path / "r.json"))
    write_result(args.result_file, {"a": 1, "nan": float("nan")})
    got = read_result(tmp_path / "r.json", ["py", "-m", "hope_trainer", "promote", "r1", "--json"], 0)
    assert got["a"] == 1 and got["nan"] != got["nan"]
    argv = ["py", "-m", "hope_trainer", "promote", "r1", "--json", *result_argv(tmp_path / "none.json")]
    with pytest.raises(ChildResultError, match=r"`hope-trainer promote r1 --json` exited with code 3 without a result"):
        read_result(tmp_path / "none.json", argv, 3)
    (tmp_path / "list.json").write_text("[1]")
    with pytest.raises(ChildResultError, match="not an object"):
        read_result(tmp_path / "list.json", argv, 0)
    (tmp_path / "big.json").write_text(json.dumps({"x": "y" * MAX_RESULT_BYTES}))
    with pytest.raises(ChildResultError, match="larger than"):
        read_result(tmp_path / "big.json", argv, 0)
    (tmp_path / "cut.json").write_text('{"x": ')
    with pytest.raises(ChildResultError, match="killed by signal 9.*not JSON"):
        read_result(tmp_path / "cut.json", argv, -9)


# -- the sequential trainer ----------------------------------------------------------------------------

@pytest.mark.parametrize("mode", ["decoys", "silent"])
def test_sequential_child_reports_exactly_its_file(fake_child, monkeypatch, mode):
    from hope_models.train import sequential

    monkeypatch.setenv("FAKE_CHILD_MODE", mode)
    child = sequential.run_child([str(fake_child), "train", "--component", "x", "--json"])
    assert child["exit_code"] == 0 and child["result"] == RESULT and child["result_error"] is None


def test_sequential_child_that_dies_before_writing(fake_child, monkeypatch, tmp_path, capsys):
    from hope_models.train import sequential

    monkeypatch.setenv("FAKE_CHILD_MODE", "dies")
    monkeypatch.setattr(sequential, "child_command",
                        lambda args, name, run_dir, vqvae: [str(fake_child), "train", "--component", name, "--json"])
    (tmp_path / "ds").mkdir()
    args = argparse.Namespace(sequential="vqvae", data=str(tmp_path / "ds"), run_dir=str(tmp_path / "run"),
                              vqvae=None, json=True)
    assert sequential.run_sequential(args) == 7
    rows = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert rows[0]["exit_code"] == 7 and rows[0]["outcome"] == "failed", rows
    assert f"`{fake_child} train --component vqvae --json` exited with code 7 without a result" in rows[0]["message"]


# -- the webapp's children ------------------------------------------------------------------------------

@pytest.mark.parametrize("mode", ["decoys", "silent"])
def test_webapp_child_output_is_its_file(fake_child, monkeypatch, tmp_path, mode):
    from webapp import commands

    monkeypatch.setenv("FAKE_CHILD_MODE", mode)
    monkeypatch.setattr(commands, "trainer_argv", lambda *args: [str(fake_child), *args])
    seen: list[str] = []
    children = commands.ChildProcesses(argparse.Namespace(home=tmp_path / "home"))
    res = children.run(["promote", "r1", "--json"], timeout_s=60, on_line=lambda line: seen.append(line) or False)
    assert res.code == 0 and res.output == RESULT and res.result_error is None
    assert len(seen) == (0 if mode == "silent" else 3)  # the consumer still sees every stdout line


def test_webapp_child_that_dies_before_writing(fake_child, monkeypatch, tmp_path):
    from webapp import commands

    monkeypatch.setenv("FAKE_CHILD_MODE", "dies")
    monkeypatch.setattr(commands, "trainer_argv", lambda *args: [str(fake_child), *args])
    res = commands.ChildProcesses(argparse.Namespace(home=tmp_path / "home")).run(["promote", "r1", "--json"],
                                                                                  timeout_s=60)
    assert res.code == 7 and res.output is None
    assert f"`{fake_child} promote r1 --json` exited with code 7 without a result" in res.error()


# -- the daemon's auto-promoter -----------------------------------------------------------------------------

def _promoter(tmp_path, fake_child):
    from datetime import timedelta

    from daemon.autopromote import AutoPromoter
    from hope_models.settings import load_settings
    from registry import runs
    from registry.db import Registry
    from registry.models import utcnow

    st = load_settings(tmp_path / "home", env={"HOPE_AUTO_PROMOTE": "1"})
    registry = Registry.open(st)
    with registry.session() as s:
        run = runs.create_run(s, component="fast_loop", config={"data": "x"}, total_steps=10,
                              run_dir=str(tmp_path / "run"))
        for state in ("starting", "running", "completed"):
            runs.transition(s, run, state, **({"reason": "trainer"} if state == "completed" else {}))
        run_id = run.id
    promoter = AutoPromoter(st, registry, python=str(fake_child), clock=lambda: utcnow() - timedelta(hours=1))
    return st, registry, promoter, run_id


def _gate(promoter, run_id) -> dict:
    import time

    promoter.tick()
    assert promoter.current_run == run_id
    deadline = time.monotonic() + 60
    while (promoter.last_outcome or {}).get("run_id") != run_id:
        assert time.monotonic() < deadline, "the fake promote child did not finish"
        time.sleep(0.05)
        promoter.tick()
    return promoter.last_outcome


@pytest.mark.parametrize("mode", ["decoys", "silent"])
def test_auto_promoter_reads_the_result_file(fake_child, monkeypatch, tmp_path, mode):
    monkeypatch.setenv("FAKE_CHILD_MODE", mode)
    st, registry, promoter, run_id = _promoter(tmp_path, fake_child)
    try:
        outcome = _gate(promoter, run_id)
        assert outcome == {"run_id": run_id, "exit_code": 0, **RESULT}
        assert f"run {run_id}: auto-promote: promoted c v1 (model 7)" in (st.home / "logs" / "promote.log").read_text()
        assert not list((st.home / "logs").glob(".promote-*"))
    finally:
        registry.close()


def test_auto_promoter_child_that_dies_before_writing(fake_child, monkeypatch, tmp_path):
    from registry import runs

    monkeypatch.setenv("FAKE_CHILD_MODE", "dies")
    st, registry, promoter, run_id = _promoter(tmp_path, fake_child)
    try:
        outcome = _gate(promoter, run_id)
        assert outcome == {"run_id": run_id, "exit_code": 7}
        with registry.session(readonly=True) as s:
            messages = [e.payload["message"] for e in runs.run_events(s, run_id, kinds=["log"])]
        assert any(f"`hope-trainer promote {run_id} --auto --json` exited with code 7 without a result" in m
                   for m in messages), messages
    finally:
        registry.close()


# -- the demo ---------------------------------------------------------------------------------------------

def _demo(tmp_path, fake_child, monkeypatch):
    from hope_trainer.demo import children, session

    monkeypatch.setattr(children, "trainer_argv", lambda *args: [str(fake_child), *args])
    settings = argparse.Namespace(home=tmp_path / "home")
    return session.Demo(settings, argparse.Namespace())


@pytest.mark.parametrize("mode", ["decoys", "silent"])
def test_demo_child_result_is_its_file(fake_child, monkeypatch, tmp_path, mode):
    monkeypatch.setenv("FAKE_CHILD_MODE", mode)
    code, result, _tail = _demo(tmp_path, fake_child, monkeypatch).run_child(["sim-demos", "--json"], timeout_s=60)
    assert code == 0 and result == RESULT


def test_demo_child_that_dies_before_writing(fake_child, monkeypatch, tmp_path):
    monkeypatch.setenv("FAKE_CHILD_MODE", "dies")
    demo = _demo(tmp_path, fake_child, monkeypatch)
    with pytest.raises(ChildResultError, match=r"sim-demos --json` exited with code 7 without a result"):
        demo.run_child(["sim-demos", "--json"], timeout_s=60)
    demo.args = argparse.Namespace(eval_episodes=1)  # evaluate: the same error becomes the summary's reflex error
    error = demo.evaluate()["error"]
    assert "eval-reflex --checkpoint promoted" in error and "exited with code 7 without a result" in error


# -- the real commands write it ------------------------------------------------------------------------------

@pytest.mark.parametrize("argv", [
    ["promote", "--json"],  # neither RUN nor --checkpoint: a usage error, before any registry
    ["eval-reflex", "--checkpoint", "promoted", "--json"],  # nothing promoted in an empty home
    ["sim-demos", "--episodes", "1", "--out", "OUT", "--policy", "play", "--noise", "1", "--json"],
])
def test_commands_write_their_result_file_and_still_print_json(tmp_path, argv):
    import subprocess

    from hope_models.child_command import trainer_argv

    path = tmp_path / "result.json"
    argv = [str(tmp_path / "out") if a == "OUT" else a for a in argv]
    proc = subprocess.run(trainer_argv(*argv, *result_argv(path)), capture_output=True, text=True, timeout=120,
                          env={**os.environ, "HOPE_HOME": str(tmp_path / "home")}, cwd=tmp_path)
    assert proc.returncode == 2, proc.stderr
    result = read_result(path, proc.args, proc.returncode)
    assert result.get("error") and result.get("ok", result.get("promoted")) is False
    assert json.loads(proc.stdout.strip().splitlines()[-1]) == result  # --json is unchanged for people


def test_restart_backoff_grows_with_quick_deaths_and_resets_after_a_stable_run():
    import time

    from hope_models.child_command import RestartBackoff

    backoff = RestartBackoff((1.0, 2.0, 5.0), stable_s=60.0)
    now = time.monotonic()
    assert [backoff.after_exit(now) for _ in range(4)] == [2.0, 5.0, 5.0, 5.0]  # quick deaths climb, then stay
    assert backoff.after_exit(now - 61.0) == 1.0  # it had stayed up: from the first again
    assert backoff.after_failed_start() == 2.0 and backoff.failures == 1
