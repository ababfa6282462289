"""`run_trainer.py demo`: the whole loop on this machine, through the real services, in one command.

    run_trainer.py demo [--episodes 50] [--steps 4000] [--eval-episodes 20] [--exit] [--port 8765]

1. records expert demonstrations in the simulated reacher (DART noise 1.0, seeds from 100000) into
   $HOPE_HOME/demo/reach-<N>-dart<noise>/ (reused when already there);
2. starts what `serve` starts, in this process (daemon/cli/serve.py's Serve: the webapp, the daemon,
   BrainService and the worker child on the embedded broker);
3. queues the chain vqvae, fast_loop, mid_loop through the registry, as `run_trainer.py sequential`
   does, and shows each run's progress in the terminal while the worker trains it;
4. auto-promotion gates every completed run (finite weights, validation loss, the sim reflex);
   as soon as BrainService serves the new fast_loop, one inference goes through the HTTP API with
   the token (that first answer closes the loop: its run's loop-closure time is recorded);
5. evaluates the promoted fast_loop in closed loop on held-out seeds 0..N-1 with the expert and a
   random policy (`eval-reflex --checkpoint promoted`, a child process);
6. prints the summary table, writes it as JSON to $HOPE_HOME/demo/summary.json, prints the Robot
   Editor URL and token, and keeps serving until Ctrl-C (`--exit`: stops after the summary).

Exit 0 when every run completed, the fast_loop was promoted and served, and its mean return is at
least --target-return (900); 1 otherwise, saying what fell short; 2 when it cannot start (port taken,
settings); 130 after Ctrl-C before the summary. This process never imports torch or MuJoCo: the
recording, training, gating and evaluation all run in child processes.

Why 4000 steps: measured on 2 busy cores, a fast_loop reading the chain's VQ-VAE codes, trained on
50 DART demos, scored 978 (2000 steps), 984 (4000) and 981 (10 000) on seeds 0-19; the mid_loop is
the slow member (~15-25 steps/s), so more steps cost minutes without changing the reflex.
"""
from __future__ import annotations

import argparse
import json
import logging
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from pathlib import Path
from typing import Any

from hope_models.cli.argtypes import positive_int
from hope_models.cli.json_result import last_json_object

log = logging.getLogger("hope.demo")

REPO_ROOT = Path(__file__).resolve().parents[2]
SCRIPT = REPO_ROOT / "run_trainer.py"
COMPONENTS = ("vqvae", "fast_loop", "mid_loop")
DEMO_SEED = 100000  # sim-demos' default; evaluation uses seeds 0..N-1, so the two never overlap
GATE_WAIT_S = 900.0  # a promote child: validation batches and, for the fast_loop, reflex episodes
SERVE_WAIT_S = 60.0  # BrainService notices a pointer within a second; loading takes well under one
CLOSURE_WAIT_S = 5.0  # the loop-closure record is written beside the first answer, on its own thread
PLAIN_EVERY_S = 5.0  # progress lines when the output is not a terminal (a log, CI)


class Interrupted(Exception):
    """Ctrl-C (or SIGTERM) before the summary."""


class DemoError(Exception):
    """The demo cannot go on; the message says why."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from daemon.cli.serve import add_listen_arguments

    parser.add_argument("--episodes", type=positive_int, default=50, help="expert demonstrations to record (default 50)")
    parser.add_argument("--noise", type=float, default=1.0, help="DART noise of the demonstrations (default 1.0)")
    parser.add_argument("--steps", type=positive_int, default=4000, help="training steps of every component (default 4000)")
    parser.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    parser.add_argument("--eval-episodes", type=positive_int, default=20,
                        help="held-out reacher seeds 0..N-1 the reflex is evaluated on (default 20)")
    parser.add_argument("--target-return", type=float, default=900.0,
                        help="the mean return the promoted fast_loop must reach (default 900)")
    add_listen_arguments(parser)
    parser.add_argument("--queue", default="pi", help="the queue the demo's runs and its worker use (default pi)")
    parser.add_argument("--exit", action="store_true", help="stop after the summary instead of serving on")


# -- small helpers --------------------------------------------------------------------------------

def say(text: str = "") -> None:
    print(text, flush=True)


class Demo:
    def __init__(self, settings: Any, args: argparse.Namespace):
        self.settings = settings
        self.args = args
        self.shutdown = threading.Event()
        self.serve = None
        self.child: subprocess.Popen | None = None
        self.timings: dict[str, float] = {}
        self.started = time.monotonic()
        self.token: str | None = None
        self.url: str | None = None
        self.inference: dict[str, Any] | None = None
        self.first_observation: tuple[list[float], list[float]] | None = None

    # -- waiting that Ctrl-C can interrupt ------------------------------------------------------

    def check(self) -> None:
        if self.shutdown.is_set():
            raise Interrupted()

    def sleep(self, seconds: float) -> None:
        if self.shutdown.wait(seconds):
            raise Interrupted()

    def run_child(self, argv: list[str], timeout_s: float) -> tuple[int, str, str]:
        """A `run_trainer.py` child in its own session (Ctrl-C reaches us, and we stop it), its
        stdout captured, its stderr to a log file. Returns (exit code, stdout, stderr tail)."""
        env = {**os.environ, "HOPE_HOME": str(self.settings.home)}
        logs = Path(self.settings.home) / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        err_path = logs / "demo-child.log"
        with open(err_path, "ab") as err, subprocess.Popen(
                [sys.executable, str(SCRIPT), *argv], stdout=subprocess.PIPE, stderr=err, stdin=subprocess.DEVNULL,
                cwd=str(REPO_ROOT), env=env, start_new_session=True) as proc:
            self.child = proc
            out: list[bytes] = []
            reader = threading.Thread(target=lambda: out.append(proc.stdout.read()), daemon=True)
            reader.start()
            deadline = time.monotonic() + timeout_s
            try:
                while proc.poll() is None:
                    if time.monotonic() > deadline:
                        raise DemoError(f"`{' '.join(argv[:1])}` took longer than {timeout_s:.0f} s (see {err_path})")
                    self.sleep(0.2)
            finally:
                if proc.poll() is None:
                    proc.terminate()
                    try:
                        proc.wait(10)
                    except subprocess.TimeoutExpired:
                        proc.kill()
                self.child = None
            reader.join(5)
        tail = "\n".join(err_path.read_text(encoding="utf-8", errors="replace").splitlines()[-5:])
        return proc.returncode, b"".join(out).decode("utf-8", "replace"), tail

    # -- 1. demonstrations ----------------------------------------------------------------------

    def record_demos(self) -> Path:
        a = self.args
        out = Path(self.settings.home) / "demo" / f"reach-{a.episodes}-dart{a.noise:g}"
        if out.is_dir():
            say(f"1. demonstrations: reusing {out} ({a.episodes} episodes recorded earlier)")
            return out
        t0 = time.monotonic()
        say(f"1. demonstrations: recording {a.episodes} expert episodes of the reacher (DART noise {a.noise:g}, "
            f"seeds {DEMO_SEED}-{DEMO_SEED + a.episodes - 1}) ...")
        partial = out.with_name(out.name + ".partial")  # renamed when complete: a reuse never sees half a set
        shutil.rmtree(partial, ignore_errors=True)
        code, stdout, tail = self.run_child(
            ["sim-demos", "--episodes", str(a.episodes), "--out", str(partial), "--task", "reach",
             "--noise", str(a.noise), "--seed", str(DEMO_SEED), "--json"], timeout_s=1800)
        result = last_json_object(stdout)
        if code != 0 or not result or not result.get("ok"):
            raise DemoError(f"recording the demonstrations failed (exit {code}): "
                            f"{(result or {}).get('error') or tail}")
        partial.rename(out)
        self.timings["demos"] = time.monotonic() - t0
        say(f"   {len(result['episodes'])} episodes in {out}, the expert's mean return {result['mean_return']:.1f} "
            f"under the noise ({self.timings['demos']:.0f} s)")
        return out

    # -- 2. the services ------------------------------------------------------------------------

    def start_services(self) -> None:
        from daemon.cli.serve import Serve

        serve_args = argparse.Namespace(host=None, port=None, no_worker=False, queue=self.args.queue, tick=0.5)
        self.serve = Serve(self.settings, serve_args)
        self.token = self.serve.start()
        self.url = self.serve.server.url
        say(f"2. services: webapp + daemon + BrainService in this process, a worker child on queue "
            f"{self.args.queue} (embedded broker); logs in {Path(self.settings.home) / 'logs'}")
        say(f"   Robot Editor: {self.url}  token: {self.token}")

    # -- 3. the chain ---------------------------------------------------------------------------

    def queue_chain(self, data: Path) -> list[str]:
        from registry.sequences import create_sequence
        from registry.run_request import build_request

        a = self.args
        req = build_request(component=COMPONENTS[0], data=str(data), steps=a.steps, queue=a.queue,
                            overrides={"seed": a.seed})
        left = self._unfinished_chain(req.config())
        if left:
            self.serve.daemon.wake()
            say("3. training: resuming the chain an interrupted demo left (its runs resume from their "
                "checkpoints): " + ", ".join(f"{c} {i}" for c, i in zip(COMPONENTS, left)))
            return left
        with self.serve.registry.session() as s:
            members = create_sequence(s, COMPONENTS, req.config(), total_steps=req.steps,
                                      runs_dir=self.settings.runs_dir, queue=req.queue)
            ids = [r.id for r in members]
            seq = members[0].sequence_id
        self.serve.daemon.wake()
        say(f"3. training: queued the chain {','.join(COMPONENTS)} ({seq}), {a.steps} steps each: "
            + ", ".join(f"{c} {i}" for c, i in zip(COMPONENTS, ids)))
        return ids

    def _unfinished_chain(self, config: dict[str, Any]) -> list[str] | None:
        """The run ids of a demo chain with this same config that an interrupted demo left queued
        (Ctrl-C hands the running job back to the queue): finishing it beats queueing a second
        chain behind it."""
        from sqlalchemy import select

        from registry import runs
        from registry.models import Run

        with self.serve.registry.session(readonly=True) as s:
            seqs = s.scalars(select(Run.sequence_id).where(Run.sequence_id.is_not(None),
                                                           Run.state.in_(("queued", "starting", "running", "interrupted")),
                                                           Run.queue == self.args.queue).distinct()).all()
            for seq in seqs:
                members = runs.sequence_runs(s, seq)
                if [m.component for m in members] != list(COMPONENTS):
                    continue
                if any(m.state in ("failed", "cancelled", "paused") for m in members):
                    continue
                base = {k: v for k, v in members[0].config.items()}
                if base == config and all(m.total_steps == self.args.steps for m in members):
                    return [m.id for m in members]
        return None

    def _gating_idle(self) -> bool:
        """Auto-promotion has nothing running and nothing left to gate: waiting longer is useless."""
        promoter = getattr(self.serve.daemon, "autopromoter", None)
        return promoter is not None and not promoter.busy and promoter.next_run() is None

    def _runs(self, ids: list[str]) -> list[dict[str, Any]]:
        from registry import runs

        with self.serve.registry.session(readonly=True) as s:
            return [runs.get_run(s, i).to_json_obj() for i in ids]

    def _gate(self, run_id: str) -> dict[str, Any] | None:
        from daemon.demo_report import gate_outcome

        with self.serve.registry.session(readonly=True) as s:
            return gate_outcome(s, run_id)

    def follow_chain(self, ids: list[str]) -> list[dict[str, Any]]:
        """Progress until every member ended, closing the loop on the fast_loop on the way: as soon
        as it is promoted and served, one inference goes through the API (that is the moment a
        robot would get the new reflex; later, the mid_loop's training would count as closure)."""
        from daemon.cli.watch import Display, end_line, progress_line

        tty = sys.stdout.isatty()
        display = Display()
        ended: set[str] = set()
        last_plain = 0.0
        fast_id = ids[COMPONENTS.index("fast_loop")]
        t0 = time.monotonic()
        while True:
            objs = self._runs(ids)
            for obj in objs:
                if obj["state"] in ("completed", "failed", "cancelled") and obj["id"] not in ended:
                    ended.add(obj["id"])
                    display.close()
                    say("   " + end_line(obj).replace("\n", "\n   "))
            active = [o for o in objs if o["id"] not in ended]
            if not active:
                display.close()
                break
            current = next((o for o in active if o["state"] == "running"), active[0])
            if tty:
                display.show(current)
            elif time.monotonic() - last_plain >= PLAIN_EVERY_S:
                last_plain = time.monotonic()
                say("   " + progress_line(current))
            if self.inference is None and fast_id in ended:
                self._try_close_loop(fast_id, display)
            self.sleep(0.5)
        self.timings["training"] = time.monotonic() - t0
        return objs

    # -- 4. the loop closure: promoted, served, one inference over HTTP --------------------------

    def _try_close_loop(self, fast_id: str, display: Any = None) -> bool:
        """One look: if the fast_loop run was promoted and BrainService serves it, infer once."""
        gate = self._gate(fast_id)
        if gate is None or gate["state"] != "promoted":
            return False
        status = (self.serve.brain.status().get("fast_loop") or {})
        if status.get("version") != gate["version"]:
            return False
        if display is not None:
            display.close()
        say(f"4. promoted and served: fast_loop {gate['version']}")
        self.inference = self.infer_over_http()
        inf = self.inference
        if inf.get("error"):
            say(f"   inference failed: {inf['error']}")
        else:
            say(f"   POST /api/brain/infer -> action [{', '.join(f'{v:+.3f}' for v in inf['action'])}] "
                f"(expert [{', '.join(f'{v:+.3f}' for v in inf['expert_action'])}]), {inf['model_version']}, "
                f"{inf['latency_ms']:.2f} ms")
        return True

    def close_loop(self, fast_id: str) -> dict[str, Any] | None:
        """After the chain: wait for the fast_loop's gate and BrainService (when not done already)."""
        deadline = time.monotonic() + GATE_WAIT_S
        promoted_at: float | None = None
        while self.inference is None:
            gate = self._gate(fast_id)
            if gate is not None and gate["state"] != "promoted":
                return gate  # refused or failed: the summary says why
            now = time.monotonic()
            if gate is None and (now > deadline or self._gating_idle()):
                self.sleep(1.0)  # the daemon's next tick may just not have spawned the child yet
                if self._gate(fast_id) is None and self._gating_idle():
                    return None  # nothing will gate it (the summary says "not gated")
            if gate is None and now > deadline:
                raise DemoError(f"the fast_loop run {fast_id} was not gated within {GATE_WAIT_S:.0f} s "
                                f"(see {Path(self.settings.home) / 'logs' / 'promote.log'})")
            if gate is not None:
                promoted_at = promoted_at or now
                if now - promoted_at > SERVE_WAIT_S:
                    status = self.serve.brain.status().get("fast_loop") or {}
                    raise DemoError(f"BrainService does not serve {gate['version']} {SERVE_WAIT_S:.0f} s after its "
                                    f"promotion (serving {status.get('version')}; last error: "
                                    f"{status.get('last_error')})")
            self._try_close_loop(fast_id)
            self.sleep(0.3)
        return self._gate(fast_id)

    def _observation(self, data: Path) -> tuple[list[float], list[float]]:
        """The first step of the first demonstration: the observation vector in the spec's order
        (joint positions, joint velocities, target offset) and the expert's command there."""
        episode = sorted(p for p in data.iterdir() if p.is_dir())[0]
        with open(episode / "steps" / "000000.jsonl", encoding="utf-8") as f:
            step = json.loads(f.readline())
        o = step["observation"]
        obs = [*o["robot_state"]["joint_positions"], *o["robot_state"]["joint_velocities"], *o["target_offset"]]
        return [float(v) for v in obs], [float(v) for v in step["action"]["command"]]

    def infer_over_http(self) -> dict[str, Any]:
        obs, expert = self.first_observation
        body = json.dumps({"component": "fast_loop", "observation": obs, "session": "demo", "reset": True}).encode()
        req = urllib.request.Request(self.url.rstrip("/") + "/api/brain/infer", data=body, method="POST",
                                     headers={"Content-Type": "application/json",
                                              "Authorization": f"Bearer {self.token}"})
        try:
            with urllib.request.urlopen(req, timeout=10) as resp:
                answer = json.loads(resp.read())
        except urllib.error.HTTPError as exc:
            return {"error": f"HTTP {exc.code}: {exc.read().decode('utf-8', 'replace')[:300]}"}
        except (urllib.error.URLError, OSError, ValueError) as exc:
            return {"error": str(exc)}
        return {**answer, "observation": obs, "expert_action": expert}

    def loop_closure(self, fast_id: str) -> float | None:
        from registry import runs

        deadline = time.monotonic() + CLOSURE_WAIT_S
        while True:
            with self.serve.registry.session(readonly=True) as s:
                value = runs.get_run(s, fast_id).loop_closure_s
            if value is not None or time.monotonic() > deadline:
                return value
            self.sleep(0.2)

    def wait_gates(self, ids: list[str]) -> dict[str, dict[str, Any] | None]:
        """Every completed member's gate outcome (the mid_loop's gate runs after the chain ends)."""
        objs = {o["id"]: o for o in self._runs(ids)}
        deadline = time.monotonic() + GATE_WAIT_S
        while True:
            gates = {i: self._gate(i) for i in ids}
            pending = [i for i in ids if objs[i]["state"] == "completed" and gates[i] is None]
            if not pending or time.monotonic() > deadline:
                return gates
            if self._gating_idle():
                self.sleep(1.0)  # one more tick: a run that just completed is picked up then
                if self._gating_idle():
                    return {i: self._gate(i) for i in ids}
            self.sleep(0.5)

    # -- 5. the reflex ----------------------------------------------------------------------------

    def evaluate(self) -> dict[str, Any]:
        n = self.args.eval_episodes
        say(f"5. reflex: the promoted fast_loop in closed loop on held-out seeds 0-{n - 1}, with the expert "
            "and a random policy on the same seeds ...")
        t0 = time.monotonic()
        code, stdout, tail = self.run_child(["eval-reflex", "--checkpoint", "promoted", "--episodes", str(n),
                                             "--seed", "0", "--task", "reach", "--json"], timeout_s=1800)
        self.timings["reflex"] = time.monotonic() - t0
        result = last_json_object(stdout)
        if code != 0 or not result or result.get("ok") is False:
            return {"error": f"eval-reflex exited {code}: {(result or {}).get('error') or tail}"}
        keep = ("mean_return", "success_rate", "time_to_reach_s", "expert_mean_return", "random_mean_return",
                "episodes", "seeds", "version", "checkpoint", "elapsed_s")
        return {k: result.get(k) for k in keep}

    # -- the whole thing ----------------------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        from daemon.demo_report import component_figures

        data = self.record_demos()
        self.first_observation = self._observation(data)
        self.check()
        self.start_services()
        ids = self.queue_chain(data)
        objs = self.follow_chain(ids)
        fast_id = ids[COMPONENTS.index("fast_loop")]
        fast_obj = next(o for o in objs if o["id"] == fast_id)
        if fast_obj["state"] == "completed" and self.inference is None:
            self.close_loop(fast_id)
        gates = self.wait_gates(ids)
        served = (self.serve.brain.status().get("fast_loop") or {}).get("version")
        fast_gate = gates.get(fast_id)
        reflex = None
        if served:
            reflex = self.evaluate()
            if fast_gate and fast_gate.get("state") == "promoted" and reflex.get("version") not in (None,
                                                                                                 fast_gate["version"]):
                reflex["note"] = f"evaluated {reflex['version']}, not the demo's {fast_gate['version']}"
        else:
            reflex = {"error": "no fast_loop is promoted, so there is nothing to evaluate"}
        closure = self.loop_closure(fast_id) if self.inference and not self.inference.get("error") else None
        objs = self._runs(ids)
        self.timings["total"] = time.monotonic() - self.started
        return {
            "components": [component_figures(o, gates.get(o["id"])) for o in objs],
            "inference": self.inference,
            "reflex": reflex,
            "loop_closure_s": closure,
            "target_return": self.args.target_return,
            "served_version": served,
            "url": self.url,
            "data": str(data),
            "timings": {k: round(v, 1) for k, v in self.timings.items()},
        }

    def stop(self) -> None:
        child = self.child
        if child is not None and child.poll() is None:
            child.terminate()
        if self.serve is not None:
            self.serve.stop()


def run(args: argparse.Namespace) -> int:
    from registry.db import RegistryError
    from daemon.demo_report import format_summary, verdict
    from registry.run_request import RunRequestError
    from registry.runs import RunError
    from daemon.cli.serve import listen_settings, setup_logging
    from hope_models.settings import SettingsError
    from webapp.auth import TokenError
    from webapp.server import ServerError

    try:
        settings = listen_settings(args)
    except SettingsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not settings.auto_promote:
        say("note: auto_promote is off in the settings; the demo turns it on for this process (it gates each run)")
        settings.auto_promote = True
    setup_logging(settings.home, console_level=logging.WARNING)
    demo = Demo(settings, args)

    def on_signal(signum, _frame):
        if demo.serve is not None and demo.shutdown.is_set():
            demo.serve.force.set()  # a second Ctrl-C: do not wait for the running job
        demo.shutdown.set()
        if demo.serve is not None:
            demo.serve.shutdown.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    say(f"HOPE Seed Trainer demo: state in {settings.home}\n")
    try:
        try:
            summary = demo.run()
        except Interrupted:
            print("\ninterrupted: stopping (the running job checkpoints and goes back to the queue; "
                  "`run_trainer.py serve` resumes it)", file=sys.stderr, flush=True)
            demo.stop()
            return 130
        except (RegistryError, TokenError, ServerError, SettingsError, RunRequestError, RunError, OSError) as exc:
            print(f"error: {exc}", file=sys.stderr)
            demo.stop()
            return 2
        except DemoError as exc:
            print(f"error: {exc}", file=sys.stderr)
            demo.stop()
            return 1
        problems = verdict(summary, args.target_return)
        log.info("demo finished in %.0f s: %s", summary["timings"]["total"], "; ".join(problems) or "ok")
        summary["ok"] = not problems
        summary["problems"] = problems
        out = Path(settings.home) / "demo" / "summary.json"
        out.write_text(json.dumps(summary, indent=1), encoding="utf-8")
        say(format_summary(summary))
        say("")
        if problems:
            say("The demo fell short:\n" + "\n".join(f"  - {p}" for p in problems))
        else:
            say(f"The promoted fast_loop reaches {summary['reflex']['mean_return']:.1f} on held-out seeds "
                f"(target {args.target_return:g}). Whole demo {summary['timings']['total'] / 60:.1f} min.")
        say(f"\nsummary: {out}")
        say(f"Robot Editor: {demo.url}  token: {demo.token}")
        code = 1 if problems else 0
        if args.exit:
            demo.stop()
            return code
        say("serving until Ctrl-C (runs, models, live progress of new runs, inference and the reflex view)")
        while not demo.shutdown.is_set():
            demo.shutdown.wait(0.5)
        demo.stop()
        return code
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
