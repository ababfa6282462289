"""Soak: a real `serve` under legitimate load and a hostile neighbour at once, for minutes.

    python bench/soak.py                 # 10 minutes (the recorded figure)
    python bench/soak.py --seconds 60    # a quick look

What runs, all on loopback against one `run_trainer.py serve` (webapp + daemon + worker child):
- a promoted fast_loop (trained and force-promoted first, on a synthetic dataset);
- a training chain vqvae -> fast_loop -> mid_loop queued through the API, re-queued when it ends;
- 20 inference clients, each POSTing /api/brain/infer at 50 Hz (a new connection per request,
  as the server closes each one), in their own process;
- 10 Socket.IO clients logged in with the token, answering pings and receiving run events;
- a hostile client repeating, without a token: Engine.IO handshakes each followed by a bad POST
  (`6`, `0`, `2probe`, `9zzz`, an oversized payload), 50 half-sent request headers and 100 silent
  WebSockets held a few seconds, then let go.

It prints the failed legitimate requests (the target is 0), inference latency percentiles and the
achieved rate, and the serve process's RSS, threads and descriptors sampled over the run (flat =
no leak), then one JSON line. Exit 1 if a legitimate request failed or descriptors grew.
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

from hostile_clients import HostileRound, SocketIOClient, http_request, process_counts  # noqa: E402

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

    def client(i: int) -> None:
        try:
            c = SocketIOClient(port, token)
            if not c.connected:
                failures.append(f"client {i}: refused: {c.connect_reply!r}")
                return
            while time.monotonic() < end:
                events[i] += sum(1 for pkt in c.pump(min(2.0, max(0.05, end - time.monotonic())))
                                 if pkt.startswith("42"))
            c.close()
        except Exception as exc:  # noqa: BLE001 - a dropped editor is a failed legitimate client
            failures.append(f"client {i}: {exc!r}")

    threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return {"clients": clients, "failed": len(failures), "failures": failures, "events": sum(events)}


def role_hostile(port: int, seconds: float) -> dict:
    end = time.monotonic() + seconds
    rounds, statuses, refused = 0, {}, 0
    while time.monotonic() < end - 10:
        r = HostileRound(port, pairs_per_body=60, half_headers=50, silent_websockets=100).run()
        time.sleep(4.0)  # hold the sockets a while, as a patient attacker does
        r.release()
        rounds += 1
        refused += r.refused
        for k, v in r.statuses.items():
            statuses[str(k)] = statuses.get(str(k), 0) + v
        time.sleep(1.0)
    return {"rounds": rounds, "bad_post_statuses": statuses, "held_refused": refused}


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


def _spawn_role(role: str, port: int, token: str, seconds: float, out: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, __file__, "--role", role, "--port", str(port), "--token", token,
                             "--seconds", str(seconds), "--out", str(out)], cwd=REPO)


def _enqueue_chain(port: int, token: str, steps: int) -> int:
    body = json.dumps({"components": ["vqvae", "fast_loop", "mid_loop"], "data": "soak", "steps": steps,
                       "batch_size": 8, "checkpoint_every_steps": 200}).encode()
    status, answer = http_request(port, "POST", "/api/training/sequential", body=body,
                                  headers={"Authorization": f"Bearer {token}", "Content-Type": "application/json"})
    if status != 201:
        sys.exit(f"soak: queueing the training chain failed: {status} {answer[:300]!r}")
    return status


def _chain_active(port: int, token: str) -> bool:
    status, answer = http_request(port, "GET", "/api/runs", headers={"Authorization": f"Bearer {token}"})
    return status == 200 and any(r["state"] in ("queued", "starting", "running", "paused")
                                 for r in json.loads(answer)["runs"])


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

    log = open(home / "serve.log", "w")
    serve = subprocess.Popen(py + ["serve", "--port", "0"], cwd=REPO, env=env, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        match = None
        while match is None and time.monotonic() < deadline and serve.poll() is None:
            time.sleep(0.2)
            match = re.search(r"Robot Editor: http://[^:]+:(\d+)/\s+token: (\S+)", (home / "serve.log").read_text())
        if match is None:
            sys.exit(f"soak: serve did not start:\n{(home / 'serve.log').read_text()[-3000:]}")
        port, token = int(match.group(1)), match.group(2)
        _enqueue_chain(port, token, args.chain_steps)
        out = {role: home / f"{role}.json" for role in ("inference", "sockets", "hostile")}
        procs = {"sockets": _spawn_role("sockets", port, token, args.seconds, out["sockets"])}
        time.sleep(2.0)  # the editors log in before the neighbour starts
        procs["inference"] = _spawn_role("inference", port, token, args.seconds, out["inference"])
        procs["hostile"] = _spawn_role("hostile", port, token, args.seconds, out["hostile"])
        samples, chains = [], 1
        started = time.monotonic()
        while any(p.poll() is None for p in procs.values()):
            threads, fds = process_counts(serve.pid)
            samples.append({"t_s": round(time.monotonic() - started), "rss_mb": round(_rss_mb(serve.pid), 1),
                            "threads": threads, "fds": fds})
            if not _chain_active(port, token):
                _enqueue_chain(port, token, args.chain_steps)
                chains += 1
            time.sleep(args.sample_s)
        time.sleep(30)  # the last hostile sockets' sessions and ping sleepers end
        threads, fds = process_counts(serve.pid)
        samples.append({"t_s": round(time.monotonic() - started), "rss_mb": round(_rss_mb(serve.pid), 1),
                        "threads": threads, "fds": fds, "after_30s_quiet": True})
        results = {role: json.loads(path.read_text()) for role, path in out.items()}
    finally:
        serve.terminate()
        try:
            serve.wait(60)
        except subprocess.TimeoutExpired:
            serve.kill()
        log.close()

    inf, socks, hostile = results["inference"], results["sockets"], results["hostile"]
    first_half = [s for s in samples if s["t_s"] <= args.seconds / 2]
    second_half = [s for s in samples if args.seconds / 2 < s["t_s"] <= args.seconds]
    def med(rows, key):
        return statistics.median(r[key] for r in rows) if rows else float("nan")
    print(f"\nsoak {args.seconds:.0f} s: {inf['requests']} inferences at {inf['rate_hz']:.0f}/s "
          f"(20 clients x 50 Hz asked), failed {inf['failed']}; latency ms {inf['latency_ms']}")
    print(f"socket.io: {socks['clients']} editors, failed {socks['failed']}, {socks['events']} events received")
    print(f"hostile: {hostile['rounds']} rounds, bad POSTs {hostile['bad_post_statuses']}, "
          f"held sockets refused {hostile['held_refused']}; training chains queued {chains}")
    print("serve process over time (t s, RSS MB, threads, fds):")
    for s in samples:
        print(f"  {s['t_s']:5d}  {s['rss_mb']:7.1f}  {s['threads']:5d}  {s['fds']:5d}"
              + ("  (30 s after the load)" if s.get("after_30s_quiet") else ""))
    print(f"median RSS first/second half: {med(first_half, 'rss_mb'):.1f} / {med(second_half, 'rss_mb'):.1f} MB; "
          f"median fds {med(first_half, 'fds'):.0f} / {med(second_half, 'fds'):.0f}; "
          f"after: {samples[-1]['fds']} fds, {samples[-1]['threads']} threads")
    failed = inf["failed"] + socks["failed"]
    for f in inf["failures"] + socks["failures"]:
        print("  failure:", f)
    summary = {"seconds": args.seconds, "inference": inf, "sockets": socks, "hostile": hostile,
               "samples": samples, "chains": chains}
    print(json.dumps({k: v for k, v in summary.items() if k != "samples"}))
    fds_grew = samples[-1]["fds"] > samples[0]["fds"] + 10
    return 1 if failed or fds_grew else 0


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--seconds", type=float, default=600.0)
    p.add_argument("--sample-s", type=float, default=10.0, help="how often serve's RSS/threads/fds are sampled")
    p.add_argument("--chain-steps", type=int, default=3000, help="steps of each component of the training chain")
    p.add_argument("--role", choices=("inference", "sockets", "hostile"), help=argparse.SUPPRESS)
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
        result = role_hostile(args.port, args.seconds)
    Path(args.out).write_text(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
