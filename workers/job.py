"""One training job for a run: the body of the `hope.train_run` task.

    run_job(settings, run_id, attempt, task_id=..., report="db") -> {"status": "finished" | "stale" | ..., ...}

It runs in the Celery worker's prefork child, which exits afterwards. Everything it says about
its run goes through a report channel (workers/report.py): "db" writes the registry on this
host; "redis" (a worker on another machine) reports through Redis for the daemon to apply. The
logic below is the same for both. In order:
1. claim the run (refused for a stale or duplicate delivery: then it does not train);
2. start a heartbeat thread at once, before torch is imported, so a slow start (torch import,
   dataset cache build) is not taken for a dead child;
3. build the TrainConfig from the claimed run and train through hope_models.train.loop.train with
   - RunControl: the run's desired_state / throttle_level, read between steps;
   - Emitter: progress and metric events at most 5 a second each, checkpoint events
     (+ runs.last_checkpoint), logs (capped), throttle events;
4. report the outcome with finish() (guarded: a superseded child changes nothing);
5. gate a completed run here, torch still loaded, when auto-promotion is on (workers/warm_gate.py).
SIGTERM (service stop) asks the loop to checkpoint and stop; finish() then requeues the run.

Torch is imported only by the trainer, inside train(): importing this module stays torch-free.
"""
from __future__ import annotations

import json
import logging
import os
import signal
import socket
import threading
import time
import traceback
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable

from hope_models.disk import full_message, is_disk_full
from hope_models.train.config import (
    REQUEST_FIELDS,
    ConfigValueError,
    TrainConfig,
    check_value,
    deployment_values,
    over_deployment_budget,
)
from hope_models.train.contract import ControlCommand
from hope_models.train.loop import TrainSetupError, train
from hope_models.train.run_dir_lock import wait_until_free
from registry.report_protocol import ChannelError, RunSnapshot, StaleDelivery
from workers.report import open_channel
from workers.warm_gate import WarmGate

if TYPE_CHECKING:
    from hope_models.settings import Settings

log = logging.getLogger(__name__)

HEARTBEAT_S = 2.0
EVENT_MIN_GAP_S = 0.2  # progress and metric events: at most 5 a second each
RATE_LIMITED = ("progress", "metric")
LOG_MAX_CHARS = 8000  # one log event (a traceback keeps its head and its tail)
LOG_MAX_EVENTS = 2000  # log events per job; later ones go to the worker log only
THROTTLE_SLOW = 0.5  # throttle_level 1: sleep this fraction of each step
RUN_DIR_WAIT_S = 60.0  # how long a new child waits for a superseded one to leave the run dir

# What a run's stored config may hold: the TrainConfig options a run request may set
# (train/config.py, checked here as the door checked them), the dataset and steps, the component
# and steps again (they must repeat the row's), and a chain link. The deployment's values (the
# thermal sources and limits, the cache dir) come from this worker's settings.
DAEMON_OWNED = ("thermal_zone", "vcgencmd", "thermal_soft_c", "thermal_hard_c", "thermal_resume_c")
EXTRA_KEYS = ("vqvae_run",)  # a run id whose run_dir becomes vqvae_dir
RUN_CONFIG_KEYS = frozenset(REQUEST_FIELDS) | {"component", "data", "steps"} | set(EXTRA_KEYS)


class JobConfigError(ValueError):
    """The run's config cannot become a TrainConfig; the message names the run and the key."""


# -- config ---------------------------------------------------------------------------------------

def build_train_config(settings: Settings, run: RunSnapshot, run_dir_of: Callable[[str], str]) -> TrainConfig:
    """TrainConfig for `run`: its config overrides, run_dir and steps from the row, the memory
    budget and cache dir from settings unless the config sets them, and no thermal sources (the
    daemon watches the temperature and sets throttle_level). `run_dir_of(run_id)` resolves
    "vqvae_run" (it raises JobConfigError when that run cannot be used)."""
    cfg = dict(run.config or {})
    owned = sorted(k for k in cfg if k in DAEMON_OWNED)
    if owned:
        raise JobConfigError(f"run {run.id}: config key(s) {', '.join(map(repr, owned))} are set by the daemon "
                             "(it watches the temperature for every job), not per run")
    unknown = sorted(k for k in cfg if k not in RUN_CONFIG_KEYS)
    if unknown:
        raise JobConfigError(f"run {run.id}: unknown config key(s) {', '.join(map(repr, unknown))} "
                             f"(known: {', '.join(sorted(RUN_CONFIG_KEYS))})")
    component = cfg.pop("component", run.component)
    if component != run.component:
        raise JobConfigError(f"run {run.id}: config component {component!r} differs from the run's {run.component!r}")
    steps = cfg.pop("steps", run.total_steps)
    if steps != run.total_steps:
        raise JobConfigError(f"run {run.id}: config steps {steps!r} differs from the run's total_steps "
                             f"{run.total_steps}")
    if not cfg.get("data"):
        raise JobConfigError(f"run {run.id}: config has no 'data' (the dataset path to train on)")
    for name in REQUEST_FIELDS:
        if cfg.get(name) is not None:
            try:
                cfg[name] = check_value(name, cfg[name])
            except ConfigValueError as exc:
                raise JobConfigError(f"run {run.id}: config {exc}") from None
    vqvae_run = cfg.pop("vqvae_run", None)
    if vqvae_run is not None:
        if cfg.get("vqvae_dir"):
            raise JobConfigError(f"run {run.id}: config sets both vqvae_run and vqvae_dir; give one")
        cfg["vqvae_dir"] = run_dir_of(str(vqvae_run))
    # the door refuses more than the deployment's budget (run_request.preflight); a run row written
    # otherwise must not take more of this machine than its owner gave the worker either
    too_much = over_deployment_budget(cfg.get("memory_budget_mb", 0.0), settings, "this worker's")
    if too_much:
        raise JobConfigError(f"run {run.id}: {too_much}")
    deployment = {**deployment_values(settings), "thermal_zone": None, "vcgencmd": None}
    return TrainConfig(component=run.component, run_dir=run.run_dir, steps=run.total_steps, **{**deployment, **cfg})


def vqvae_dir_of(run: RunSnapshot) -> Callable[[str], str]:
    """build_train_config's resolver for "vqvae_run": the registry's side resolved it at claim
    time (a remote child has no registry to look it up in)."""
    def run_dir_of(vqvae_run: str) -> str:
        if run.vqvae_error:
            raise JobConfigError(run.vqvae_error)
        if not run.vqvae_dir:
            raise JobConfigError(f"run {run.id}: vqvae_run {vqvae_run} was not resolved when the run was claimed")
        return run.vqvae_dir

    return run_dir_of


# -- control --------------------------------------------------------------------------------------

class RunControl:
    """The trainer's Control, read from the run through the channel (a cheap read; the loop polls
    at most every control_interval_s). desired_state pause/cancel pass through; throttle_level 1
    slows each step by THROTTLE_SLOW; throttle_level >= 2 pauses (finish() records it as a
    thermal pause).

    The run must still be this child's (state running, worker pid and host its own): if the
    daemon gave the run up and requeued it (e.g. after a missed heartbeat), this child cancels
    itself, leaving a checkpoint for the one that took over. A SIGTERM (`shutdown` set) becomes a
    "shutdown" request (desired pause + requested_reason shutdown on the row), so finish() puts
    the run back in the queue. No answer (a busy database, Redis or the daemon away) keeps the
    last one: training does not stop for that."""

    def __init__(self, channel, *, shutdown: threading.Event | None = None, lost: threading.Event | None = None,
                 emit: Callable[[str, dict], None] | None = None):
        self.channel = channel
        self.run_id, self.pid, self.host = channel.run_id, channel.pid, channel.host
        self.shutdown = shutdown or threading.Event()
        self.lost = lost or threading.Event()
        self._emit = emit
        self._last = ControlCommand()
        self._requested: set[str] = set()
        self._said: set[str] = set()

    def _say(self, key: str, message: str, level: str = "warning") -> None:
        if key in self._said:
            return
        self._said.add(key)
        log.log(logging.WARNING if level == "warning" else logging.INFO, "run %s: %s", self.run_id, message)
        if self._emit is not None:
            self._emit("log", {"level": level, "message": message})

    def _request(self, what: str) -> None:
        """Say once why we are about to pause: "shutdown" (finish() then requeues the run), or
        "thermal" (if the host cools below the resume limit before finish(), throttle_level is
        back at 0 and the pause would otherwise read as a user's, never resumed automatically)."""
        if what in self._requested:
            return
        self._requested.add(what)
        try:
            self.channel.request(what)
        except ChannelError as exc:
            log.warning("run %s: could not record the %s request: %s", self.run_id, what, exc)

    def poll(self, step: int) -> ControlCommand:
        if self.shutdown.is_set():
            self._request("shutdown")
        try:
            row = self.channel.control()
        except ChannelError as exc:
            self._say("no-answer", f"cannot read the run's control state ({exc}); keeping the last one")
            return self._last
        if self.lost.is_set() or not row.owned_by(self.pid, self.host):
            self.lost.set()
            self._say("lost", f"the run is no longer this child's ({row.describe()}); pid {self.pid} checkpoints "
                              "and stops")
            cmd = ControlCommand(desired="cancel")
        elif row.desired_state == "cancel":
            cmd = ControlCommand(desired="cancel")
        elif row.desired_state == "pause" or self.shutdown.is_set():
            cmd = ControlCommand(desired="pause")
        elif row.throttle_level >= 2:
            self._say("hot", f"throttle level {row.throttle_level}: pausing until the daemon sees it cool down",
                      "info")
            self._request("thermal")
            cmd = ControlCommand(desired="pause")
        elif row.throttle_level == 1:
            cmd = ControlCommand(throttle=THROTTLE_SLOW)
        else:
            cmd = ControlCommand()
        self._last = cmd
        return cmd


# -- events ---------------------------------------------------------------------------------------

def cap_text(text: str, limit: int = LOG_MAX_CHARS) -> str:
    """At most `limit` characters: the head and the tail (where a traceback says what failed)."""
    if len(text) <= limit:
        return text
    head = limit // 4
    tail = limit - head - 40
    return f"{text[:head]}\n... [{len(text) - head - tail} characters cut] ...\n{text[-tail:]}"


def _describe(kind: str, payload: dict) -> tuple[str, str]:
    """(level, message) for trainer events that are not registry event kinds."""
    if kind == "resume":
        return "info", f"resuming from step {payload.get('step')} ({payload.get('path')})"
    if kind == "memory":
        return "warning", f"memory soft limit at step {payload.get('step')}: {payload.get('message')}"
    if kind == "state":  # the trainer's own end-of-job record; the registry writes the run's state
        return "info", f"trainer: {payload.get('state')} at step {payload.get('step')}: {payload.get('message')}"
    return "info", f"{kind}: {json.dumps(payload, default=str)}"


class Emitter:
    """The trainer's emit(kind, payload) -> run events through the channel (and the run row's
    live fields).

    progress: at most one event per EVENT_MIN_GAP_S (5/s), plus runs.step/loss/steps_per_s and
    the heartbeat; the newest skipped one is kept and written by flush() at the end of the job,
    so the last progress always lands. metric: the same limit (every record is in the run dir's
    metrics.jsonl anyway). checkpoint: an event + runs.last_checkpoint. log: capped in size and
    count. throttle: as is. Other trainer events (resume, memory, state) become log events.
    A channel error drops the event (logged): it never stops training."""

    def __init__(self, channel, *, lost: threading.Event | None = None, min_gap_s: float = EVENT_MIN_GAP_S,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep):
        self.channel, self.run_id = channel, channel.run_id
        self.lost = lost or threading.Event()
        self.min_gap_s, self._clock, self._sleep = min_gap_s, clock, sleep
        self._last_write: dict[str, float] = {}
        self._pending: dict[str, dict] = {}
        self.logs = 0
        self.dropped = 0

    def __call__(self, kind: str, payload: dict) -> None:
        payload = dict(payload or {})
        if kind in RATE_LIMITED:
            last = self._last_write.get(kind)
            if last is not None and self._clock() - last < self.min_gap_s:
                self._pending[kind] = payload
                return
            self._pending.pop(kind, None)
            self._write_limited(kind, payload)
        elif kind == "checkpoint":
            self._write(kind, payload, heartbeat={"step": payload.get("step"), "last_checkpoint": payload.get("path")})
        elif kind == "log":
            self._log(str(payload.get("level", "info")), str(payload.get("message", "")))
        elif kind == "throttle":
            self._write(kind, payload)
        else:
            level, message = _describe(kind, payload)
            self._log(level, message, extra={"event": kind, "data": payload})

    def flush(self) -> None:
        """Write the newest skipped progress/metric event, keeping the 5/s limit (waits < 0.2 s)."""
        for kind in RATE_LIMITED:
            payload = self._pending.pop(kind, None)
            if payload is None:
                continue
            wait = self.min_gap_s - (self._clock() - self._last_write.get(kind, float("-inf")))
            if wait > 0:
                self._sleep(wait)
            self._write_limited(kind, payload)

    def _write_limited(self, kind: str, payload: dict) -> None:
        self._last_write[kind] = self._clock()
        heartbeat = None
        if kind == "progress":
            heartbeat = {"step": payload.get("step"), "loss": payload.get("loss"),
                         "steps_per_s": payload.get("steps_per_s")}
        self._write(kind, payload, heartbeat=heartbeat)

    def _log(self, level: str, message: str, extra: dict | None = None) -> None:
        self.logs += 1
        if self.logs > LOG_MAX_EVENTS:
            log.log(logging.WARNING if level != "info" else logging.INFO, "run %s: %s", self.run_id, message)
            if self.logs == LOG_MAX_EVENTS + 1:
                self._write("log", {"level": "warning", "message": f"more than {LOG_MAX_EVENTS} log events: "
                                    "the rest of this job's log goes to the worker log only"})
            return
        self._write("log", {"level": level, "message": cap_text(message), **(extra or {})})

    def _write(self, kind: str, payload: dict, heartbeat: dict | None = None) -> None:
        try:
            if not self.channel.event(kind, payload, heartbeat):
                self.lost.set()
        except ChannelError as exc:
            self.dropped += 1
            log.warning("run %s: %s event not recorded: %s", self.run_id, kind, exc)


# -- heartbeat ------------------------------------------------------------------------------------

class Heartbeat:
    """A daemon thread saying "alive" every `interval_s` while the job runs (setup included). It
    stops, and sets `lost`, once the run is no longer this child's."""

    def __init__(self, channel, lost: threading.Event, interval_s: float = HEARTBEAT_S):
        self.channel, self.lost, self.interval_s = channel, lost, interval_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._beat, name=f"heartbeat-{channel.run_id}", daemon=True)

    def start(self) -> "Heartbeat":
        self._thread.start()
        return self

    def _beat(self) -> None:
        while not self._stop.wait(self.interval_s):
            try:
                mine = self.channel.heartbeat()
            except ChannelError as exc:
                log.warning("run %s: heartbeat not recorded: %s", self.channel.run_id, exc)
                continue
            if not mine:
                self.lost.set()
                return

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=10)


# -- the job --------------------------------------------------------------------------------------

def _install_sigterm(flag: threading.Event):
    def on_sigterm(signum, frame):  # only set a flag: the loop's next control poll acts on it
        flag.set()

    try:
        return signal.signal(signal.SIGTERM, on_sigterm)
    except ValueError:  # not the main thread (a test calling run_job from a thread)
        return None


class _Job:
    def __init__(self, channel, settings: Settings, run: RunSnapshot, shutdown: threading.Event):
        self.channel, self.settings, self.run = channel, settings, run
        self.lost = threading.Event()
        self.shutdown = shutdown
        self.emitter = Emitter(channel, lost=self.lost)
        self.control = RunControl(channel, shutdown=self.shutdown, lost=self.lost, emit=self.emitter)
        self.threads = 1  # the training's torch threads, also the gate's

    def train(self) -> tuple[str, str, int | None, str | None]:
        """(outcome, message, step, last checkpoint) of the trainer, or failed with why."""
        run = self.run
        try:
            cfg = build_train_config(self.settings, run, vqvae_dir_of(run))
            self.threads = cfg.threads
            # A child the daemon gave up on stops at its next control poll (RunControl sees the run
            # is no longer its own) and leaves a checkpoint this job resumes from: wait for it to
            # leave the run dir. The trainer takes the lock itself right after (and reports it busy).
            wait_until_free(Path(cfg.run_dir), RUN_DIR_WAIT_S, self.shutdown)
            # Asked to stop before training began (SIGTERM or a request during setup): do not start.
            first = self.control.poll(run.step)
            if first.desired != "run":
                outcome = "cancelled" if first.desired == "cancel" else "paused_user"
                return outcome, f"{first.desired} requested before training started", None, None
            result = train(cfg, self.control, self.emitter)
            return result.outcome, result.message, result.steps, result.checkpoint
        except (JobConfigError, TrainSetupError) as exc:
            self.emitter("log", {"level": "error", "message": str(exc)})
            return "failed", str(exc), None, None
        except Exception as exc:  # a bug or an environment problem: say what and where
            if is_disk_full(exc):  # a full disk is no bug: pause (reason "disk"), no traceback
                message = full_message(exc, run.run_dir)
                self.emitter("log", {"level": "error", "message": message})
                return "paused_disk", message, None, None
            self.emitter("log", {"level": "error", "message": traceback.format_exc()})
            return "failed", f"{type(exc).__name__}: {exc}", None, None

    def __call__(self) -> dict[str, Any]:
        run, pid = self.run, self.channel.pid
        heartbeat = Heartbeat(self.channel, self.lost).start()
        try:
            outcome, message, step, checkpoint = self.train()
            self.emitter.flush()
        finally:
            heartbeat.stop()
        gate = WarmGate(self.settings, self.channel, self.threads)
        with gate.held():  # before the run is completed: auto-promotion then leaves it to this child
            final = self.channel.finish(outcome, message, step=step, last_checkpoint=checkpoint)
            if not self.shutdown.is_set():  # a service stopping gates at its next start instead
                gate.run(run.id, final)
        out = {"run_id": run.id, "attempt": run.attempt, "outcome": outcome, "step": step, "message": message,
               "report": self.channel.mode}
        if final is None:
            log.warning("run %s: pid %d was superseded; its outcome %s is not recorded", run.id, pid, outcome)
            return {"status": "superseded", **out}
        if final == "reported":  # through Redis: the daemon applies it
            log.info("run %s: %s at step %s, reported to the daemon", run.id, outcome, step)
            return {"status": "reported", **out}
        log.info("run %s: %s -> %s at step %s", run.id, outcome, final, step)
        return {"status": "finished", "state": final, **out}


def run_job(settings: Settings, run_id: str, attempt: int, *, task_id: str, report: str = "db", host: str | None = None,
            pid: int | None = None) -> dict[str, Any]:
    """Claim run `run_id` for delivery (task_id, attempt) and train it in this process, reporting
    through `report` ("db": the registry on this host; "redis": the daemon, from another
    machine); a small JSON-able summary. Stale deliveries return {"status": "stale"} (or
    "missing", "no_answer") without training."""
    host = host or socket.gethostname()
    pid = pid or os.getpid()
    # From the start of the task: a SIGTERM during setup is served at the first control poll.
    shutdown = threading.Event()
    previous = _install_sigterm(shutdown)
    try:
        channel = open_channel(settings, report, run_id, task_id, attempt, pid, host)
        try:
            try:
                run = channel.claim()
            except StaleDelivery as exc:
                log.warning("run %s: %s", run_id, exc.why)
                return {"status": exc.status, "run_id": run_id, "attempt": attempt, "task_id": task_id}
            log.info("run %s: claimed by pid %d on %s (task %s, attempt %d, reports via %s)", run_id, pid, host,
                     task_id, attempt, channel.mode)
            return _Job(channel, settings, run, shutdown)()
        finally:
            channel.close()
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
