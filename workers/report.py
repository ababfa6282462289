"""The channel a training job reports its run through: the registry itself, or Redis.

    channel = open_channel(settings, report, run_id, task_id, attempt, pid, host)
    run = channel.claim()            # RunSnapshot, or raises StaleDelivery (then do not train)
    channel.heartbeat(step=...)      # False: the run is no longer this child's
    channel.control()                # ControlRow: what the registry asks for (ChannelError: no answer now)
    channel.request("shutdown")      # "shutdown" | "thermal": why the job is about to pause
    channel.event(kind, payload, row)    # a run event (+ the run row's live fields in `row`)
    channel.finish(outcome, message, step=..., last_checkpoint=...)

Two implementations with the same meaning:
- RegistryChannel ("db"): a worker on the registry's host writes $HOPE_HOME/hope.db directly
  (registry/report_channel.py; the daemon applies remote reports with it too).
- RedisChannel ("redis", here): a worker on another machine pushes its reports to Redis and reads
  its run's control state there; the protocol is registry/report_protocol.py.
Nothing here imports torch.
"""
from __future__ import annotations

import json
import logging
import time
from contextlib import contextmanager
from typing import TYPE_CHECKING, Any, Callable, Iterator

from registry.db import Registry
from registry.report_channel import RegistryChannel
from registry.report_protocol import (
    ANSWER_TTL_S,
    REPORT_MODES,
    REPORTS_KEY,
    REQUESTS,
    ChannelError,
    ControlRow,
    RunSnapshot,
    StaleDelivery,
    claim_key,
    control_key,
    dumps,
)

if TYPE_CHECKING:
    from hope_models.settings import Settings

log = logging.getLogger(__name__)

CLAIM_WAIT_S = 60.0  # how long a remote child waits for the daemon to answer its claim
FINISH_RETRY_S = 60.0  # a remote child retries sending its outcome this long (Redis restarting)


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
        import redis  # lazy: loads redis

        client = redis.Redis.from_url(url, socket_timeout=10, socket_connect_timeout=10, health_check_interval=30)
        return cls(client, *args, **kw)

    @contextmanager
    def _redis_errors(self, what: str) -> Iterator[None]:
        import redis  # lazy: loads redis

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


def open_channel(settings: Settings, report: str, run_id: str, task_id: str, attempt: int, pid: int, host: str):
    """The channel a task asked for: "db" opens the registry under settings.home (this host holds
    it); "redis" needs settings.redis_url and opens no registry at all."""
    if report == "db":

        registry = Registry.open(settings, migrate=False)
        return RegistryChannel(registry, run_id, task_id, attempt, pid, host, own_registry=True)
    if report == "redis":
        if not settings.redis_url:
            raise ChannelError(f"run {run_id}: task {task_id} reports through Redis, but this worker has no "
                               "redis_url (set HOPE_REDIS_URL to the daemon's Redis)", transient=False)
        return RedisChannel.from_url(settings.redis_url, run_id, task_id, attempt, pid, host)
    raise ChannelError(f"run {run_id}: task {task_id} asks for report mode {report!r}; known: "
                       f"{', '.join(REPORT_MODES)}", transient=False)


__all__ = ["CLAIM_WAIT_S", "FINISH_RETRY_S", "RedisChannel", "open_channel"]
