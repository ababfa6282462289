"""The long-poll flood against the webapp's server: does the robot's inference keep answering?

    python bench/longpoll_attack.py                       # this checkout's `serve`, then gunicorn gthread
    python bench/longpoll_attack.py --repo /tmp/old-checkout    # another tree's webapp (git archive REV)
    python bench/longpoll_attack.py --server gunicorn     # needs gunicorn importable (PYTHONPATH)

The attacker (tests/hostile_clients.py LongPollFlood, no token, from 127.0.0.2): one Engine.IO
polling handshake, then 200 concurrent long-poll GETs on its session id, each re-sent as it
returns, a new handshake every 8 s. Meanwhile a probe from 127.0.0.1 asks every 0.25 s for
/api/ping on the editor's port, and POST /api/brain/infer on the inference port (the editor's port
when the server has no inference port). It prints, per server, how many probes got 200, the worst
probe time, and the server's threads a few seconds after the attacker left, then one JSON line.

Servers: `werkzeug`: `run_trainer.py serve --no-worker` of --repo (Werkzeug's threaded server
with webapp/server.py's guards). `gunicorn`: the same Flask app (create_app, the same Socket.IO
guard, BrainService) under gunicorn's gthread worker, one worker (Socket.IO's polling sessions live
in one process) with --threads 200 (the webapp's connection cap), its default timeouts, and a
second bind standing for the inference port (gunicorn has one thread pool per worker).
Both serve a fast_loop trained for 40 steps on a synthetic dataset and promoted first.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO / "tests"))
# the tree under test first (gunicorn's worker imports the webapp of --repo through this)
sys.path.insert(0, os.environ.get("HOPE_BENCH_REPO") or str(REPO))

from hostile_clients import LongPollFlood, http_request, process_counts  # noqa: E402

OBS_DIM, ACT_DIM = 6, 2


def gunicorn_app():
    """gunicorn's app factory: what `run_trainer.py webapp` builds, without its HttpServer."""
    from hope_models.runtime.brain_service import BrainService
    from hope_models.settings import load_settings
    from webapp import create_app
    from webapp.auth import load_or_create_token

    settings = load_settings()
    brain = BrainService(settings.home)
    brain.start()
    app, _ = create_app(settings, token=load_or_create_token(settings), brain=brain)
    return app


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def prepare(home: Path, env: dict) -> None:
    from hope_models.data.synthetic import generate_dataset

    data = home / "datasets" / "bench"
    generate_dataset(data, 1500, obs_dim=OBS_DIM, act_dim=ACT_DIM, episode_seconds=(5, 10), seed=3)
    py = [sys.executable, str(REPO / "run_trainer.py")]
    for argv in (["train", "--component", "fast_loop", "--data", str(data), "--run-dir", str(home / "runs" / "seed"),
                  "--steps", "40", "--warmup", "4"], ["promote", "--checkpoint", str(home / "runs" / "seed"), "--force"]):
        done = subprocess.run(py + argv, cwd=REPO, env=env, capture_output=True, text=True)
        if done.returncode != 0:
            sys.exit(f"bench: {' '.join(argv[:2])} failed:\n{done.stderr[-2000:]}")


def start_werkzeug(repo: Path, home: Path, env: dict) -> tuple[subprocess.Popen, int, int, int]:
    log = home / "serve.log"
    proc = subprocess.Popen([sys.executable, str(repo / "run_trainer.py"), "serve", "--port", "0", "--no-worker"],
                            cwd=repo, env=env, stdout=open(log, "w"), stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:
        text = log.read_text(errors="replace")
        editor = re.search(r"Robot Editor: http://[^:]+:(\d+)/", text)
        if editor and ("inference:" in text or "brain:" in text):
            door = re.search(r"inference: http://[^:]+:(\d+)/", text)
            return proc, int(editor.group(1)), int(door.group(1)) if door else int(editor.group(1)), proc.pid
        time.sleep(0.2)
    sys.exit(f"bench: serve did not start:\n{log.read_text(errors='replace')[-3000:]}")


def _worker_pid(master: int) -> int:
    """gunicorn's worker (where the threads are), the master's one child."""
    children = Path(f"/proc/{master}/task/{master}/children").read_text().split()
    return int(children[0]) if children else master


def start_gunicorn(repo: Path, home: Path, env: dict) -> tuple[subprocess.Popen, int, int, int]:
    editor, door = _free_port(), _free_port()
    log = home / "gunicorn.log"
    proc = subprocess.Popen([sys.executable, "-m", "gunicorn", "-k", "gthread", "-w", "1", "--threads", "200",
                             "-b", f"127.0.0.1:{editor}", "-b", f"127.0.0.1:{door}", "longpoll_attack:gunicorn_app()"],
                            cwd=REPO / "bench", env={**env, "HOPE_BENCH_REPO": str(repo), "PYTHONPATH": os.pathsep.join(
                                [str(REPO / "bench"), str(repo), env.get("PYTHONPATH", "")])},
                            stdout=open(log, "w"), stderr=subprocess.STDOUT)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and proc.poll() is None:
        try:
            if http_request(editor, "GET", "/api/ping", timeout=2)[0] == 200:
                return proc, editor, door, _worker_pid(proc.pid)
        except OSError:
            pass  # not listening yet
        time.sleep(0.3)
    sys.exit(f"bench: gunicorn did not start:\n{log.read_text(errors='replace')[-3000:]}")


def attack(name: str, pid: int, editor: int, door: int, token: str, seconds: float) -> dict:
    auth = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
    body = json.dumps({"component": "fast_loop", "observation": [0.1] * OBS_DIM}).encode()
    if http_request(door, "POST", "/api/brain/infer", body=body, headers=auth, timeout=10)[0] != 200:
        sys.exit(f"bench: {name}: inference does not answer before the attack")
    quiet = process_counts(pid)
    flood = LongPollFlood(editor, concurrency=200, refresh_s=8.0, source="127.0.0.2").start()
    probes = {"editor ping": [], "infer": []}
    worst = {"editor ping": 0.0, "infer": 0.0}
    peak = quiet[0]
    end = time.monotonic() + seconds
    try:
        while time.monotonic() < end:
            for key, port, method, path, data, headers in (("editor ping", editor, "GET", "/api/ping", b"", None),
                                                           ("infer", door, "POST", "/api/brain/infer", body, auth)):
                t0 = time.monotonic()
                status, _ = http_request(port, method, path, body=data, headers=headers, timeout=5)
                probes[key].append(status)
                worst[key] = max(worst[key], time.monotonic() - t0)
            peak = max(peak, process_counts(pid)[0])
            time.sleep(0.25)
    finally:
        flood.stop()
    left = time.monotonic()
    time.sleep(5.0)
    after = process_counts(pid)
    back = None
    while time.monotonic() - left < 60:
        if process_counts(pid)[0] <= quiet[0] + 5:
            back = round(time.monotonic() - left, 1)
            break
        time.sleep(0.5)
    out = {"server": name, "seconds": seconds, "attacker_requests": sum(flood.statuses.values()),
           "attacker_statuses": {str(k): v for k, v in sorted(flood.statuses.items())},
           "threads_quiet": quiet[0], "threads_peak": peak, "threads_5s_after": after[0], "threads_back_after_s": back}
    for key, statuses in probes.items():
        ok = sum(1 for s in statuses if s == 200)
        out[key] = {"ok": ok, "of": len(statuses), "worst_s": round(worst[key], 2),
                    "statuses": {str(s): statuses.count(s) for s in sorted(set(statuses))}}
        print(f"{name}: {key}: {ok} of {len(statuses)} probes answered 200 (worst {worst[key]:.2f} s) "
              f"{out[key]['statuses']}", flush=True)
    print(f"{name}: attacker sent {out['attacker_requests']} long-polls {out['attacker_statuses']}; threads "
          f"{quiet[0]} quiet, {peak} peak, {after[0]} 5 s after, back within {back} s", flush=True)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--server", choices=("werkzeug", "gunicorn", "both"), default="both")
    parser.add_argument("--repo", type=Path, default=REPO, help="the checkout whose webapp runs")
    parser.add_argument("--seconds", type=float, default=30.0)
    args = parser.parse_args()
    home = Path(tempfile.mkdtemp(prefix="hope-longpoll-"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env.update({"HOPE_HOME": str(home), "HOPE_AUTO_PROMOTE": "0", "HOPE_THERMAL_ZONE": str(home / "no-zone"),
                "HOPE_VCGENCMD": "", "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"})
    print(f"bench: HOPE_HOME {home}; training and promoting a fast_loop to serve", flush=True)
    prepare(home, env)
    from hope_models.settings import load_settings
    from webapp.auth import load_or_create_token

    token = load_or_create_token(load_settings(env=env))
    import importlib.util

    names = ("werkzeug", "gunicorn") if args.server == "both" else (args.server,)
    if "gunicorn" in names and importlib.util.find_spec("gunicorn") is None:
        print("bench: gunicorn is not importable (pip install --target /tmp/gunicorn gunicorn; "
              "PYTHONPATH=/tmp/gunicorn); measuring Werkzeug only", flush=True)
        names = tuple(n for n in names if n != "gunicorn")
    results = []
    for name in names:
        proc, editor, door, pid = start_werkzeug(args.repo, home, env) if name == "werkzeug" else \
            start_gunicorn(args.repo, home, env)
        try:
            results.append(attack(name, pid, editor, door, token, args.seconds))
        finally:
            proc.terminate()
            try:
                proc.wait(20)
            except subprocess.TimeoutExpired:
                proc.kill()
    print(json.dumps(results), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
