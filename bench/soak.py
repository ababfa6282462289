"""Soak: a real `serve` under legitimate load and every attacker at once, for minutes.

    python bench/soak.py                      # 1 quiet minute, then 10 minutes under attack (the recorded figure)
    python bench/soak.py --seconds 60 --quiet-seconds 20    # a quick look

What runs, all on loopback against one `run_trainer.py serve` (webapp + daemon + worker child + the
inference door child, whose RSS and descriptors are sampled too):
- a promoted fast_loop (trained and force-promoted first, on a synthetic dataset);
- a training chain vqvae -> fast_loop -> mid_loop queued through the API, re-queued when it ends;
- 20 inference clients, each POSTing /api/brain/infer at 50 Hz to the robot's door (the inference
  port; a new connection per request, as the server closes each one), in their own process;
- 10 Socket.IO clients logged in with the token on the editor's port, answering pings and
  receiving run events;
- first a quiet phase (`--quiet-seconds`, the legitimate load alone: the quiet inference figure),
  then every attacker of bench/soak_attackers.py, each in its own process, for `--seconds`. The
  attackers run at nice 19: on a real LAN their CPU is other machines', so what the soak measures is
  what their requests cost serve, not what building them costs this box.

It prints the failed legitimate requests (the target is 0), inference latency percentiles quiet and
under attack (target: p99 within 2x), editors dropped (target 0), what each attacker met, the bytes
the logs grew by (target under 1 MB), and the serve process's RSS, threads and descriptors sampled
over the run (flat = no leak), then one JSON line. Exit 1 if a target is missed.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "tests"))

from hostile_clients import SocketIOClient, http_request, process_counts  # noqa: E402
from soak_attackers import ATTACKERS  # noqa: E402

OBS_DIM, ACT_DIM = 6, 2


# -- the roles, each run as its own process so the load does not share the sampler's GIL ------------


def role_inference(port: int, token: str, seconds: float, clients: int, hz: float) -> dict:
    body = json.dumps({"component": "fast_loop", "observation": [0.1] * OBS_DIM}).encode()
    headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
    lat: list[list[float]] = [[] for _ in range(clients)]
    failures: list[str] = []
    end = time.monotonic() + seconds

    def client(i: int) -> None:
        period = 1.0 / hz
        next_at = time.monotonic() + i * period / clients
        while time.monotonic() < end:
            wait = next_at - time.monotonic()
            if wait > 0:
                time.sleep(wait)
            next_at += period
            started = time.perf_counter()
            try:
                status, answer = http_request(port, "POST", "/api/brain/infer", body=body, headers=headers,
                                              timeout=10)
                ok = status == 200 and len(json.loads(answer)["action"]) == ACT_DIM
            except Exception as exc:  # noqa: BLE001 - every failure is counted, with its reason
                status, ok, answer = -1, False, repr(exc).encode()
            lat[i].append(time.perf_counter() - started)
            if not ok:
                failures.append(f"{status} {answer[:120]!r}")
            if next_at < time.monotonic() - 1.0:
                next_at = time.monotonic()  # fell behind: do not burst to catch up

    threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    all_lat = sorted(x for per in lat for x in per)
    return {"requests": len(all_lat), "failed": len(failures), "failures": failures[:20],
            "rate_hz": len(all_lat) / seconds, "latency_ms": _percentiles(all_lat)}


def role_sockets(port: int, token: str, seconds: float, clients: int) -> dict:
    events = [0] * clients
    failures: list[str] = []
    end = time.monotonic() + seconds

    started = time.monotonic()

    def client(i: int) -> None:
        where = "connecting"
        try:
            c = SocketIOClient(port, token)
            if not c.connected:
                failures.append(f"client {i}: refused: {c.connect_reply!r}")
                return
            where = "connected"
            while time.monotonic() < end:
                events[i] += sum(1 for pkt in c.pump(min(2.0, max(0.05, end - time.monotonic())))
                                 if pkt.startswith("42"))
            c.close()
        except Exception as exc:  # noqa: BLE001 - a dropped editor is a failed legitimate client
            failures.append(f"client {i} ({where}, {time.monotonic() - started:.0f} s in): {exc!r}")

    threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return {"clients": clients, "failed": len(failures), "failures": failures, "events": sum(events)}


def _percentiles(values: list[float]) -> dict:
    if not values:
        return {}
    def q(p):
        return round(values[min(len(values) - 1, int(p * len(values)))] * 1000, 2)
    return {"p50": q(0.50), "p90": q(0.90), "p99": q(0.99), "max": round(values[-1] * 1000, 2)}


# -- the driver -----------------------------------------------------------------------------------------


def _run(cmd: list[str], env: dict, what: str) -> str:
    proc = subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True)
    if proc.returncode != 0:
        sys.exit(f"soak: {what} failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-2000:]}")
    return proc.stdout


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def _door_pid(serve_pid: int) -> int | None:
    """serve's inference door child (webapp/door_process.py), or None."""
    import psutil

    try:
        for child in psutil.Process(serve_pid).children():
            if "webapp.door_process" in " ".join(child.cmdline()):
                return child.pid
    except psutil.Error:
        pass
    return None


def _spawn_role(role: str, port: int, token: str, seconds: float, out: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, __file__, "--role", role, "--port", str(port), "--token", token,
                             "--seconds", str(seconds), "--out", str(out)], cwd=REPO)


def _api(port: int, method: str, path: str, token: str, body: bytes = b"") -> tuple[int, bytes]:
    """The driver's own calls as a real client makes them: after a 503 (Retry-After: 2) it tries again."""
    headers = {"Authorization": f"Bearer {token}", "Content-Type": "application/json"}
    for _ in range(10):
        status, answer = http_request(port, method, path, body=body, headers=headers, timeout=30)
        if status != 503:
            return status, answer
        time.sleep(2.0)
    return status, answer


def _enqueue_chain(port: int, token: str, steps: int) -> int:
    body = json.dumps({"components": ["vqvae", "fast_loop", "mid_loop"], "data": "soak", "steps": steps,
                       "batch_size": 8, "checkpoint_every_steps": 200}).encode()
    status, answer = _api(port, "POST", "/api/training/sequential", token, body)
    if status != 201:
        sys.exit(f"soak: queueing the training chain failed: {status} {answer[:300]!r}")
    return status


def _chain_active(port: int, token: str) -> bool:
    status, answer = _api(port, "GET", "/api/runs?state=queued,starting,running,paused", token)
    return status != 200 or any(r["state"] in ("queued", "starting", "running", "paused") and r["queue"] == "pi"
                                for r in json.loads(answer)["runs"])


def _start_serve(home: Path, env: dict) -> tuple[subprocess.Popen, int, int, str]:
    """serve, and (process, editor port, inference port, token) once it printed them."""
    py = [sys.executable, str(REPO / "run_trainer.py")]
    log = open(home / "serve.log", "w")
    serve = subprocess.Popen(py + ["serve", "--port", "0", "--inference-port", "0"], cwd=REPO, env=env,
                             stdout=log, stderr=subprocess.STDOUT)
    log.close()
    deadline = time.monotonic() + 60
    main = door = None
    while (main is None or door is None) and time.monotonic() < deadline and serve.poll() is None:
        time.sleep(0.2)
        text = (home / "serve.log").read_text()
        main = re.search(r"Robot Editor: http://[^:]+:(\d+)/\s+token: (\S+)", text)
        door = re.search(r"inference: http://[^:]+:(\d+)/api/brain/infer", text)
    if main is None or door is None:
        serve.kill()
        sys.exit(f"soak: serve did not start:\n{(home / 'serve.log').read_text()[-3000:]}")
    return serve, int(main.group(1)), int(door.group(1)), main.group(2)


def _log_bytes(home: Path) -> int:
    files = list((home / "logs").glob("*")) + [home / "serve.log"]
    return sum(f.stat().st_size for f in files if f.is_file())


class Sampler:
    """serve's RSS, threads and descriptors every `every_s`, and the training chain kept queued."""

    def __init__(self, pid: int, port: int, token: str, chain_steps: int, every_s: float):
        self.pid, self.port, self.token, self.chain_steps, self.every_s = pid, port, token, chain_steps, every_s
        self.samples: list[dict] = []
        self.chains = 0
        self.started = time.monotonic()

    def sample(self, phase: str) -> None:
        threads, fds = process_counts(self.pid)
        door = _door_pid(self.pid)
        door_fds = process_counts(door)[1] if door else 0
        self.samples.append({"t_s": round(time.monotonic() - self.started), "phase": phase,
                             "rss_mb": round(_rss_mb(self.pid), 1), "threads": threads, "fds": fds,
                             "door_rss_mb": round(_rss_mb(door), 1) if door else 0.0, "door_fds": door_fds})

    def follow(self, procs: dict, phase: str) -> None:
        while any(p.poll() is None for p in procs.values()):
            self.sample(phase)
            if not _chain_active(self.port, self.token):
                _enqueue_chain(self.port, self.token, self.chain_steps)
                self.chains += 1
            time.sleep(self.every_s)


def _phase(home: Path, name: str, roles: dict, seconds: float, sampler: Sampler) -> dict:
    """Run each role's process for `seconds` (role -> (port, delay before it starts)); their results."""
    out = {role: home / f"{name}-{role}.json" for role in roles}
    procs = {}
    for role, (port, delay) in roles.items():
        time.sleep(delay)
        procs[role] = _spawn_role(role, port, sampler.token, seconds, out[role])
    sampler.follow(procs, name)
    failed = [role for role, proc in procs.items() if proc.returncode != 0]
    if failed:
        sys.exit(f"soak: the {', '.join(failed)} process(es) of the {name} phase failed")
    return {role: json.loads(path.read_text()) for role, path in out.items()}


def drive(args) -> int:
    from hope_models.data.synthetic import generate_dataset

    home = Path(tempfile.mkdtemp(prefix="hope-soak-"))
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env.update({"HOPE_HOME": str(home), "HOPE_AUTO_PROMOTE": "0", "HOPE_THERMAL_ZONE": str(home / "no-zone"),
                "HOPE_VCGENCMD": "", "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1"})
    data = home / "datasets" / "soak"
    generate_dataset(data, 3000, obs_dim=OBS_DIM, act_dim=ACT_DIM, episode_seconds=(5, 15), seed=3)
    print(f"soak: HOPE_HOME {home}; training and promoting a fast_loop to serve", flush=True)
    py = [sys.executable, str(REPO / "run_trainer.py")]
    _run(py + ["train", "--component", "fast_loop", "--data", str(data), "--run-dir", str(home / "runs" / "seed"),
               "--steps", "40", "--warmup", "4"], env, "training the served fast_loop")
    _run(py + ["promote", "--checkpoint", str(home / "runs" / "seed"), "--force"], env, "promoting it")

    serve, port, door, token = _start_serve(home, env)
    try:
        sampler = Sampler(serve.pid, port, token, args.chain_steps, args.sample_s)
        _enqueue_chain(port, token, args.chain_steps)
        sampler.chains = 1
        logs_before = _log_bytes(home)
        legitimate = {"sockets": (port, 0.0), "inference": (door, 2.0)}  # the editors log in first
        quiet = _phase(home, "quiet", legitimate, args.quiet_seconds, sampler)
        attackers = {name: (port, 0.0) for name in args.attackers}
        attacked = _phase(home, "attack", {**legitimate, **attackers}, args.seconds, sampler)
        time.sleep(30)  # the last attackers' sessions and ping sleepers end
        sampler.sample("after 30 s quiet")
        logs_grew = _log_bytes(home) - logs_before
    finally:
        serve.terminate()
        try:
            serve.wait(60)
        except subprocess.TimeoutExpired:
            serve.kill()
    return report(args, quiet, attacked, sampler, logs_grew)


def report(args, quiet_roles: dict, attacked: dict, sampler: Sampler, logs_grew: int) -> int:
    quiet, quiet_socks = quiet_roles["inference"], quiet_roles["sockets"]
    inf, socks = attacked["inference"], attacked["sockets"]
    samples = sampler.samples
    under = [s for s in samples if s["phase"] == "attack"]
    first, second = under[: len(under) // 2], under[len(under) // 2:]

    def med(rows, key):
        return statistics.median(r[key] for r in rows) if rows else float("nan")

    q99, a99 = quiet["latency_ms"].get("p99", float("nan")), inf["latency_ms"].get("p99", float("nan"))
    print(f"\nquiet {args.quiet_seconds:.0f} s: {quiet['requests']} inferences at {quiet['rate_hz']:.0f}/s, "
          f"failed {quiet['failed']}; latency ms {quiet['latency_ms']}")
    print(f"attack {args.seconds:.0f} s: {inf['requests']} inferences at {inf['rate_hz']:.0f}/s "
          f"(20 clients x 50 Hz asked), failed {inf['failed']}; latency ms {inf['latency_ms']}; "
          f"p99 {a99 / q99:.2f}x the quiet figure")
    print(f"socket.io: {socks['clients']} editors, dropped {quiet_socks['failed']} quiet, {socks['failed']} under "
          f"attack; {socks['events']} events received under attack")
    for name in args.attackers:
        print(f"attacker {name}: {json.dumps(attacked[name])}")
    print(f"logs grew by {logs_grew / 1024:.0f} KB; training chains queued {sampler.chains}")
    print("serve process over time (t s, phase, RSS MB, threads, fds; its inference door child's RSS MB, fds):")
    for s in samples:
        print(f"  {s['t_s']:5d}  {s['phase']:16s} {s['rss_mb']:7.1f}  {s['threads']:5d}  {s['fds']:5d}"
              f"   door {s['door_rss_mb']:6.1f}  {s['door_fds']:4d}")
    print(f"under attack, median RSS first/second half: {med(first, 'rss_mb'):.1f} / {med(second, 'rss_mb'):.1f} MB; "
          f"median fds {med(first, 'fds'):.0f} / {med(second, 'fds'):.0f}; threads "
          f"{med(first, 'threads'):.0f} / {med(second, 'threads'):.0f}; after: {samples[-1]['fds']} fds, "
          f"{samples[-1]['threads']} threads; the door's median RSS {med(first, 'door_rss_mb'):.1f} / "
          f"{med(second, 'door_rss_mb'):.1f} MB")
    for f in quiet["failures"] + quiet_socks["failures"] + inf["failures"] + socks["failures"]:
        print("  failure:", f)
    missed = {"failed inferences": quiet["failed"] + inf["failed"] > 0, "editors dropped": socks["failed"] + quiet_socks["failed"] > 0,
              "p99 over 2x quiet": not a99 <= 2 * q99, "logs over 1 MB": logs_grew > 1 << 20,
              "RSS grew": med(second, "rss_mb") > med(first, "rss_mb") * 1.1 + 20,
              "door RSS grew": med(second, "door_rss_mb") > med(first, "door_rss_mb") * 1.1 + 10,
              "fds grew": samples[-1]["fds"] > samples[0]["fds"] + 10}
    summary = {"seconds": args.seconds, "quiet_seconds": args.quiet_seconds, "quiet": quiet_roles, "attack": attacked,
               "logs_grew_bytes": logs_grew, "chains": sampler.chains, "missed": [k for k, v in missed.items() if v]}
    print(json.dumps(summary))
    return 1 if any(missed.values()) else 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=600.0, help="the attack phase")
    p.add_argument("--quiet-seconds", type=float, default=60.0, help="the quiet phase before it")
    p.add_argument("--attackers", nargs="*", default=list(ATTACKERS), choices=list(ATTACKERS))
    p.add_argument("--sample-s", type=float, default=10.0, help="how often serve's RSS/threads/fds are sampled")
    p.add_argument("--chain-steps", type=int, default=3000, help="steps of each component of the training chain")
    p.add_argument("--role", choices=("inference", "sockets", *ATTACKERS), help=argparse.SUPPRESS)
    p.add_argument("--port", type=int, help=argparse.SUPPRESS)
    p.add_argument("--token", help=argparse.SUPPRESS)
    p.add_argument("--out", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.role is None:
        return drive(args)
    if args.role == "inference":
        result = role_inference(args.port, args.token, args.seconds, clients=20, hz=50.0)
    elif args.role == "sockets":
        result = role_sockets(args.port, args.token, args.seconds, clients=10)
    else:
        # The attackers' own CPU would be other machines' on a real LAN: at the lowest priority here,
        # what they cost serve (every request still answered) is what the soak measures, not what
        # building and sending them costs this 2-core box.
        os.nice(19)
        result = ATTACKERS[args.role](args.port, args.token, args.seconds)
    Path(args.out).write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
