"""The channel a training job reports its run through: the registry itself, or Redis.

    channel = open_channel(settings, report, run_id, task_id, attempt, pid, host)
    run = channel.claim()            # RunSnapshot, or raises StaleDelivery (then do not train)
    channel.heartbeat(step=...)      # False: the run is no longer this child's
    channel.control()                # ControlRow: what the registry asks for (ChannelError: no answer now)
    channel.request("shutdown")      # "shutdown" | "thermal": why the job is about to pause
    channel.event(kind, payload, row)    # a run event (+ the run row's live fields in `row`)
    channel.finish(outcome, message, step=..., last_checkpoint=...)

Two implementations with the same meaning:
- RegistryChannel ("db"): a worker on the registry's host writes $HOPE_HOME/hope.db directly.
- RedisChannel ("redis"): a worker on another machine. The registry is SQLite in WAL mode, whose
  index lives in one host's shared memory, so it cannot be shared over a network. The remote
  child reaches Redis anyway (the Celery broker), so it reports there and the daemon on the
  registry's host applies its reports (daemon/remote.py) with RegistryChannel: one set of rules
  for what a report does to a run, whichever way it travelled.
The daemon decides per queue and puts it in the task: hope.train_run(run_id, attempt, report=...).

The Redis protocol (JSON only, keys under "hope:"):
    child -> daemon  RPUSH hope:reports  {"type": claim|heartbeat|event|control_request|finish,
                                          "run_id", "task_id", "attempt", "pid", "host", "time", ...}
    daemon -> child  SET hope:claim:<run_id>:<task_id>  {"ok": true, "run": RunSnapshot}
                                                        | {"ok": false, "status", "why"}   (TTL; a child
                                                          that gives up sets it itself, NX: withdrawn)
                     SET hope:control:<run_id>          ControlRow, every daemon tick   (TTL)
Nothing here imports torch.
"""
from __future__ import annotations

import json
import logging
import time
from contextlib import contextmanager
from dataclasses import asdict, dataclass
from datetime import datetime
from typing import Any, Callable, Iterator

from sqlalchemy import select
from sqlalchemy.exc import OperationalError, SQLAlchemyError

from registry import runs
from registry.models import Run
from hope_models.json_finite import finite

log = logging.getLogger(__name__)

REPORT_MODES = ("db", "redis")
REPORTS_KEY = "hope:reports"
REPORT_TYPES = ("claim", "heartbeat", "event", "control_request", "finish")
REQUESTS = ("shutdown", "thermal")
CLAIM_WAIT_S = 60.0  # how long a remote child waits for the daemon to answer its claim
FINISH_RETRY_S = 60.0  # a remote child retries sending its outcome this long (Redis restarting)
ANSWER_TTL_S = 300  # claim answers and control states expire: nothing is left behind in Redis
CONTROL_TTL_S = 300


def claim_key(run_id: str, task_id: str) -> str:
    return f"hope:claim:{run_id}:{task_id}"


def control_key(run_id: str) -> str:
    return f"hope:control:{run_id}"


class ChannelError(RuntimeError):
    """A report could not be made or read. `transient`: worth trying again (a locked database,
    Redis unreachable); otherwise the request itself is wrong (e.g. an unknown event kind)."""

    def __init__(self, message: str, *, transient: bool = True):
        super().__init__(message)
        self.transient = transient


class StaleDelivery(Exception):
    """The task may not train: re-sent, requeued, cancelled, already claimed, or unanswered.
    `status` goes into the task's result ("stale", "missing", "no_answer")."""

    def __init__(self, status: str, why: str):
        super().__init__(why)
        self.status, self.why = status, why


# -- what travels -----------------------------------------------------------------------------

@dataclass
class RunSnapshot:
    """What a job needs of its run row, taken at claim time (the remote child has no registry).
    vqvae_run is resolved by the registry's side: vqvae_dir, or vqvae_error saying why not."""

    id: str
    component: str
    config: dict[str, Any]
    total_steps: int
    run_dir: str
    attempt: int
    step: int = 0
    vqvae_dir: str | None = None
    vqvae_error: str | None = None

    def to_json_obj(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json_obj(cls, obj: Any) -> "RunSnapshot":
        try:
            snap = cls(**obj)
        except TypeError as exc:
            raise ChannelError(f"the daemon's claim answer has a malformed run: {exc}", transient=False) from None
        if not isinstance(snap.config, dict) or not isinstance(snap.total_steps, int):
            raise ChannelError(f"the daemon's claim answer for run {snap.id} has a malformed config or total_steps",
                               transient=False)
        return snap


@dataclass
class ControlRow:
    """The run row's control fields: what the job reads between steps."""

    state: str
    worker_pid: int | None = None
    worker_host: str | None = None
    desired_state: str = "run"
    throttle_level: int = 0
    requested_reason: str | None = None

    @classmethod
    def of(cls, run: Run | None) -> "ControlRow":
        if run is None:
            return cls(state="gone")
        return cls(run.state, run.worker_pid, run.worker_host, run.desired_state, run.throttle_level,
                   run.requested_reason)

    def owned_by(self, pid: int, host: str) -> bool:
        return self.state == "running" and self.worker_pid == pid and self.worker_host == host

    def describe(self) -> str:
        return "gone" if self.state == "gone" else f"{self.state}, worker pid {self.worker_pid} on {self.worker_host}"

    def to_json_obj(self) -> dict[str, Any]:
        return asdict(self)

    @classmethod
    def from_json_obj(cls, obj: Any) -> "ControlRow":
        try:
            row = cls(**obj)
        except TypeError as exc:
            raise ChannelError(f"malformed control state: {exc}") from None
        if not isinstance(row.state, str) or not isinstance(row.throttle_level, int):
            raise ChannelError(f"malformed control state: {obj!r}")
        return row


def dumps(obj: Any) -> str:
    return json.dumps(finite(obj), allow_nan=False, default=str, separators=(",", ":"))


# -- the registry's side (used by local children and by the daemon for remote ones) -------------

def resolve_vqvae_run(s, vqvae_run: str, for_run: str) -> str:
    """The run dir of `vqvae_run`, which must be a completed vqvae run (RunError otherwise)."""
    other = s.get(Run, vqvae_run)
    if other is None:
        raise runs.RunError(f"run {for_run}: vqvae_run {vqvae_run} does not exist")
    if other.component != "vqvae" or other.state != "completed":
        raise runs.RunError(f"run {for_run}: vqvae_run {vqvae_run} is a {other.state} {other.component} run, "
                            "not a completed vqvae run")
    return other.run_dir


def snapshot_of(s, run: Run) -> RunSnapshot:
    config = dict(run.config or {})
    snap = RunSnapshot(id=run.id, component=run.component, config=config, total_steps=run.total_steps,
                       run_dir=run.run_dir, attempt=run.attempt, step=run.step or 0)
    if config.get("vqvae_run") is not None:
        try:
            snap.vqvae_dir = resolve_vqvae_run(s, str(config["vqvae_run"]), run.id)
        except runs.RunError as exc:  # the job fails with this message, like any config error
            snap.vqvae_error = str(exc)
    return snap


@contextmanager
def _registry_errors(what: str) -> Iterator[None]:
    try:
        yield
    except runs.RunError as exc:
        raise ChannelError(str(exc), transient=False) from exc
    except OperationalError as exc:  # locked past the busy timeout, disk I/O: try again later
        raise ChannelError(f"{what}: {exc}", transient=True) from exc
    except SQLAlchemyError as exc:
        raise ChannelError(f"{what}: {exc}", transient=False) from exc


class RegistryChannel:
    """Reports written straight into the registry. Every change is guarded: only the child that
    holds the run (running, worker pid and host its own) moves it, so a superseded child or a
    report applied twice changes nothing."""

    mode = "db"

    def __init__(self, registry, run_id: str, task_id: str, attempt: int, pid: int, host: str, *,
                 own_registry: bool = False):
        self.registry, self.run_id, self.task_id = registry, run_id, task_id
        self.attempt, self.pid, self.host = int(attempt), int(pid), host
        self._own_registry = own_registry

    def _mine(self, s) -> Run | None:
        run = s.scalars(select(Run).where(Run.id == self.run_id).execution_options(populate_existing=True)).first()
        if run is None or not ControlRow.of(run).owned_by(self.pid, self.host):
            return None
        return run

    def claim(self) -> RunSnapshot:
        with _registry_errors(f"run {self.run_id}: claim"), self.registry.session() as s:
            run = runs.claim(s, self.run_id, self.task_id, self.attempt, self.host, self.pid)
            if run is None:
                run = s.get(Run, self.run_id)
                if run is not None and run.celery_task_id == self.task_id and run.attempt == self.attempt \
                        and self._mine(s) is not None:
                    return snapshot_of(s, run)  # this very claim, reported twice (daemon restart)
                status, why = self._stale_note(s, run)
            else:
                return snapshot_of(s, run)
        raise StaleDelivery(status, why)

    def _stale_note(self, s, run: Run | None) -> tuple[str, str]:
        if run is None:
            return "missing", f"task {self.task_id}: no run {self.run_id} in the registry; nothing to train"
        why = (f"ignored a stale delivery (task {self.task_id}, attempt {self.attempt}): the run is {run.state}, "
               f"attempt {run.attempt}, task {run.celery_task_id}, pid {run.worker_pid}; it did not train")
        runs.add_event(s, self.run_id, "log", {"level": "warning", "message": why})
        return "stale", why

    def heartbeat(self, **row: Any) -> bool:
        with _registry_errors(f"run {self.run_id}: heartbeat"), self.registry.session() as s:
            if self._mine(s) is None:
                return False
            return runs.heartbeat(s, self.run_id, self.pid, **{k: v for k, v in row.items() if v is not None})

    def control(self) -> ControlRow:
        with _registry_errors(f"run {self.run_id}: reading its control state"), \
                self.registry.session(readonly=True) as s:
            row = s.execute(select(Run.state, Run.worker_pid, Run.worker_host, Run.desired_state,
                                   Run.throttle_level, Run.requested_reason)
                            .where(Run.id == self.run_id)).one_or_none()
        return ControlRow("gone") if row is None else ControlRow(*row)

    def request(self, what: str) -> None:
        """shutdown: desired pause + requested_reason "shutdown" (finish() then requeues the run);
        thermal: requested_reason "thermal", so the pause reads as thermal even if the host has
        cooled down (throttle level back at 0) before finish()."""
        if what not in REQUESTS:
            raise ChannelError(f"run {self.run_id}: request {what!r} is not one of {', '.join(REQUESTS)}",
                               transient=False)
        with _registry_errors(f"run {self.run_id}: recording the {what} request"), self.registry.session() as s:
            run = self._mine(s)
            if run is None:
                return
            if what == "shutdown" and run.desired_state != "cancel":
                runs.request_shutdown(s, run)
            elif what == "thermal" and run.requested_reason is None:
                run.requested_reason = "thermal"

    def event(self, kind: str, payload: dict, row: dict | None = None, *, at: datetime | None = None) -> bool:
        """Record an event (as the child's log, even from a superseded child); `row` updates the
        run's live fields (step, loss, ...) and the heartbeat, only while the run is ours. False
        when it is not (then the job should stop). `at`: when it happened (the remote child's
        clock), never later than now."""
        with _registry_errors(f"run {self.run_id}: {kind} event"), self.registry.session() as s:
            event = runs.add_event(s, self.run_id, kind, payload)
            if at is not None:
                event.time = min(at, event.time)
            if row is None:
                return True
            if self._mine(s) is None:
                return False
            values = {k: v for k, v in row.items() if v is not None}
            return runs.heartbeat(s, self.run_id, self.pid, **values)

    def finish(self, outcome: str, message: str, *, step: int | None, last_checkpoint: str | None) -> str | None:
        """The run's new state, or None when the run was no longer this child's (nothing written)."""
        with _registry_errors(f"run {self.run_id}: recording outcome {outcome}"), self.registry.session() as s:
            if self._mine(s) is None:
                return None
            final = runs.finish(s, self.run_id, self.pid, outcome, message, step=step, last_checkpoint=last_checkpoint)
            return None if final is None else final.state

    def close(self) -> None:
        if self._own_registry:
            self.registry.close()


# -- the remote child's side --------------------------------------------------------------------

class RedisChannel:
    """Reports pushed to Redis for the daemon to apply; control read from the key it publishes.
    heartbeat() and event() cannot know whether the run is still ours (the daemon answers
    later): a superseded child learns it from the control state, which then names another
    worker or another state."""

    mode = "redis"

    def __init__(self, client, run_id: str, task_id: str, attempt: int, pid: int, host: str, *,
                 claim_wait_s: float = CLAIM_WAIT_S, finish_retry_s: float = FINISH_RETRY_S, poll_s: float = 0.1,
                 clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep):
        self.client, self.run_id, self.task_id = client, run_id, task_id
        self.attempt, self.pid, self.host = int(attempt), int(pid), host
        self.claim_wait_s = claim_wait_s
        self.finish_retry_s, self.poll_s = finish_retry_s, poll_s
        self._clock, self._sleep = clock, sleep

    @classmethod
    def from_url(cls, url: str, *args: Any, **kw: Any) -> "RedisChannel":
        import redis

        client = redis.Redis.from_url(url, socket_timeout=10, socket_connect_timeout=10, health_check_interval=30)
        return cls(client, *args, **kw)

    @contextmanager
    def _redis_errors(self, what: str) -> Iterator[None]:
        import redis

        try:
            yield
        except redis.RedisError as exc:
            raise ChannelError(f"run {self.run_id}: {what} through Redis failed: {type(exc).__name__}: {exc}") from exc

    def message(self, type_: str, **fields: Any) -> str:
        return dumps({"type": type_, "run_id": self.run_id, "task_id": self.task_id, "attempt": self.attempt,
                      "pid": self.pid, "host": self.host, "time": time.time(), **fields})

    def _push(self, type_: str, **fields: Any) -> str:
        raw = self.message(type_, **fields)
        with self._redis_errors(type_):
            self.client.rpush(REPORTS_KEY, raw)
        return raw

    def claim(self) -> RunSnapshot:
        self._push("claim")
        key = claim_key(self.run_id, self.task_id)
        answer = self._wait_answer(key)
        if answer is None:
            # Withdraw, unless the answer lands at this very moment: SET NX on the answer's key
            # is atomic, and the daemon skips a claim whose key is already set.
            withdrawn = {"ok": False, "status": "no_answer", "why": "withdrawn by the child: no answer in time"}
            with self._redis_errors("withdrawing the claim"):
                if self.client.set(key, dumps(withdrawn), nx=True, ex=ANSWER_TTL_S):
                    raise StaleDelivery("no_answer", (
                        f"run {self.run_id}: the daemon did not answer the claim of task {self.task_id} within "
                        f"{self.claim_wait_s:g} s (is it running, on the same Redis?); the claim is withdrawn and the "
                        "daemon re-sends the task after its claim timeout"))
            answer = self._wait_answer(key)  # it did land: read it
        with self._redis_errors("reading the claim answer"):
            self.client.delete(key)
        if not isinstance(answer, dict):
            raise ChannelError(f"run {self.run_id}: malformed claim answer {answer!r}", transient=False)
        if not answer.get("ok"):
            raise StaleDelivery(str(answer.get("status") or "stale"), str(answer.get("why") or "refused by the daemon"))
        return RunSnapshot.from_json_obj(answer.get("run"))

    def _wait_answer(self, key: str) -> Any:
        deadline = self._clock() + self.claim_wait_s
        while True:
            with self._redis_errors("waiting for the claim answer"):
                raw = self.client.get(key)
            if raw is not None:
                try:
                    return json.loads(raw)
                except ValueError:
                    raise ChannelError(f"run {self.run_id}: the claim answer at {key} is not JSON",
                                       transient=False) from None
            if self._clock() >= deadline:
                return None
            self._sleep(self.poll_s)

    def heartbeat(self, **row: Any) -> bool:
        self._push("heartbeat", row=row or None)
        return True

    def control(self) -> ControlRow:
        key = control_key(self.run_id)
        with self._redis_errors("reading the control state"):
            raw = self.client.get(key)
        if raw is None:
            raise ChannelError(f"run {self.run_id}: no control state in Redis ({key}): the daemon has not "
                               "published it for a while")
        try:
            return ControlRow.from_json_obj(json.loads(raw))
        except ValueError:
            raise ChannelError(f"run {self.run_id}: the control state at {key} is not JSON") from None

    def request(self, what: str) -> None:
        if what not in REQUESTS:
            raise ChannelError(f"run {self.run_id}: request {what!r} is not one of {', '.join(REQUESTS)}",
                               transient=False)
        self._push("control_request", request=what)

    def event(self, kind: str, payload: dict, row: dict | None = None) -> bool:
        self._push("event", kind=kind, payload=payload, row=row)
        return True

    def finish(self, outcome: str, message: str, *, step: int | None, last_checkpoint: str | None) -> str:
        """Sent, not applied: returns "reported". The outcome is the one report that must arrive
        (a lost one costs a retrain from the last checkpoint), so a Redis restart is waited out."""
        deadline = self._clock() + self.finish_retry_s
        while True:
            try:
                self._push("finish", outcome=outcome, message=message, step=step, last_checkpoint=last_checkpoint)
                return "reported"
            except ChannelError as exc:
                if self._clock() >= deadline:
                    raise
                log.warning("%s; retrying", exc)
                self._sleep(1.0)

    def close(self) -> None:
        self.client.close()


def open_channel(settings, report: str, run_id: str, task_id: str, attempt: int, pid: int, host: str):
    """The channel a task asked for: "db" opens the registry under settings.home (this host holds
    it); "redis" needs settings.redis_url and opens no registry at all."""
    if report == "db":
        from registry.db import Registry

        registry = Registry.open(settings, migrate=False)
        return RegistryChannel(registry, run_id, task_id, attempt, pid, host, own_registry=True)
    if report == "redis":
        if not settings.redis_url:
            raise ChannelError(f"run {run_id}: task {task_id} reports through Redis, but this worker has no "
                               "redis_url (set HOPE_REDIS_URL to the daemon's Redis)", transient=False)
        return RedisChannel.from_url(settings.redis_url, run_id, task_id, attempt, pid, host)
    raise ChannelError(f"run {run_id}: task {task_id} asks for report mode {report!r}; known: "
                       f"{', '.join(REPORT_MODES)}", transient=False)


__all__ = ["ANSWER_TTL_S", "CONTROL_TTL_S", "ChannelError", "ControlRow", "REPORTS_KEY", "REPORT_MODES",
           "REPORT_TYPES", "REQUESTS", "RedisChannel", "RegistryChannel", "RunSnapshot", "StaleDelivery",
           "claim_key", "control_key", "dumps", "open_channel", "resolve_vqvae_run", "snapshot_of"]
