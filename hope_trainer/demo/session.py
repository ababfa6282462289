"""The demo's session (`hope-trainer demo`): records the demonstrations, starts what `serve` starts
in this process, trains the chain (hope_trainer/demo/chain.py), closes the loop
(hope_trainer/demo/closure.py), evaluates the reflex and returns the summary's figures.

Every torch or MuJoCo step runs as a `hope-trainer` child in its own session (hope_models/child_command.py),
so this process never imports either; a wait here ends with Interrupted on Ctrl-C.
"""
from __future__ import annotations

import argparse
import shutil
import threading
import time
from pathlib import Path
from typing import Any

from hope_models.child_result import ChildResultError
from hope_models.components import ACTOR
from hope_models.durable import fsync_path
from hope_trainer.commands.serve import Serve
from hope_trainer.demo.chain import ChainSteps
from hope_trainer.demo.children import ChildGroup
from hope_trainer.demo.closure import ClosureSteps
from hope_trainer.demo.report import component_figures, merge_evaluations, split_range
from hope_trainer.demo.shared import COMPONENTS, DEMO_SEED, DemoError, Interrupted, say


class Demo(ChainSteps, ClosureSteps):
    """One demo from the recording to the summary's figures; `stop()` leaves nothing running."""

    recorded = "expert episodes of the reacher"  # what step 1 says it records

    def __init__(self, settings: Any, args: argparse.Namespace):
        self.settings = settings
        self.args = args
        self.shutdown = threading.Event()
        self.serve = None
        self.groups: list[ChildGroup] = []  # the children running now (children.py)
        self.timings: dict[str, float] = {}
        self.started = time.monotonic()
        self.token: str | None = None
        self.url: str | None = None
        self.inference_url: str | None = None  # the robot's door (webapp/inference_door.py)
        self.inference: dict[str, Any] | None = None
        self.door_answer: dict[str, Any] | None = None  # the robot's port before it served the promoted fast_loop
        self.first_observation: tuple[dict[str, Any], list[float]] | None = None
        self.eval_started = time.monotonic()

    # -- waiting that Ctrl-C can interrupt ------------------------------------------------------

    def check(self) -> None:
        if self.shutdown.is_set():
            raise Interrupted()

    def sleep(self, seconds: float) -> None:
        if self.shutdown.wait(seconds):
            raise Interrupted()

    def run_child(self, argv: list[str], timeout_s: float) -> tuple[int, dict[str, Any], str]:
        """A `hope-trainer` child (children.py): (exit code, the result it wrote to its
        --result-file, stderr tail); ChildResultError (naming the command and its exit code) when
        it wrote none."""
        return self.run_children([argv], timeout_s)[0]

    def run_children(self, argvs: list[list[str]], timeout_s: float) -> list[tuple[int, dict[str, Any], str]]:
        """`hope-trainer` children started together and waited for together (run_child's, each)."""
        return self.wait_children(self.start_children(argvs), timeout_s)

    def start_children(self, argvs: list[list[str]]) -> ChildGroup:
        group = ChildGroup(argvs, self.settings)
        self.groups.append(group)  # before they start: stop() ends them whatever happens next
        return group.start()

    def wait_children(self, group: ChildGroup, timeout_s: float) -> list[tuple[int, dict[str, Any], str]]:
        """Until every child of `group` exited (Interrupted on Ctrl-C; DemoError after `timeout_s`),
        then their results; the group is stopped and its files removed either way."""
        deadline = time.monotonic() + timeout_s
        try:
            while group.running():
                if time.monotonic() > deadline:
                    raise DemoError(f"{group.what()} took longer than {timeout_s:.0f} s (see {group.log_path})")
                self.sleep(0.2)
            return group.results()
        finally:
            group.close()
            self.groups.remove(group)

    # -- 1. demonstrations ----------------------------------------------------------------------

    def data_dir(self) -> Path:
        a = self.args
        return Path(self.settings.home) / "demo" / f"reach-{a.episodes}-dart{a.noise:g}"

    def recording_argvs(self, out: Path) -> list[list[str]]:
        """The sim-demos children that record the demonstrations into `out`."""
        a = self.args
        return [["sim-demos", "--episodes", str(a.episodes), "--out", str(out), "--task", "reach",
                 "--noise", str(a.noise), "--seed", str(DEMO_SEED), "--json"]]

    def record_demos(self) -> Path:
        a = self.args
        out = self.data_dir()
        if out.is_dir():
            say(f"1. demonstrations: reusing {out} ({a.episodes} episodes recorded earlier)")
            return out
        t0 = time.monotonic()
        # A directory of episodes cannot be written as one file: it is recorded beside its final name
        # and renamed when complete (the rename made durable), so a reuse never sees half a set.
        partial = out.with_name(out.name + ".partial")
        shutil.rmtree(partial, ignore_errors=True)
        argvs = self.recording_argvs(partial)
        say(f"1. demonstrations: recording {a.episodes} {self.recorded} (DART noise {a.noise:g}, "
            f"seeds {DEMO_SEED}-{DEMO_SEED + a.episodes - 1})"
            + (f" in {len(argvs)} processes" if len(argvs) > 1 else "") + " ...")
        try:
            done = self.run_children(argvs, timeout_s=1800)
        except ChildResultError as exc:
            raise DemoError(f"recording the demonstrations failed: {exc}") from None
        for code, result, tail in done:
            if code != 0 or not result.get("ok"):
                raise DemoError(f"recording the demonstrations failed (exit {code}): {result.get('error') or tail}")
        partial.rename(out)
        fsync_path(out.parent)
        self.timings["demos"] = time.monotonic() - t0
        episodes = sum(len(r["episodes"]) for _, r, _ in done)
        mean = sum(r["mean_return"] * len(r["episodes"]) for _, r, _ in done) / episodes
        say(f"   {episodes} episodes in {out}, the expert's mean return {mean:.1f} "
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

    eval_processes = 1  # eval-reflex children the held-out seeds are split over

    def eval_argvs(self) -> list[list[str]]:
        """eval-reflex children of the promoted fast_loop over held-out seeds 0..N-1, one seed range each."""
        return [["eval-reflex", "--checkpoint", "promoted", "--episodes", str(count), "--seed", str(first),
                 "--task", "reach", "--json"] for first, count in split_range(self.args.eval_episodes,
                                                                              self.eval_processes)]

    def start_evaluation(self) -> ChildGroup:
        n = self.args.eval_episodes
        argvs = self.eval_argvs()
        say(f"5. reflex: the promoted fast_loop in closed loop on held-out seeds 0-{n - 1}, with the expert "
            "and a random policy on the same seeds" + (f" ({len(argvs)} processes)" if len(argvs) > 1 else "")
            + " ...")
        self.eval_started = time.monotonic()
        return self.start_children(argvs)

    def finish_evaluation(self, group: ChildGroup) -> dict[str, Any]:
        try:
            done = self.wait_children(group, timeout_s=1800)
        except ChildResultError as exc:
            return {"error": str(exc)}
        finally:
            self.timings["reflex"] = time.monotonic() - self.eval_started
        for code, result, tail in done:
            if code != 0 or result.get("ok") is False:
                return {"error": f"eval-reflex exited {code}: {result.get('error') or tail}"}
        return merge_evaluations([result for _, result, _ in done])

    def evaluate(self) -> dict[str, Any]:
        return self.finish_evaluation(self.start_evaluation())

    # -- where the camera demo (camera.py) asks more: a stage that fails stops it -------------------

    def loop_closed(self) -> None:
        """Called once the first inference through the API came back (or failed)."""

    def check_chain(self, objs: list[dict[str, Any]]) -> None:
        """After every member ended (here a failed member is a line of the summary)."""

    def check_reflex(self, fast_gate: dict[str, Any] | None, reflex: dict[str, Any]) -> None:
        """After the reflex's evaluation, or the reason there was none."""

    def summary_path(self) -> Path:
        return Path(self.settings.home) / "demo" / "summary.json"

    # -- the whole thing ----------------------------------------------------------------------------

    def run(self) -> dict[str, Any]:
        data = self.record_demos()
        self.first_observation = self._observation(data)
        self.check()
        self.start_services()
        ids = self.queue_chain(data)
        objs = self.follow_chain(ids)
        self.check_chain(objs)
        fast_id = ids[COMPONENTS.index(ACTOR)]
        fast_obj = next(o for o in objs if o["id"] == fast_id)
        if fast_obj["state"] == "completed" and self.inference is None:
            self.close_loop(fast_id)
        gates = self.wait_gates(ids)
        # the whole brain as soon as the chain is served: its first answer closes the Mid Loop's loop
        brain = self.brain_inference(gates, ids, data)
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
        self.check_reflex(fast_gate, reflex)
        closure = self.loop_closure(fast_id) if self.inference and not self.inference.get("error") else None
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
        for group in list(self.groups):
            group.close()  # stopped, and its result files removed
        if self.serve is not None:
            self.serve.stop()
