"""Job-lifecycle benchmark: how long the service takes around a job, and what it costs idle.

For each broker (the embedded sqla+sqlite one, and Redis on a local redis-server), the production
layout is started as separate processes with a fresh $HOPE_HOME: `run_trainer.py daemon`,
`run_trainer.py worker -Q pi` and `run_trainer.py webapp`. Then:

1. idle RSS (and PSS, which splits pages shared after a fork) of the daemon, the worker parent,
   its idle pool child, and the webapp, a few seconds after they settled. Target: daemon + worker
   parent + webapp under 400 MB RSS together.
2. --solo jobs, each enqueued while the service is idle: enqueue-to-first-step latency, split into
   enqueue -> dispatched (daemon tick), dispatched -> claimed (broker delivery + child fork),
   claimed -> first step (the child imports torch, opens the dataset cache, builds the model).
3. --chained jobs enqueued together: job-end-to-next-start latency, from one run's finished_at to
   the next one's dispatch, claim and first step.
4. the worker parent's RSS before the first job and after each job (it must not grow: each job
   runs in a child that exits afterwards).
Last, the idle RSS of `run_trainer.py serve` (daemon + webapp in one process) and its worker.

Every job is a tiny fast_loop run (--steps, one thread, log_every 1 so step 1 is recorded), so the
figures are the service's overhead, not training. Times come from the registry (created_at,
run_events times, finished_at): the same clock, written by the processes themselves.

    .venv/bin/python bench/job_lifecycle.py                  # --solo 2 --chained 3 --steps 60
    .venv/bin/python bench/job_lifecycle.py --brokers embedded --json

It prints figures; it is not a test.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from datetime import datetime
from itertools import pairwise
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

RSS_TARGET_MB = 400.0


# -- processes ------------------------------------------------------------------------------------

class Proc:
    def __init__(self, name: str, cmd: list[str], env: dict[str, str], log: Path):
        self.name = name
        self.log = log
        self._fh = open(log, "ab")
        self.popen = subprocess.Popen(cmd, env=env, cwd=REPO, stdout=self._fh, stderr=subprocess.STDOUT,
                                      start_new_session=True)

    @property
    def pid(self) -> int:
        return self.popen.pid

    def alive(self) -> bool:
        return self.popen.poll() is None

    def stop(self, timeout: float = 30.0) -> None:
        if self.alive():
            self.popen.send_signal(signal.SIGTERM)
            try:
                self.popen.wait(timeout)
            except subprocess.TimeoutExpired:
                pass
        try:
            os.killpg(self.pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            pass
        self.popen.wait(10)
        self._fh.close()


def memory_mb(pid: int) -> dict[str, float]:
    import psutil

    info = psutil.Process(pid).memory_full_info()
    return {"rss_mb": info.rss / 2**20, "pss_mb": getattr(info, "pss", info.rss) / 2**20}


def pool_children(pid: int) -> list[int]:
    import psutil

    try:
        return [c.pid for c in psutil.Process(pid).children() if c.status() != psutil.STATUS_ZOMBIE]
    except psutil.NoSuchProcess:
        return []


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Redis:
    def __init__(self, workdir: Path):
        exe = shutil.which("redis-server")
        if exe is None:
            raise SystemExit("redis-server is not installed (apt-get install redis-server); "
                             "or run with --brokers embedded")
        self.port = free_port()
        workdir.mkdir(parents=True, exist_ok=True)
        self.proc = subprocess.Popen([exe, "--port", str(self.port), "--bind", "127.0.0.1", "--save", "",
                                      "--appendonly", "no", "--dir", str(workdir)],
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.5) as c:
                    c.sendall(b"PING\r\n")
                    if c.recv(16).startswith(b"+PONG"):
                        return
            except OSError:
                time.sleep(0.05)
        raise SystemExit(f"redis-server on port {self.port} did not answer")

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(10)


# -- one broker mode --------------------------------------------------------------------------------

def wait_for(predicate, timeout: float, what: str, procs: list[Proc]):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        for p in procs:
            if not p.alive():
                tail = p.log.read_text(errors="replace").splitlines()[-30:]
                raise SystemExit(f"{p.name} exited while waiting for {what}:\n" + "\n".join(tail))
        time.sleep(0.05)
    tails = []
    for p in procs:
        tails.append(f"--- {p.name} ---")
        tails.extend(p.log.read_text(errors="replace").splitlines()[-20:])
    raise SystemExit(f"timed out after {timeout} s waiting for {what}\n" + "\n".join(tails))


def _t(value: Any) -> datetime:
    return value if isinstance(value, datetime) else datetime.fromisoformat(value)


def job_times(registry, run_id: str) -> dict[str, Any]:
    """created, dispatched (state starting), claimed (started_at), first step (first progress), finished."""
    from registry import runs

    with registry.session(readonly=True) as s:
        run = runs.get_run(s, run_id)
        events = runs.run_events(s, run_id, kinds=["state", "progress"])
        dispatched = next(e.time for e in events if e.kind == "state" and e.payload.get("state") == "starting")
        first = next(e for e in events if e.kind == "progress")
        return {"id": run.id, "state": run.state, "created": run.created_at, "dispatched": dispatched,
                "claimed": run.started_at, "first_step": first.time, "first_step_no": first.payload.get("step"),
                "finished": run.finished_at}


def run_mode(mode: str, dataset: Path, args: argparse.Namespace, work: Path) -> dict[str, Any]:
    from hope_models.settings import load_settings
    from registry.db import Registry
    from registry.run_request import build_request, submit

    home = work / mode
    home.mkdir(parents=True)
    redis = Redis(work / f"redis-{mode}") if mode == "redis" else None
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env.update({"HOPE_HOME": str(home), "PYTHONUNBUFFERED": "1", "OMP_NUM_THREADS": "1",
                "HOPE_THERMAL_ZONE": str(home / "no-thermal-zone")})  # this machine's zone must not throttle
    env.pop("NOTIFY_SOCKET", None)
    if redis is not None:
        env["HOPE_REDIS_URL"] = redis.url
    settings = load_settings(env=env)
    registry = Registry.open(settings)  # migrated before the services start, as the daemon would
    py = sys.executable
    procs: list[Proc] = []
    try:
        daemon = Proc("daemon", [py, str(REPO / "run_trainer.py"), "daemon", "--tick-s", str(args.tick)], env,
                      home / "daemon.log")
        worker = Proc("worker", [py, str(REPO / "run_trainer.py"), "worker", "-Q", "pi", "--loglevel", "info"], env,
                      home / "worker.log")
        webapp = Proc("webapp", [py, str(REPO / "run_trainer.py"), "webapp", "--port", "0"], env, home / "webapp.log")
        procs = [daemon, worker, webapp]
        wait_for(lambda: "ready." in worker.log.read_text(errors="replace"), 60, "the worker to be ready", procs)
        wait_for(lambda: "Robot Editor:" in webapp.log.read_text(errors="replace"), 60, "the webapp", procs)
        time.sleep(args.settle)
        idle = {"daemon": memory_mb(daemon.pid), "worker_parent": memory_mb(worker.pid),
                "webapp": memory_mb(webapp.pid)}
        children = pool_children(worker.pid)
        idle["worker_pool_child"] = memory_mb(children[0]) if children else {"rss_mb": 0.0, "pss_mb": 0.0}
        worker_rss = [memory_mb(worker.pid)["rss_mb"]]

        def enqueue() -> str:
            req = build_request(component="fast_loop", data=str(dataset), steps=args.steps,
                                overrides={"threads": 1, "batch_size": 8, "warmup": 5, "log_every": 1,
                                           "checkpoint_every_steps": args.steps, "seed": 0})
            with registry.session() as s:
                return submit(s, settings, req).id

        def state(run_id: str) -> str:
            from registry import runs

            with registry.session(readonly=True) as s:
                return runs.get_run(s, run_id).state

        def wait_done(run_id: str) -> None:
            wait_for(lambda: state(run_id) in ("completed", "failed", "cancelled"), 180, f"run {run_id}", procs)
            if state(run_id) != "completed":
                raise SystemExit(f"run {run_id} ended {state(run_id)}; see {home}")

        def worker_settled() -> float:
            # after a job the pool child exits and a fresh one is forked; measure once that happened
            time.sleep(1.0)
            return memory_mb(worker.pid)["rss_mb"]

        solo = []
        for _ in range(args.solo):
            run_id = enqueue()
            wait_done(run_id)
            solo.append(job_times(registry, run_id))
            worker_rss.append(worker_settled())
            time.sleep(args.idle_between)
        chained_ids = [enqueue() for _ in range(args.chained)]
        for run_id in chained_ids:
            wait_done(run_id)
        chained = [job_times(registry, r) for r in chained_ids]
        worker_rss.append(worker_settled())
    finally:
        for p in reversed(procs):
            p.stop()
        registry.close()
        if redis is not None:
            redis.stop()

    def s(a, b) -> float:
        return (_t(b) - _t(a)).total_seconds()

    enqueue_to_first = [{"total_s": s(j["created"], j["first_step"]),
                         "to_dispatch_s": s(j["created"], j["dispatched"]),
                         "to_claim_s": s(j["dispatched"], j["claimed"]),
                         "to_first_step_s": s(j["claimed"], j["first_step"]),
                         "first_step": j["first_step_no"]} for j in solo]
    end_to_next = [{"total_s": s(a["finished"], b["first_step"]), "to_dispatch_s": s(a["finished"], b["dispatched"]),
                    "to_claim_s": s(a["finished"], b["claimed"]), "first_step": b["first_step_no"]}
                   for a, b in pairwise(chained)]
    together = sum(idle[k]["rss_mb"] for k in ("daemon", "worker_parent", "webapp"))
    return {"mode": mode, "idle": idle, "idle_total_rss_mb": together, "enqueue_to_first_step": enqueue_to_first,
            "end_to_next_start": end_to_next, "worker_parent_rss_mb": worker_rss, "jobs": args.solo + args.chained}


def serve_idle(args: argparse.Namespace, work: Path) -> dict[str, Any]:
    """Idle RSS of `run_trainer.py serve` (daemon + webapp in one process) and its worker child."""
    home = work / "serve"
    home.mkdir(parents=True)
    env = {k: v for k, v in os.environ.items() if not k.startswith("HOPE_")}
    env.update({"HOPE_HOME": str(home), "PYTHONUNBUFFERED": "1", "HOPE_THERMAL_ZONE": str(home / "no-zone")})
    env.pop("NOTIFY_SOCKET", None)
    serve = Proc("serve", [sys.executable, str(REPO / "run_trainer.py"), "serve", "--port", "0"], env,
                 home / "serve.log")
    try:
        worker_log = home / "logs" / "worker.log"
        wait_for(lambda: worker_log.exists() and "ready." in worker_log.read_text(errors="replace"), 60,
                 "serve's worker to be ready", [serve])
        time.sleep(args.settle)
        import psutil

        # serve -> exec wrapper (replaced by) celery parent -> pool child
        worker = [c for c in psutil.Process(serve.pid).children() if "celery" in " ".join(c.cmdline())][0]
        out = {"serve": memory_mb(serve.pid), "worker_parent": memory_mb(worker.pid)}
        out["total_rss_mb"] = out["serve"]["rss_mb"] + out["worker_parent"]["rss_mb"]
        return out
    finally:
        serve.popen.send_signal(signal.SIGINT)
        serve.stop()


# -- report --------------------------------------------------------------------------------------------

def _stat(values: list[float]) -> str:
    if not values:
        return "-"
    if len(values) == 1:
        return f"{values[0]:.2f}"
    return f"{statistics.median(values):.2f} ({min(values):.2f}-{max(values):.2f})"


def report(results: list[dict[str, Any]]) -> str:
    modes = [r["mode"] for r in results]
    lines = ["Latency, seconds: median (min-max)", ""]
    header = "| | " + " | ".join(modes) + " |"
    lines += [header, "|---|" + "---:|" * len(modes)]

    def row(label: str, key: str, part: str) -> None:
        lines.append(f"| {label} | " + " | ".join(_stat([x[part] for x in r[key]]) for r in results) + " |")

    row("enqueue -> first step", "enqueue_to_first_step", "total_s")
    row("  enqueue -> dispatched", "enqueue_to_first_step", "to_dispatch_s")
    row("  dispatched -> claimed by the job child", "enqueue_to_first_step", "to_claim_s")
    row("  claimed -> first step (torch import, cache, model)", "enqueue_to_first_step", "to_first_step_s")
    row("job end -> next job's first step", "end_to_next_start", "total_s")
    row("  job end -> next dispatched", "end_to_next_start", "to_dispatch_s")
    row("  job end -> next claimed", "end_to_next_start", "to_claim_s")
    lines += ["", "Idle memory, MB: RSS (PSS)", "", header, "|---|" + "---:|" * len(modes)]
    for key, label in (("daemon", "daemon"), ("worker_parent", "worker parent"), ("webapp", "webapp"),
                       ("worker_pool_child", "worker's idle pool child (forked, no torch)")):
        lines.append(f"| {label} | " + " | ".join(
            f"{r['idle'][key]['rss_mb']:.0f} ({r['idle'][key]['pss_mb']:.0f})" for r in results) + " |")
    lines.append("| **daemon + worker parent + webapp** | " + " | ".join(
        f"**{r['idle_total_rss_mb']:.0f}** {'PASS' if r['idle_total_rss_mb'] < RSS_TARGET_MB else 'FAIL'} "
        f"(< {RSS_TARGET_MB:.0f})" for r in results) + " |")
    lines += ["", "Worker parent RSS, MB: before the first job, then after each solo job and after the chain", ""]
    for r in results:
        rss = r["worker_parent_rss_mb"]
        lines.append(f"- {r['mode']}: " + " -> ".join(f"{v:.1f}" for v in rss) +
                     f"  (after {r['jobs']} jobs: {rss[-1] - rss[0]:+.1f} MB)")
    return "\n".join(lines)


def report_serve(out: dict[str, Any]) -> str:
    return (f"serve (daemon + webapp in one process) {out['serve']['rss_mb']:.0f} MB RSS "
            f"({out['serve']['pss_mb']:.0f} PSS) + its worker parent {out['worker_parent']['rss_mb']:.0f} MB "
            f"({out['worker_parent']['pss_mb']:.0f}) = {out['total_rss_mb']:.0f} MB idle")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--brokers", default="embedded,redis", help="embedded,redis (default both)")
    parser.add_argument("--solo", type=int, default=2, help="jobs enqueued one at a time on an idle service")
    parser.add_argument("--chained", type=int, default=3, help="jobs enqueued together (end-to-next-start)")
    parser.add_argument("--steps", type=int, default=60, help="steps per job (default 60)")
    parser.add_argument("--tick", type=float, default=0.5, help="daemon tick, seconds (default 0.5, as deployed)")
    parser.add_argument("--settle", type=float, default=5.0, help="seconds idle before measuring RSS")
    parser.add_argument("--idle-between", type=float, default=1.0, help="idle seconds between solo jobs")
    parser.add_argument("--no-serve", action="store_true", help="skip the idle RSS of `serve`")
    parser.add_argument("--out", help="work dir (default: a temp dir, removed afterwards)")
    parser.add_argument("--json", action="store_true", help="print the raw figures as JSON too")
    args = parser.parse_args()
    if args.solo < 1 or args.chained < 2:
        parser.error("--solo must be >= 1 and --chained >= 2")

    from hope_models.data.synthetic import generate_dataset

    work = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="hope-lifecycle-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        dataset = work / "ds"
        if not dataset.exists():
            generate_dataset(dataset, 600, obs_dim=4, act_dim=2, episode_seconds=(3, 9), seed=3)
        results = []
        for mode in [m.strip() for m in args.brokers.split(",") if m.strip()]:
            if mode not in ("embedded", "redis"):
                parser.error(f"--brokers: unknown {mode!r}")
            started = time.monotonic()
            results.append(run_mode(mode, dataset, args, work))
            print(f"{mode}: {time.monotonic() - started:.0f} s", file=sys.stderr, flush=True)
        serve = None if args.no_serve else serve_idle(args, work)
        print(report(results))
        if serve is not None:
            print("\n" + report_serve(serve))
        if args.json:
            print(json.dumps({"brokers": results, "serve": serve}, default=str, indent=1))
    finally:
        if not args.out:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
