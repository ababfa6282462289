"""The demo's session (`hope-trainer demo`): records the demonstrations, starts what `serve` starts
in this process, trains the chain (hope_trainer/demo/chain.py), closes the loop
(hope_trainer/demo/closure.py), evaluates the reflex and returns the summary's figures.

Every torch or MuJoCo step runs as a `hope-trainer` child in its own session (hope_models/child_command.py),
so this process never imports either; a wait here ends with Interrupted on Ctrl-C.
"""
from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import threading
import time
from pathlib import Path
from typing import Any

from hope_models.child_command import trainer_argv
from hope_models.child_result import ChildResultError, read_result, result_argv, result_file
from hope_models.components import ACTOR
from hope_models.durable import fsync_path
from hope_models.log_limits import rotate_if_over
from hope_trainer.commands.serve import Serve
from hope_trainer.demo.chain import ChainSteps
from hope_trainer.demo.closure import ClosureSteps
from hope_trainer.demo.report import component_figures
from hope_trainer.demo.shared import COMPONENTS, DEMO_SEED, DemoError, Interrupted, say


class Demo(ChainSteps, ClosureSteps):
    """One demo from the recording to the summary's figures; `stop()` leaves nothing running."""

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
        self.inference_url: str | None = None  # the robot's door (webapp/inference_door.py)
        self.inference: dict[str, Any] | None = None
        self.first_observation: tuple[list[float], list[float]] | None = None

    # -- waiting that Ctrl-C can interrupt ------------------------------------------------------

    def check(self) -> None:
        if self.shutdown.is_set():
            raise Interrupted()

    def sleep(self, seconds: float) -> None:
        if self.shutdown.wait(seconds):
            raise Interrupted()

    def run_child(self, argv: list[str], timeout_s: float) -> tuple[int, dict[str, Any], str]:
        """A `hope-trainer` child in its own session (Ctrl-C reaches us, and we stop it), its stdout
        and stderr to a log file. Returns (exit code, the result it wrote to its --result-file,
        stderr tail); ChildResultError (naming the command and its exit code) when it wrote none."""
        with result_file("hope-demo-") as path:
            full = trainer_argv(*argv, *result_argv(path))
            code, tail = self._run(argv, full, timeout_s)
            return code, read_result(path, full, code), tail

    def _run(self, argv: list[str], full: list[str], timeout_s: float) -> tuple[int, str]:
        env = {**os.environ, "HOPE_HOME": str(self.settings.home)}
        logs = Path(self.settings.home) / "logs"
        logs.mkdir(parents=True, exist_ok=True)
        err_path = logs / "demo-child.log"
        rotate_if_over(err_path, self.settings)
        with open(err_path, "ab") as err, subprocess.Popen(
                full, stdout=err, stderr=err, stdin=subprocess.DEVNULL, env=env, start_new_session=True) as proc:
            self.child = proc
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
        tail = "\n".join(err_path.read_text(encoding="utf-8", errors="replace").splitlines()[-5:])
        return proc.returncode, tail

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
        # A directory of episodes cannot be written as one file: it is recorded beside its final name
        # and renamed when complete (the rename made durable), so a reuse never sees half a set.
        partial = out.with_name(out.name + ".partial")
        shutil.rmtree(partial, ignore_errors=True)
        try:
            code, result, tail = self.run_child(
                ["sim-demos", "--episodes", str(a.episodes), "--out", str(partial), "--task", "reach",
                 "--noise", str(a.noise), "--seed", str(DEMO_SEED), "--json"], timeout_s=1800)
        except ChildResultError as exc:
            raise DemoError(f"recording the demonstrations failed: {exc}") from None
        if code != 0 or not result.get("ok"):
            raise DemoError(f"recording the demonstrations failed (exit {code}): {result.get('error') or tail}")
        partial.rename(out)
        fsync_path(out.parent)
        self.timings["demos"] = time.monotonic() - t0
        say(f"   {len(result['episodes'])} episodes in {out}, the expert's mean return {result['mean_return']:.1f} "
            f"under the noise ({self.timings['demos']:.0f} s)")
        return out

    # -- 2. the services ------------------------------------------------------------------------

    def start_services(self) -> None:
        serve_args = argparse.Namespace(host=None, port=None, no_worker=False, queue=self.args.queue, tick=0.5)
        self.serve = Serve(self.settings, serve_args)
        self.token = self.serve.start()
        self.url = self.serve.server.url
        self.inference_url = self.serve.door.url
        say(f"2. services: webapp + daemon + BrainService in this process, a worker child on queue "
            f"{self.args.queue} (embedded broker) and the robot's inference door as another; "
            f"logs in {Path(self.settings.home) / 'logs'}")
        say(f"   Robot Editor: {self.url}  token: {self.token}")
        say(f"   inference (the robot's port): {self.inference_url}api/brain/infer")

    # -- 3. the chain: demo/chain.py; 4. the loop closure: demo/closure.py ------------------------

    # -- 5. the reflex ----------------------------------------------------------------------------

    def evaluate(self) -> dict[str, Any]:
        n = self.args.eval_episodes
        say(f"5. reflex: the promoted fast_loop in closed loop on held-out seeds 0-{n - 1}, with the expert "
            "and a random policy on the same seeds ...")
        t0 = time.monotonic()
        try:
            code, result, tail = self.run_child(["eval-reflex", "--checkpoint", "promoted", "--episodes", str(n),
                                                 "--seed", "0", "--task", "reach", "--json"], timeout_s=1800)
        except ChildResultError as exc:
            return {"error": str(exc)}
        finally:
            self.timings["reflex"] = time.monotonic() - t0
        if code != 0 or result.get("ok") is False:
            return {"error": f"eval-reflex exited {code}: {result.get('error') or tail}"}
        keep = ("mean_return", "success_rate", "time_to_reach_s", "expert_mean_return", "random_mean_return",
                "episodes", "seeds", "version", "checkpoint", "elapsed_s")
        return {k: result.get(k) for k in keep}

    # -- the whole thing ----------------------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        data = self.record_demos()
        self.first_observation = self._observation(data)
        self.check()
        self.start_services()
        ids = self.queue_chain(data)
        objs = self.follow_chain(ids)
        fast_id = ids[COMPONENTS.index(ACTOR)]
        fast_obj = next(o for o in objs if o["id"] == fast_id)
        if fast_obj["state"] == "completed" and self.inference is None:
            self.close_loop(fast_id)
        gates = self.wait_gates(ids)
        served = (self.serve.brain.status().get(ACTOR) or {}).get("version")
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
        brain = self.brain_inference(gates, ids, data)
        objs = self._runs(ids)
        self.timings["total"] = time.monotonic() - self.started
        return {
            "components": [component_figures(o, gates.get(o["id"])) for o in objs],
            "inference": self.inference,
            "brain": brain,
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
