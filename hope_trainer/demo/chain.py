"""Step 3 of the demo: queue the chain vqvae, fast_loop, mid_loop (or pick up the one an interrupted
demo left) and follow it in the terminal until every member ended.

`ChainSteps` is a part of `Demo` (hope_trainer/demo/session.py): it reads the session's `serve`,
`args`, `settings`, `timings` and `inference`, and waits with its `sleep` (which Ctrl-C ends).
"""
from __future__ import annotations

import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, Any

from daemon.cli.watch import Display, end_line, progress_line
from hope_models.components import ACTOR, PREDICTOR, TOKENIZER
from hope_trainer.demo.shared import COMPONENTS, PLAIN_EVERY_S, say
from registry.run_request import build_request

if TYPE_CHECKING:
    from hope_models.settings import Settings

VQVAE_RUN = "vqvae_run"  # the config key create_sequence gives each member that reads the chain's tokenizer
# The state demo's steps per member, unless --steps gives every member one count. The Mid Loop's
# held-out figures are best near 1000 steps on the 50 demos and only worse after (it overfits:
# docs/training.md, "How many steps"), and it is the slow member; the module doc of
# commands/demo.py says why the others' 4000.
STATE_STEPS = {TOKENIZER: 4000, ACTOR: 4000, PREDICTOR: 1000}
# The Mid Loop's torch threads: the cores this machine gives the demo, up to the 2 measured. With
# OpenMP's passive waits (hope_models/omp_wait.py) 2 threads made its step 1.6x faster than 1 even
# beside other jobs, and its held-out figures equal to 3 decimals after 1000 steps (docs/benchmarks.md,
# "The demo's Mid Loop"); more were not tried. The other members keep the loop's one thread: theirs
# were not measured.
MAX_MID_THREADS = 2


def mid_loop_threads() -> int:
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # no affinity call on this OS: the count of its CPUs
        cores = os.cpu_count() or 1
    return max(1, min(cores, MAX_MID_THREADS))


class ChainSteps:
    # what Demo (session.py) provides; annotations only, nothing is set here
    serve: Any
    args: Any
    settings: Settings
    timings: dict[str, float]
    inference: dict[str, Any] | None

    if TYPE_CHECKING:
        def sleep(self, seconds: float) -> None: ...
        def _try_close_loop(self, fast_id: str, display: Any = None) -> bool: ...

    def member_configs(self, data: Path) -> dict[str, dict[str, Any]]:
        """Each member's run config (its `config` column, checked as a run request's), by component:
        here each member trains its STATE_STEPS (or every member --steps) with the demo's seed, the
        Mid Loop on mid_loop_threads()."""
        a = self.args
        extra = {PREDICTOR: {"threads": mid_loop_threads()}}
        return {name: build_request(component=name, data=str(data), steps=a.steps or STATE_STEPS[name], queue=a.queue,
                                    overrides={"seed": a.seed, **extra.get(name, {})}).config() for name in COMPONENTS}

    def queue_chain(self, data: Path) -> list[str]:
        from registry.sequences import create_sequence  # lazy: loads sqlalchemy

        a = self.args
        configs = self.member_configs(data)
        left = self._unfinished_chain(configs)
        if left:
            self.serve.daemon.wake()
            say("3. training: resuming the chain an interrupted demo left (its runs resume from their "
                "checkpoints): " + ", ".join(f"{c} {i}" for c, i in zip(COMPONENTS, left, strict=False)))
            return left
        first = configs[COMPONENTS[0]]
        with self.serve.registry.session() as s:
            members = create_sequence(s, COMPONENTS, first, total_steps=first["steps"],
                                      runs_dir=self.settings.runs_dir, queue=a.queue, member_configs=configs)
            ids = [r.id for r in members]
            seq = members[0].sequence_id
        self.serve.daemon.wake()
        steps = {c["steps"] for c in configs.values()}
        each = (f"{steps.pop()} steps each" if len(steps) == 1
                else ", ".join(f"{name} {cfg['steps']}" for name, cfg in configs.items()) + " steps")
        say(f"3. training: queued the chain {','.join(COMPONENTS)} ({seq}), {each}: "
            + ", ".join(f"{c} {i}" for c, i in zip(COMPONENTS, ids, strict=False)))
        return ids

    def _unfinished_chain(self, configs: dict[str, dict[str, Any]]) -> list[str] | None:
        """The run ids of a demo chain with these same member configs that an interrupted demo left
        queued (Ctrl-C hands the running job back to the queue): finishing it beats queueing a
        second chain behind it."""
        from sqlalchemy import select  # lazy: loads sqlalchemy

        from registry import runs  # lazy: loads sqlalchemy
        from registry.models import Run  # lazy: loads sqlalchemy

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
                # the chain gave each member after the tokenizer its run id: the rest must be equal
                if all({k: v for k, v in m.config.items() if k != VQVAE_RUN} == configs[m.component]
                       and m.total_steps == configs[m.component]["steps"] for m in members):
                    return [m.id for m in members]
        return None

    def _runs(self, ids: list[str]) -> list[dict[str, Any]]:
        from registry import runs  # lazy: loads sqlalchemy

        with self.serve.registry.session(readonly=True) as s:
            return [runs.get_run(s, i).to_json_obj() for i in ids]

    def follow_chain(self, ids: list[str]) -> list[dict[str, Any]]:
        """Progress until every member ended, closing the loop on the fast_loop on the way: as soon
        as it is promoted and served, one inference goes through the API (that is the moment a
        robot would get the new reflex; later, the mid_loop's training would count as closure)."""
        tty = sys.stdout.isatty()
        display = Display()
        ended: set[str] = set()
        last_plain = 0.0
        fast_id = ids[COMPONENTS.index(ACTOR)]
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
