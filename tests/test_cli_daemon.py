"""The daemon-side CLI with real processes: enqueue/status/control with no daemon, and a real
`run_trainer.py serve` (webapp + daemon + worker child on the embedded broker, tmp $HOPE_HOME):
two enqueues trained in order and watched, pause/resume/cancel of a running job, Ctrl-C mid-run
then a restart that resumes the run from its checkpoint, and the token on the real HTTP server.
"""
from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import pytest

from daemon_fixtures import REPO, Home, Proc, home, tiny_dataset, wait_until  # noqa: F401 - fixtures

# small, fast jobs: ~60-90 steps/s for this fast_loop on one thread
JOB = ["--component", "fast_loop", "--threads", "1", "--batch-size", "8", "--warmup", "5", "--log-every", "5"]


def cli(home: Home, *args: str, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, str(REPO / "run_trainer.py"), *args], capture_output=True, text=True,
                          cwd=REPO, env=home.env, timeout=timeout)


def cli_json(home: Home, *args: str):
    proc = cli(home, *args, "--json")
    assert proc.returncode == 0, f"{args}: exit {proc.returncode}\n{proc.stderr}"
    return json.loads(proc.stdout)


class Serve:
    """A `run_trainer.py serve --port 0` process; knows its URL and token from its first line."""

    def __init__(self, home: Home, name: str = "serve"):
        self.home = home
        self.log = home.path / f"{name}.log"
        if self.log not in home.logs:
            home.logs.append(self.log)
        home.logs.append(home.path / "logs" / "worker.log")
        start = self.log.stat().st_size if self.log.exists() else 0
        self.proc = Proc(name, [sys.executable, str(REPO / "run_trainer.py"), "serve", "--port", "0"], home.env,
                         self.log)

        def banner():
            text = self.log.read_bytes()[start:].decode(errors="replace")
            if not self.proc.alive():
                pytest.fail(f"serve exited with {self.proc.popen.returncode}:\n{text}")
            return re.search(r"Robot Editor: (http://\S+)  token: (\S+)", text)

        match = wait_until(banner, 30, "serve to print its URL", home)
        self.url, self.token = match.group(1), match.group(2)

    def http(self, path: str, token: str | None = None, method: str = "GET") -> tuple[int, dict]:
        request = urllib.request.Request(self.url.rstrip("/") + path, method=method)
        if token is not None:
            request.add_header("Authorization", f"Bearer {token}")
        try:
            with urllib.request.urlopen(request, timeout=10) as response:
                return response.status, json.loads(response.read())
        except urllib.error.HTTPError as exc:
            return exc.code, json.loads(exc.read())

    def stop(self, sig: int = signal.SIGINT, timeout: float = 60) -> tuple[int, float]:
        started = time.monotonic()
        self.proc.signal(sig)
        try:
            code = self.proc.popen.wait(timeout)
        except subprocess.TimeoutExpired:
            pytest.fail(f"serve did not stop within {timeout} s after {signal.Signals(sig).name}\n"
                        + self.home.describe())
        elapsed = time.monotonic() - started
        self.proc.stop()  # closes the log; kills any leftover of its group
        return code, elapsed


@pytest.fixture
def served(tmp_path):
    """A tmp home and the serve processes a test starts, all stopped at the end."""
    home = Home(tmp_path / "home")
    started: list[Serve] = []

    def start(name: str = "serve") -> Serve:
        s = Serve(home, name)
        started.append(s)
        return s

    yield home, start
    for s in started:
        s.proc.stop()
    home.close()


# -- no daemon -----------------------------------------------------------------------------------

def test_enqueue_status_and_control_with_no_daemon(home, tiny_dataset):
    out = cli_json(home, "enqueue", *JOB, "--data", str(tiny_dataset), "--steps", "40", "--seed", "2",
                   "--checkpoint-every", "10", "--priority", "3", "--model-config", '{"d_model": 32}')
    assert set(out) == {"id", "state", "run_dir"}
    assert re.fullmatch(r"r-\d{8}-\d{6}-[0-9a-f]{6}", out["id"]) and out["state"] == "queued"
    assert out["run_dir"] == str(home.path / "runs" / out["id"])

    status = cli_json(home, "status")
    assert list(status) == ["runs"] and len(status["runs"]) == 1
    run = status["runs"][0]
    for key in ("id", "component", "state", "step", "total_steps", "pause_reason", "attempt", "queue", "priority",
                "loss", "steps_per_s", "error", "run_dir", "created_at", "config"):
        assert key in run, key
    assert (run["id"], run["component"], run["state"], run["step"], run["total_steps"], run["priority"]) == \
        (out["id"], "fast_loop", "queued", 0, 40, 3)
    assert run["config"] == {"data": str(tiny_dataset.resolve()), "steps": 40, "seed": 2, "batch_size": 8,
                             "warmup": 5, "threads": 1, "checkpoint_every_steps": 10, "log_every": 5,
                             "model_config": {"d_model": 32}}
    assert cli_json(home, "status", out["id"])["runs"][0]["id"] == out["id"]
    table = cli(home, "status")
    assert table.returncode == 0 and out["id"] in table.stdout and "queued" in table.stdout

    # control on a queued run works at once, with no daemon
    assert cli_json(home, "pause", out["id"])["run"]["state"] == "paused"
    assert "paused(user)" in cli(home, "status").stdout
    assert cli_json(home, "resume", out["id"])["run"]["state"] == "queued"
    assert cli_json(home, "cancel", out["id"])["run"]["state"] == "cancelled"
    again = cli(home, "cancel", out["id"])
    assert again.returncode == 2 and "nothing to cancel" in again.stderr
    watched = cli(home, "watch", out["id"], "--interval", "0.1")
    assert watched.returncode == 5 and "cancelled" in watched.stdout

    chain = cli_json(home, "sequential", "--components", "vqvae,fast_loop,mid_loop", "--data", str(tiny_dataset),
                     "--steps", "30", "--threads", "1")
    members = chain["runs"]
    assert [m["component"] for m in members] == ["vqvae", "fast_loop", "mid_loop"]
    rows = {r["id"]: r for r in cli_json(home, "status", "--all")["runs"]}
    assert [rows[m["id"]]["sequence_index"] for m in members] == [0, 1, 2]
    assert {rows[m["id"]]["sequence_id"] for m in members} == {chain["sequence_id"]}
    assert rows[members[2]["id"]]["config"]["vqvae_run"] == members[0]["id"]
    # a separate run may only read a vqvae run that has completed (nothing orders the two)
    mid = ["enqueue", "--component", "mid_loop", "--data", str(tiny_dataset), "--vqvae-run"]
    early = cli(home, *mid, members[0]["id"])
    assert early.returncode == 2 and "is queued, not completed" in early.stderr
    wrong = cli(home, *mid, members[1]["id"])
    assert wrong.returncode == 2 and "trains fast_loop, not vqvae" in wrong.stderr


def test_no_worker_on_the_queue_waits_visibly_cancel_ends_it_a_late_worker_refuses_it_state_is_private(
        tmp_path, tiny_dataset):
    """The real processes, started the way a user does, under a permissive umask (022) in a fresh
    HOPE_HOME: `enqueue --queue gpu` with the daemon up and no gpu worker. The run is sent (the
    embedded broker holds its message) but must read `starting`, waiting for a gpu worker, not
    `running`; `cancel` ends it at once; a gpu worker started later takes the message and does
    not train it. Then everything the product wrote under HOPE_HOME is its user's alone."""
    import os
    import sqlite3
    import stat

    from registry import runs
    from registry.db import Registry
    from hope_models.settings import load_settings

    state_dir = tmp_path / "home"  # created by the product, not by the test
    logs = tmp_path / "logs"
    logs.mkdir()
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env.update({"HOPE_HOME": str(state_dir), "PYTHONUNBUFFERED": "1", "HOPE_THERMAL_ZONE": str(tmp_path / "no-zone"),
                "HOPE_VCGENCMD": "", "HOPE_AUTO_PROMOTE": "0", "OMP_NUM_THREADS": "1"})
    user = type("U", (), {"env": env})()  # what cli() needs of a Home
    procs: list[Proc] = []
    previous = os.umask(0o022)  # a typical login umask: files 0644, directories 0755 unless the product says otherwise
    try:
        rid = cli_json(user, "enqueue", *JOB, "--data", str(tiny_dataset), "--steps", "40", "--queue", "gpu")["id"]
        procs.append(Proc("daemon", [sys.executable, str(REPO / "run_trainer.py"), "daemon", "--tick-s", "0.2"], env,
                          logs / "daemon.log"))

        def status() -> dict:
            return {r["id"]: r for r in cli_json(user, "status")["runs"]}

        def why() -> str:
            return "\n".join(p.log.read_text(errors="replace")[-3000:] for p in procs)

        deadline = time.monotonic() + 30
        while (run := status()[rid])["state"] == "queued":
            assert time.monotonic() < deadline, "the daemon did not dispatch the run\n" + why()
            time.sleep(0.3)
        assert run["state"] == "starting" and run["worker_pid"] is None, why()
        assert run["waiting"].startswith("waiting for a worker on queue 'gpu' since "), run
        # the message really was sent: the daemon commits `starting` first and sends right after,
        # so a poll may see the state a moment before the broker file exists
        wait_until(lambda: (state_dir / "broker" / "broker.sqlite").is_file(), 15, "the run's task in the broker")
        table = cli(user, "status").stdout.splitlines()
        assert [row.split()[3] for row in table if row.startswith(rid + " ")] == ["starting"]
        assert any(row.startswith(f"{rid}: waiting for a worker on queue 'gpu'") for row in table), table

        t0 = time.monotonic()
        cancelled = cli_json(user, "cancel", rid)["run"]
        assert cancelled["state"] == "cancelled" and cancelled["waiting"] is None  # at once, not "asked to"
        assert time.monotonic() - t0 < 10

        procs.append(Proc("worker-gpu", [sys.executable, str(REPO / "run_trainer.py"), "worker", "-Q", "gpu"], env,
                          logs / "worker.log", teardown_kill=True))
        registry = Registry.open(load_settings(env=env), migrate=False)
        try:
            def refused():
                with registry.session(readonly=True) as s:
                    return [e for e in runs.run_events(s, rid, kinds=["log"])
                            if "ignored a stale delivery" in e.payload["message"]]

            deadline = time.monotonic() + 60
            while not refused():
                assert time.monotonic() < deadline, "the late worker never took the old message\n" + why()
                time.sleep(0.3)
            with registry.session(readonly=True) as s:
                run = runs.get_run(s, rid)
                assert (run.state, run.worker_pid, run.step) == ("cancelled", None, 0)
                assert runs.run_events(s, rid, kinds=["progress", "checkpoint"]) == []
        finally:
            registry.close()
        assert not (state_dir / "runs" / rid / "checkpoints").exists()
        broker = sqlite3.connect(state_dir / "broker" / "broker.sqlite")
        try:
            assert broker.execute("SELECT count(*) FROM kombu_message").fetchone()[0] == 0  # taken, not left behind
        finally:
            broker.close()
    finally:
        for p in reversed(procs):
            p.kill() if p.teardown_kill else p.stop()
        os.umask(previous)

    # $HOPE_HOME and all it holds (registry, broker, their WAL files and locks) are private
    assert stat.S_IMODE(state_dir.stat().st_mode) == 0o700
    seen = []
    for root, dirs, files in os.walk(state_dir):
        for name in dirs:
            assert stat.S_IMODE((Path(root) / name).stat().st_mode) == 0o700, Path(root) / name
        for name in files:
            path = Path(root) / name
            assert stat.S_IMODE(path.lstat().st_mode) == 0o600, f"{path} is {stat.S_IMODE(path.lstat().st_mode):o}"
            seen.append(path.relative_to(state_dir).as_posix())
    assert {"hope.db", "broker/broker.sqlite"} <= set(seen), seen


@pytest.mark.parametrize("args, needle", [
    (["enqueue", *JOB, "--data", "/no/such/dataset"], "data: /no/such/dataset does not exist"),
    (["enqueue", "--component", "mid_loop", "--data", ".", "--vqvae-run", "r-nope"], "no run r-nope"),
    (["enqueue", "--component", "fast_loop", "--data", ".", "--queue", "GPU"], "queue"),
    (["sequential", "--components", "fast_loop,vqvae", "--data", "."], "vqvae must come before"),
    (["sequential", "--components", "mid_loop", "--data", "."], "needs a trained VQ-VAE"),
    (["enqueue", "--component", "mid_loop", "--data", "."], "predicts VQ-VAE codes"),
    (["status", "r-unknown"], "no run r-unknown"),
    (["watch", "r-unknown"], "no run r-unknown"),
    (["pause", "r-unknown"], "no run r-unknown"),
])
def test_cli_errors_exit_2_with_the_reason(home, args, needle):
    proc = cli(home, *args)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert needle in proc.stderr
    assert "Traceback" not in proc.stderr


def test_cli_commands_do_not_import_torch(home, tiny_dataset):
    code = ("import sys, run_trainer\n"
            f"assert run_trainer.main(['enqueue', '--component', 'vqvae', '--data', {str(tiny_dataset)!r}]) == 0\n"
            "assert run_trainer.main(['status']) == 0\n"
            "from daemon.cli import sequential  # noqa\n"
            "from hope_trainer.commands import serve, webapp  # noqa\n"
            "print('torch' in sys.modules)\n")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, env=home.env,
                          timeout=60)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip().splitlines()[-1] == "False"


def test_run_request_fields_are_trainconfig_fields():
    from dataclasses import fields

    from daemon.cli.enqueue import OVERRIDE_ARGS
    from registry.run_request import CONFIG_FIELDS
    from hope_models.train.loop import TrainConfig

    from workers.job import RUN_CONFIG_KEYS

    names = {f.name for f in fields(TrainConfig)}
    assert set(CONFIG_FIELDS) <= names
    # everything enqueue may write, the worker accepts
    assert set(CONFIG_FIELDS) | {"data", "steps", "vqvae_dir", "vqvae_run"} <= RUN_CONFIG_KEYS
    assert set(OVERRIDE_ARGS) == set(CONFIG_FIELDS)
    assert {"data", "steps", "vqvae_dir"} <= names


# -- a real serve ----------------------------------------------------------------------------------

def _workers_of(home: Home) -> list[int]:
    """Pids of Celery processes running with this test's HOPE_HOME."""
    import psutil

    pids = []
    for proc in psutil.process_iter(["pid", "cmdline"]):
        try:
            if "celery" in " ".join(proc.info["cmdline"] or []) and \
                    proc.environ().get("HOPE_HOME") == str(home.path):
                pids.append(proc.info["pid"])
        except (psutil.NoSuchProcess, psutil.AccessDenied):
            continue
    return pids


def _timeline_ok(home: Home, first: str, second: str) -> None:
    a, b = home.run(first), home.run(second)
    assert a["state"] == b["state"] == "completed", home.describe()
    # never two at once: the second started (was dispatched) after the first had finished
    dispatched_b = [e["time"] for e in home.events(second, ["state"]) if e["payload"]["state"] == "starting"]
    assert a["finished_at"] <= min(dispatched_b), home.describe()


def test_serve_trains_two_enqueues_in_order_and_cli_controls_a_running_job(served, tiny_dataset):
    home, start = served
    serve = start()

    # the token on the real server: health open, the rest refused without it
    assert serve.http("/api/health")[0] == 200
    assert serve.http("/api/runs")[0] == 401
    assert serve.http("/api/runs", token="not-the-token-at-all")[0] == 401
    assert serve.http("/api/runs", token=serve.token) == (200, {"runs": []})
    assert (home.path / "token").read_text().strip() == serve.token

    common = [*JOB, "--data", str(tiny_dataset), "--checkpoint-every", "20"]
    first = cli_json(home, "enqueue", *common, "--steps", "60")["id"]
    second = cli_json(home, "enqueue", *common, "--steps", "40")["id"]
    w1 = cli(home, "watch", first, "--interval", "0.2", timeout=120)
    assert w1.returncode == 0, w1.stdout + w1.stderr + home.describe()
    assert f"completed: {first}" in w1.stdout and "60/60" in w1.stdout
    w2 = cli(home, "watch", second, "--interval", "0.2", timeout=120)
    assert w2.returncode == 0, w2.stdout + w2.stderr + home.describe()
    status = {r["id"]: r for r in cli_json(home, "status")["runs"]}
    assert status[first]["state"] == status[second]["state"] == "completed"
    assert status[first]["step"] == 60 and status[second]["step"] == 40
    _timeline_ok(home, first, second)
    # the serve process dispatched and relayed two jobs without loading torch (only job children do)
    assert "libtorch" not in Path(f"/proc/{serve.proc.pid}/maps").read_text()
    api_runs = serve.http("/api/runs", token=serve.token)[1]["runs"]
    assert {r["id"]: r["state"] for r in api_runs} == {first: "completed", second: "completed"}

    # pause / resume / cancel of a job that is training
    long = cli_json(home, "enqueue", *common, "--steps", "5000")["id"]
    wait_until(lambda: home.run(long)["state"] == "running" and home.run(long)["step"] >= 25, 60,
               "the long run to train", home)
    assert cli_json(home, "pause", long)["run"]["desired_state"] == "pause"
    paused = wait_until(lambda: (r := home.run(long))["state"] == "paused" and r, 20, "the pause", home)
    assert paused["pause_reason"] == "user" and paused["last_checkpoint"].endswith(f"{paused['step']:08d}")
    assert cli_json(home, "resume", long)["run"]["state"] == "queued"
    wait_until(lambda: home.run(long)["state"] == "running" and home.run(long)["step"] > paused["step"], 60,
               "the resumed run to train past its pause", home)
    resumed_logs = [e["payload"]["message"] for e in home.events(long, ["log"])]
    assert any(f"resuming from step {paused['step']}" in m for m in resumed_logs), resumed_logs
    watcher = subprocess.Popen([sys.executable, str(REPO / "run_trainer.py"), "watch", long, "--interval", "0.2"],
                               stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=home.env)
    assert cli_json(home, "cancel", long)["run"]["desired_state"] == "cancel"
    out, err = watcher.communicate(timeout=60)
    assert watcher.returncode == 5, out + err + home.describe()
    cancelled = home.run(long)
    assert cancelled["state"] == "cancelled" and cancelled["step"] < 5000
    assert Path(cancelled["last_checkpoint"]).is_dir()  # cancel keeps the checkpoints

    code, elapsed = serve.stop(signal.SIGTERM)
    assert code == 0 and elapsed < 30, (code, elapsed)


def test_serve_ctrl_c_mid_run_then_restart_resumes(served, tiny_dataset):
    home, start = served
    serve = start()
    run_id = cli_json(home, "enqueue", *JOB, "--data", str(tiny_dataset), "--steps", "400",
                      "--checkpoint-every", "20")["id"]
    wait_until(lambda: home.run(run_id)["step"] >= 40, 60, "the run to train 40 steps", home)
    code, elapsed = serve.stop(signal.SIGINT)
    assert code == 0, home.describe()
    assert elapsed < 20, f"serve took {elapsed:.1f} s to stop"
    left = home.run(run_id)
    assert left["state"] == "queued" and left["attempt"] == 1, home.describe()
    assert 40 <= left["step"] < 400 and left["last_checkpoint"].endswith(f"{left['step']:08d}"), left
    assert home.states(run_id)[-1] == "queued"
    # nothing of serve is left running: its worker (its own session) went with it
    assert _workers_of(home) == []

    again = start("serve2")
    watched = cli(home, "watch", run_id, "--interval", "0.2", timeout=120)
    assert watched.returncode == 0, watched.stdout + watched.stderr + home.describe()
    done = home.run(run_id)
    assert done["state"] == "completed" and done["step"] == 400 and done["attempt"] == 1
    messages = [e["payload"]["message"] for e in home.events(run_id, ["log"])]
    assert any(f"resuming from step {left['step']}" in m for m in messages), messages
    code, _ = again.stop(signal.SIGINT)
    assert code == 0


def test_serve_refuses_a_taken_port_with_a_clear_error(home):
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        proc = cli(home, "serve", "--port", str(port))
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert f"cannot listen on 127.0.0.1:{port}" in proc.stderr and "--port" in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (home.path / "logs" / "worker.log").exists()  # nothing was started
