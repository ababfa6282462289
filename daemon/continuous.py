"""Continuous learning: the daemon queues a chain on the inbox by itself when enough new data came.

    policy = ContinuousLearning(settings, registry, local_queues=("pi",), disk_guard=..., autopromoter=...)
    decision = policy.tick(sample, throttle_level)   # each daemon tick, before dispatch

Each tick it decides one phase and writes it to the registry when it changed (registry/learning.py;
the webapp's GET /api/learning/status reads it from there), first match wins:

    paused                 the app paused learning (the runs it paused stay paused; a run a worker
                           claims meanwhile is paused too); nothing is dispatched on local queues
    training <component>   a run is active on a local queue
    waiting to cool / waiting for memory / waiting for disk
                           a local run the daemon paused for the host, or one queued but held back
    starting <component>   a run is queued on a local queue and about to start
    gating <component>     the auto-promoter's gate is running on a completed run
    idle                   auto_train is off (or the last attempt to queue could not be queued)
    waiting for data       fewer than auto_train_min_new_episodes new trainable episodes for every
                           component (the decision says how many more)
    waiting to cool        the temperature is at or above thermal_soft_c, or the host is throttled
    waiting for memory     less than memory_budget_mb available
    waiting for disk       the free space under $HOPE_HOME below the dispatch floor (disk_guard.py)

When none holds it back, it queues a chain (registry/sequences.py, as `sequential` does) of the
auto_train_components that have at least auto_train_min_new_episodes new trainable episodes, on
the inbox dataset (settings.inbox_dir; its cache fingerprint changes as episodes are added, so
each chain trains a new dataset version), auto_train_steps steps each (0 = TrainConfig's default).
An episode is new for a component when the inbox manifest says it can train it and the last auto
run of that component was not queued for it (the watermark, per component, in the registry, so a
restart neither forgets nor repeats). The chain, the watermark and the reason (a `log` event on
each member, and the registry row's last_auto_reason) are written in one transaction. The gate,
the auto-promotion and BrainService's hot reload take it from there, as for any completed run.
A mid_loop without a vqvae in its chain reads the codes of the VQ-VAE being served.
The daemon never imports torch: the inbox is read from its manifest.
"""
from __future__ import annotations

import logging
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Iterable

from sqlalchemy import select

from hope_models import disk
from hope_models.components import NEEDS_VQVAE, TOKENIZER
from hope_models.intake.inbox import InboxError, list_inbox
from registry import learning, runs
from registry.models import LearningState, Model, Run
from registry.run_request import RunRequestError, build_request, check_vqvae_run, preflight
from registry.sequences import create_sequence

log = logging.getLogger(__name__)

# a host-waiting phase whose only change is a live figure in its detail (a temperature, megabytes)
# is rewritten at most this often; every other change of the decision is written at once
DETAIL_EVERY_S = 15.0
LIVE_PHASES = ("waiting to cool", "waiting for memory", "waiting for disk")


@dataclass
class Decision:
    phase: str
    detail: str | None = None
    data: dict[str, Any] = field(default_factory=dict)
    sequence_id: str | None = None  # set when this tick queued an auto chain


def read_inbox(inbox_dir: Path) -> dict[str, set[str]]:
    """{episode_id: the components it can train} from the inbox's manifest ({} when there is none;
    a rejected episode trains nothing). hope_models/data/inbox.py raises InboxError for a manifest
    that is not ours."""
    return {e["episode_id"]: set(e["trainable"]) for e in list_inbox(inbox_dir)
            if e.get("status") != "rejected" and e.get("episode_id")}


class InboxCounter:
    """The inbox's trainable episodes, re-read only when its manifest changed on disk."""

    def __init__(self, inbox_dir: Path, reader: Callable[[Path], dict[str, set[str]]] = read_inbox):
        self.inbox_dir, self.reader = Path(inbox_dir), reader
        self._stamp: tuple | None = None
        self._episodes: dict[str, set[str]] = {}

    def episodes(self) -> dict[str, set[str]]:
        try:
            st = (self.inbox_dir / "manifest.json").stat()
            stamp = (st.st_ino, st.st_mtime_ns, st.st_size)
        except FileNotFoundError:
            stamp = None
        if stamp is None:
            self._stamp, self._episodes = None, {}
        elif stamp != self._stamp:
            self._episodes, self._stamp = self.reader(self.inbox_dir), stamp
        return self._episodes

    def trainable(self, components: Iterable[str]) -> dict[str, set[str]]:
        eps = self.episodes()
        return {c: {eid for eid, can in eps.items() if c in can} for c in components}


class ContinuousLearning:
    def __init__(self, settings: Any, registry: Any, *, local_queues: Iterable[str] = ("pi",),
                 disk_guard: Any = None, autopromoter: Any = None, inbox_reader: Callable | None = None,
                 free_mb: Callable[[Any], float | None] = disk.free_mb, clock: Callable[[], float] = time.monotonic):
        self.settings, self.registry = settings, registry
        self.local_queues = sorted(set(local_queues))
        self.queue = tuple(local_queues)[0]  # where auto chains go: the daemon's own worker
        self.disk_guard, self.autopromoter = disk_guard, autopromoter
        self.inbox = InboxCounter(settings.inbox_dir, *(() if inbox_reader is None else (inbox_reader,)))
        self.free_mb, self.clock = free_mb, clock
        self._written: tuple[str, str | None, float] | None = None
        self._refused: tuple | None = None  # (inbox state, message) of a chain that could not be queued
        self._marks: tuple[str | None, dict[str, set[str]]] | None = None  # (last auto sequence, watermark)
        self._failures = 0
        self.last: Decision | None = None

    def start(self) -> None:
        with self.registry.session() as s:
            learning.set_local_queues(s, self.local_queues)

    # -- the tick -----------------------------------------------------------------------------

    def tick(self, sample: dict[str, Any], throttle_level: int = 0) -> Decision:
        """Never raises for a fault of its own: the rest of the daemon's tick (dispatch above all)
        must go on; the fault is the phase's detail and in the log (once per streak)."""
        try:
            decision = self._busy(throttle_level) or self._decide(sample or {}, throttle_level)
            self._failures = 0
        except Exception as exc:  # noqa: BLE001
            self._failures += 1
            if self._failures == 1 or self._failures % 100 == 0:
                log.exception("continuous learning failed (%d in a row)", self._failures)
            decision = Decision("idle", f"continuous learning failed: {type(exc).__name__}: {exc} (see the daemon's "
                                "log); retried every tick")
        self._write(decision)
        self.last = decision
        return decision

    def _busy(self, level: int = 0) -> Decision | None:
        """The phases the registry alone decides: paused, a local run training or waiting."""
        with self.registry.session(readonly=True) as s:
            state = learning.read(s)
            local = s.scalars(select(Run).where(Run.queue.in_(self.local_queues),
                                                Run.state.in_(("queued", "starting", "running", "paused")))
                              .order_by(Run.created_at)).all()
            paused = bool(state is not None and state.paused)
            unheld = [r.id for r in local if r.state in runs.ACTIVE and
                      not (r.state == "running" and r.desired_state != "run")]
            if not paused:
                return self._local_phase(local, level)
        if unheld:
            with self.registry.session() as s:
                learning.hold_active(s, self.local_queues)
        return Decision("paused", "paused from the app; the local queues are held")

    def _local_phase(self, local: list[Run], level: int) -> Decision | None:
        active = [r for r in local if r.state in runs.ACTIVE]
        if active:
            return Decision(f"training {active[0].component}", f"run {active[0].id}")
        host = [r for r in local if r.state == "paused" and r.pause_reason in learning.HOST_PAUSES]
        if host:
            run = host[0]
            assert run.pause_reason is not None  # one of HOST_PAUSES (the filter above)
            phase = {"thermal": "waiting to cool", "memory": "waiting for memory", "disk": "waiting for disk"}
            return Decision(phase[run.pause_reason], f"run {run.id} ({run.component}) paused for {run.pause_reason}")
        queued = [r for r in local if r.state == "queued"]
        if queued:
            run = queued[0]
            if run.error_message:  # the dispatcher's hold (disk floor)
                return Decision("waiting for disk", run.error_message)
            if level >= 2:  # dispatch starts nothing here on a hot host
                return Decision("waiting to cool", f"run {run.id} ({run.component}) is queued; throttle level {level}")
            return Decision(f"starting {run.component}", f"run {run.id} is queued")
        return None

    def _gating(self) -> Decision | None:
        run_id = getattr(self.autopromoter, "current_run", None)
        if not run_id:
            return None
        with self.registry.session(readonly=True) as s:
            run = s.get(Run, run_id)
            component = run.component if run is not None else "a run"
        return Decision(f"gating {component}", f"the gate is judging run {run_id}")

    def _decide(self, sample: dict[str, Any], level: int) -> Decision:
        gating = self._gating()
        if gating is not None:
            return gating
        if not self.settings.auto_train:
            return Decision("idle", "auto_train is off")
        components = list(self.settings.auto_train_components)
        minimum = int(self.settings.auto_train_min_new_episodes)
        marks = self._watermark()
        try:
            trainable = self.inbox.trainable(components)
        except InboxError as exc:  # said in the phase; everything else in the daemon goes on
            return Decision("idle", f"the inbox cannot be read: {exc.message}")
        new = {c: trainable[c] - marks.get(c, set()) for c in components}
        counts = {c: len(ids) for c, ids in new.items()}
        ready = [c for c in components if counts[c] >= minimum]
        data = {"new_episodes": counts, "min_new_episodes": minimum}
        if not ready:
            more = minimum - max(counts.values(), default=0)
            return Decision("waiting for data", f"{more} more new trainable episode(s) needed in "
                            f"{self.settings.inbox_dir} (new: {_counts(counts)})",
                            {**data, "more_needed": more, "next_components": []})
        data["next_components"] = ready
        held = self._host_condition(sample, level)
        if held is not None:
            held.data.update(data)
            return held
        stamp = (self.inbox._stamp, self._marks[0] if self._marks else None)
        if self._refused is not None and self._refused[0] == stamp:
            return Decision("idle", f"the last auto chain could not be queued: {self._refused[1]}; waiting for the "
                            "inbox to change", data)
        return self._start(ready, new, trainable, sample, data, stamp)

    def _watermark(self) -> dict[str, set[str]]:
        """The registry's watermark, read again only when a new auto run was recorded (it can hold
        thousands of ids; the daemon ticks twice a second)."""
        with self.registry.session(readonly=True) as s:
            seq = s.scalar(select(LearningState.last_auto_sequence_id).where(LearningState.id == learning.ROW_ID))
            if self._marks is None or self._marks[0] != seq:
                self._marks = (seq, learning.watermark(s))
        return self._marks[1]

    def _host_condition(self, sample: dict[str, Any], level: int) -> Decision | None:
        temp, soft = sample.get("temp_c"), float(self.settings.thermal_soft_c)
        if level > 0 or (temp is not None and temp >= soft):
            shown = "unknown" if temp is None else f"{temp:.1f} C"
            return Decision("waiting to cool", f"{shown} (below {soft:.1f} C and throttle level 0 needed; "
                            f"level {level})", {"temp_c": temp})
        mem, budget = sample.get("mem_available_mb"), float(self.settings.memory_budget_mb)
        if mem is None or mem < budget:
            shown = "unknown" if mem is None else f"{mem:.0f} MB"
            return Decision("waiting for memory", f"{shown} available, memory_budget_mb {budget:.0f} MB needed",
                            {"mem_available_mb": mem})
        free, floor = self.free_mb(self.settings.home), self._disk_floor_mb()
        if free is not None and free < floor:
            return Decision("waiting for disk", f"{free:.0f} MB free under {self.settings.home}, below the floor "
                            f"of {floor:.0f} MB", {"disk_free_mb": free})
        return None

    def _disk_floor_mb(self) -> float:
        if self.disk_guard is None:
            return disk.dispatch_floor_mb(0.0, 1, self.settings.disk_floor_mb)
        with self.registry.session(readonly=True) as s:
            return max(self.disk_guard.floor_mb(s, Run(id=f"auto-train:{c}", component=c, config={
                "data": str(self.settings.inbox_dir)}, run_dir=str(Path(self.settings.runs_dir) / "auto-train")))
                for c in self.settings.auto_train_components)

    # -- queueing the chain --------------------------------------------------------------------

    def _chain(self, ready: list[str], trainable: dict[str, set[str]]) -> tuple[list[str], str | None, str]:
        """The chain's components, the served VQ-VAE's run a mid_loop without a vqvae reads, a note."""
        chain = list(ready)
        if not any(c in NEEDS_VQVAE for c in chain) or TOKENIZER in chain:
            return chain, None, ""
        with self.registry.session(readonly=True) as s:
            served = s.scalars(select(Model.run_id).join(Run, Run.id == Model.run_id).where(
                Model.component == TOKENIZER, Model.promoted_at.is_not(None), Run.state == "completed")).first()
        if served is not None:
            return chain, served, f"; codes from the served VQ-VAE (run {served})"
        needing = ", ".join(c for c in chain if c in NEEDS_VQVAE)
        if trainable.get(TOKENIZER):
            return [TOKENIZER, *chain], None, f"; {TOKENIZER} added: no VQ-VAE is served for the {needing}'s codes"
        kept = [c for c in chain if c not in NEEDS_VQVAE]
        return kept, None, f"; {needing} left out: no VQ-VAE is served and none can be trained"

    def _start(self, ready, new, trainable, sample, data, stamp) -> Decision:
        chain, vqvae_run, note = self._chain(ready, trainable)
        if not chain:
            return Decision("idle", note.lstrip("; "), data)
        with self.registry.session(readonly=True) as s:
            state = learning.read(s)
            since = f"since run {state.last_auto_sequence_id}" if state and state.last_auto_sequence_id else \
                "(no auto run before)"
        union = set().union(*(new[c] for c in chain if c in new))
        free = self.free_mb(self.settings.home)
        reason = (f"auto-train: {len(union)} new trainable episodes in {self.settings.inbox_dir} {since} "
                  f"({', '.join(f'{c}: {len(new.get(c, ()))}' for c in chain)}); host idle, "
                  f"{_fmt(sample.get('temp_c'), '{:.1f} C', 'temperature unknown')}, "
                  f"{_fmt(sample.get('mem_available_mb'), '{:.0f} MB memory available', 'memory unknown')}, "
                  f"{_fmt(free, '{:.0f} MB disk free', 'disk free unknown')}{note}")
        steps = int(self.settings.auto_train_steps) or None
        try:
            req = build_request(component=chain[0], data=str(self.settings.inbox_dir), steps=steps, queue=self.queue,
                                vqvae_run=vqvae_run, base=Path(self.settings.datasets_dir))
            with self.registry.session(readonly=True) as s:
                vqvae_dir = check_vqvae_run(s, req.vqvae_run)
            preflight(self.settings, req, chain, vqvae_run_dir=vqvae_dir)
            with self.registry.session() as s:
                members = create_sequence(s, chain, req.config(), total_steps=req.steps, runs_dir=self.settings.runs_dir,
                                          queue=req.queue, priority=req.priority, max_attempts=req.max_attempts)
                payload = {"reason": reason, "new_episodes": {c: len(new.get(c, ())) for c in chain},
                           "components": chain, "inbox": str(self.settings.inbox_dir), "sample": _sample(sample)}
                for run in members:
                    runs.add_event(s, run.id, "log", {"level": "info", "message": reason, "auto_train": payload})
                sequence_id = members[0].sequence_id
                assert sequence_id is not None  # create_sequence gives every member the chain's id
                learning.record_auto_run(s, sequence_id, reason, {c: trainable[c] for c in chain if c in trainable})
        except (RunRequestError, runs.RunError, OSError) as exc:
            self._refused = (stamp, str(exc))
            log.warning("auto-train: could not queue %s on %s: %s", ",".join(chain), self.settings.inbox_dir, exc)
            return Decision("idle", f"the last auto chain could not be queued: {exc}", data)
        log.info("%s -> sequence %s", reason, sequence_id)
        return Decision(f"starting {chain[0]}", reason, {**data, "next_components": chain}, sequence_id)

    # -- writing the decision ---------------------------------------------------------------------

    def _write(self, d: Decision) -> None:
        now = self.clock()
        if self._written is not None:
            phase, detail, at = self._written
            if (phase, detail) == (d.phase, d.detail) or \
                    (phase == d.phase and phase in LIVE_PHASES and now - at < DETAIL_EVERY_S):
                return
        with self.registry.session() as s:
            learning.record_decision(s, d.phase, d.detail, d.data or None, min_interval_s=0)
        if self._written is None or self._written[0] != d.phase:
            log.info("continuous learning: %s (%s)", d.phase, d.detail or "")
        self._written = (d.phase, d.detail, now)


def _counts(counts: dict[str, int]) -> str:
    return ", ".join(f"{c}: {n}" for c, n in counts.items()) or "no components"


def _fmt(value: float | None, pattern: str, unknown: str) -> str:
    return unknown if value is None else pattern.format(value)


def _sample(sample: dict[str, Any]) -> dict[str, Any]:
    return {k: sample.get(k) for k in ("time", "temp_c", "mem_available_mb", "cpu_percent")}


__all__ = ["ContinuousLearning", "Decision", "InboxCounter", "read_inbox"]
