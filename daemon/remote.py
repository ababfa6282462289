"""Remote workers: apply the reports their jobs push to Redis, and publish what they must obey.

A worker on another machine cannot write the registry (SQLite WAL works on one host only), so its
job child reports through Redis (registry/report_protocol.py) and the daemon, every tick:
- poll(): reads the waiting reports in order and applies each one with RegistryChannel, the
  code a local child uses to write the registry itself, so a report means the same whichever way
  it came: claim (answered at hope:claim:<run>:<task>), heartbeat, event (+ the row's live
  fields), control_request (shutdown / thermal), finish;
- publish_running(): SET hope:control:<run> (the run's ControlRow, with a TTL) for every running
  run on a queue that is not local, which the remote child reads between steps: desired state,
  throttle level, and whose run it is. A report from a child the run no longer belongs to gets
  the current state published at once, so that child stops even if the run is not running now.
A remote worker PARENT's beats ("worker" reports: alive, its queues, its current run; "stopped" at
its shutdown) come through the same list and go to the workers table (registry/workers.py) with
report "redis", for the Workers page.

Reports are read with LRANGE and trimmed once applied (at least once, not at most once): a daemon
killed mid-batch applies the rest again at its next start rather than losing a finish. Applying
twice is harmless: claim answers the same child again, heartbeats and requests are idempotent, a
second finish finds the run no longer running, and at worst an event is recorded twice.
A malformed report is logged and dropped; a registry that is busy past its timeout leaves the
report in place for the next tick. Nothing here crashes the daemon or imports torch.
"""
from __future__ import annotations

import logging
from dataclasses import replace
from datetime import datetime, timezone
from typing import Any, Iterable

from sqlalchemy import select

from registry import runs, workers
from registry.models import Run, Worker, utcnow
from registry.report_channel import RegistryChannel
from registry.report_protocol import (
    ANSWER_TTL_S,
    CONTROL_TTL_S,
    REPORTS_KEY,
    BadReport,
    ChannelError,
    ControlRow,
    StaleDelivery,
    claim_key,
    control_key,
    dumps,
    parse_report,
)

log = logging.getLogger(__name__)

BATCH = 500  # reports per tick: a busy remote job sends ~10 a second


class RemoteReports:
    def __init__(self, registry: Any, client: Any, *, local_queues: Iterable[str] = ("pi",), batch: int = BATCH):
        self.registry = registry
        self.client = client
        self.local_queues = set(local_queues)
        self.batch = int(batch)
        self.applied = 0
        self.dropped = 0

    # -- reports -------------------------------------------------------------------------------

    def poll(self, batches: int = 1) -> int:
        """Apply the reports waiting in Redis, oldest first, up to `batches` batches; how many
        were taken off the list (applied or dropped)."""
        total = 0
        for _ in range(max(1, int(batches))):
            done, stopped = self._poll_batch()
            total += done
            if stopped or done < self.batch:
                break
        return total

    def _poll_batch(self) -> tuple[int, bool]:
        """(reports taken off the list, stopped early because the registry was busy)."""
        raws = self.client.lrange(REPORTS_KEY, 0, self.batch - 1)
        done = 0
        try:
            for raw in raws:
                try:
                    self.apply(raw)
                    self.applied += 1
                except ChannelError as exc:
                    if exc.transient:  # the registry is busy: this one and the rest wait for the next tick
                        log.warning("remote reports: %s; %d report(s) left for the next tick", exc, len(raws) - done)
                        return done, True
                    self.dropped += 1
                    log.warning("remote report dropped: %s", exc)
                except BadReport as exc:
                    self.dropped += 1
                    log.warning("malformed remote report dropped: %s: %.300r", exc, raw)
                except Exception:  # noqa: BLE001 - a report must never stop the daemon; drop it, loudly
                    self.dropped += 1
                    log.exception("remote report dropped: applying it failed: %.300r", raw)
                done += 1
        finally:
            if done:
                self.client.ltrim(REPORTS_KEY, done, -1)  # only children append, at the tail: the head is ours
        return done, False

    def apply(self, raw: bytes | str) -> None:
        msg = parse_report(raw)
        if msg["type"] == "worker":
            self._worker(msg)
            return
        channel = RegistryChannel(self.registry, msg["run_id"], msg["task_id"], msg["attempt"], msg["pid"],
                                  msg["host"])
        kind = msg["type"]
        if kind == "claim":
            self._claim(channel)
            return
        if kind == "heartbeat":
            mine = channel.heartbeat(**(msg.get("row") or {}))
        elif kind == "event":
            at = datetime.fromtimestamp(msg["time"], timezone.utc)
            mine = channel.event(msg["kind"], msg["payload"], msg.get("row"), at=at)
        elif kind == "control_request":
            channel.request(msg["request"])
            mine = True
        else:  # finish
            state = channel.finish(msg["outcome"], msg["message"], step=msg.get("step"),
                                   last_checkpoint=msg.get("last_checkpoint"))
            if state is None:
                log.warning("run %s: the outcome %s of pid %d on %s came from a superseded child; not recorded",
                            msg["run_id"], msg["outcome"], msg["pid"], msg["host"])
            else:
                log.info("run %s: %s -> %s (reported by pid %d on %s)", msg["run_id"], msg["outcome"], state,
                         msg["pid"], msg["host"])
            mine = False  # the run has left running (or was not this child's): say so
        if not mine:
            self.publish(msg["run_id"])

    def _worker(self, msg: dict[str, Any]) -> None:
        # last_seen is when we applied the beat, not the remote clock's "time": the two machines'
        # clocks may differ by more than 3 intervals (a Pi has no RTC), which would show a live
        # worker offline. Reports are applied every tick and in order, so this is at most a tick late.
        beat = replace(msg["beat"], at=utcnow())
        with self.registry.session() as s:
            if msg["event"] == "stopped":
                if workers.mark_stopped(s, beat.name, beat.pid, at=beat.at):
                    log.info("worker %s (pid %d on %s) stopped", beat.name, beat.pid, beat.host)
                return
            known = s.get(Worker, beat.name)
            if known is None or known.pid != beat.pid or known.stopped_at is not None:
                log.info("worker %s (pid %d on %s, queues %s) beats through Redis", beat.name, beat.pid, beat.host,
                         ",".join(beat.queues))
            workers.record_beat(s, beat)

    def _claim(self, channel: RegistryChannel) -> None:
        key = claim_key(channel.run_id, channel.task_id)
        if self.client.exists(key):
            # Answered already (this report applied twice) or withdrawn by a child that gave up waiting.
            log.warning("run %s: claim of task %s by pid %d on %s already answered or withdrawn; skipped",
                        channel.run_id, channel.task_id, channel.pid, channel.host)
            return
        try:
            run = channel.claim()
        except StaleDelivery as exc:
            log.warning("run %s: refused the claim of pid %d on %s: %s", channel.run_id, channel.pid, channel.host,
                        exc.why)
            self.client.set(key, dumps({"ok": False, "status": exc.status, "why": exc.why}), ex=ANSWER_TTL_S)
            return
        # Before the answer: the child's first control read must already see that it holds the run.
        self.publish(channel.run_id)
        if self.client.set(key, dumps({"ok": True, "run": run.to_json_obj()}), nx=True, ex=ANSWER_TTL_S):
            log.info("run %s: claimed by pid %d on %s (remote, task %s)", channel.run_id, channel.pid, channel.host,
                     channel.task_id)
            return
        # The child withdrew between our check and now: it will not train. Do not wait for its
        # heartbeats to be missed.
        with self.registry.session() as s:
            row = s.get(Run, channel.run_id)
            if row is not None and ControlRow.of(row).owned_by(channel.pid, channel.host):
                runs.mark_interrupted(s, row, f"the remote child pid {channel.pid} on {channel.host} withdrew its "
                                              "claim (no answer in time)")
        self.publish(channel.run_id)

    # -- control -------------------------------------------------------------------------------

    def publish(self, run_id: str) -> None:
        """The run's control state as the registry has it now."""
        with self.registry.session(readonly=True) as s:
            row = ControlRow.of(s.get(Run, run_id))
        self.client.set(control_key(run_id), dumps(row.to_json_obj()), ex=CONTROL_TTL_S)

    def publish_running(self) -> int:
        """Control state for every running run on a queue that is not local (their children are
        elsewhere and read it from Redis); re-set every tick so it outlives no daemon by much."""
        query = select(Run).where(Run.state.in_(runs.ACTIVE))
        if self.local_queues:
            query = query.where(Run.queue.not_in(self.local_queues))
        with self.registry.session(readonly=True) as s:
            rows = {r.id: ControlRow.of(r) for r in s.scalars(query)}
        if rows:
            pipe = self.client.pipeline(transaction=False)
            for run_id, row in rows.items():
                pipe.set(control_key(run_id), dumps(row.to_json_obj()), ex=CONTROL_TTL_S)
            pipe.execute()
        return len(rows)


__all__ = ["RemoteReports"]
