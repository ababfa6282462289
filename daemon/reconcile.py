"""Reconcile: make the registry agree with the processes that are really there.

For every active run, `starting` or `running` (at daemon start and on every tick):
- claimed (worker_pid set) and its child is gone: on this host (worker_host == our hostname) the
  pid no longer exists, is a zombie, or is a newer process that reused the pid; on any host, no
  heartbeat for heartbeat_timeout_s (the child beats every 2 s from a thread, from before it
  imports torch). -> registry.mark_interrupted: requeued with attempt + 1 (the trainer resumes from
  the last checkpoint in run_dir) or failed once max_attempts are used up. A local child that is
  alive but silent is hung: it is killed first, so two processes never train in one run dir.
- starting (sent, not claimed) for claim_timeout_s since it was last sent: the message was lost
  or no worker serves that queue yet -> re-sent with a new task id, same attempt (a log event
  says so); it stays starting, waiting for a worker. The old message, if it ever arrives, is
  refused by claim(). At daemon start the timeout is
  heartbeat_timeout_s instead: a daemon killed between committing a dispatch and sending its
  message left a run that nothing would ever claim.

The heartbeat verdict is skipped for a round when the daemon itself was not running for a while
(suspend, a stalled tick): stale heartbeats then say nothing about the child.
"""
from __future__ import annotations

import logging
import os
import signal
import socket
import time
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any, Callable

import psutil
from sqlalchemy import select

from registry import runs
from registry.models import Run, utcnow

log = logging.getLogger(__name__)

PID_START_SLACK_S = 2.0  # clock granularity between psutil's create_time and the claim's timestamp


@dataclass
class Action:
    run_id: str
    action: str  # "interrupted" | "resent"
    why: str


def child_alive(pid: int, claimed_at: datetime | None) -> tuple[bool, str]:
    """(alive, why not) for a worker child pid on this host."""
    try:
        proc = psutil.Process(pid)
        status = proc.status()
        created = proc.create_time()
    except psutil.NoSuchProcess:
        return False, f"worker child pid {pid} is gone"
    except psutil.AccessDenied:
        return True, ""  # exists (another user's process): cannot say more
    if status == psutil.STATUS_ZOMBIE:
        return False, f"worker child pid {pid} is gone (exited, not yet reaped)"
    if claimed_at is not None and created > claimed_at.timestamp() + PID_START_SLACK_S:
        return False, f"worker child pid {pid} is gone (the pid now belongs to a newer process)"
    return True, ""


class Reconciler:
    def __init__(self, registry: Any, *, host: str | None = None, heartbeat_timeout_s: float = 30.0,
                 claim_timeout_s: float = 600.0, resend: Callable[[str], Any] | None = None,
                 kill: Callable[[int], None] | None = None, clock: Callable[[], float] = time.monotonic):
        self.registry = registry
        self.host = host or socket.gethostname()
        self.heartbeat_timeout_s = float(heartbeat_timeout_s)
        self.claim_timeout_s = float(claim_timeout_s)
        self._resend = resend
        self._kill = kill or (lambda pid: os.kill(pid, signal.SIGKILL))
        self._clock = clock
        self._last_round: float | None = None

    def _suspect(self, run: Run, now: datetime, trust_heartbeats: bool) -> str | None:
        """Why this running run looks dead (None: it looks fine). Called inside a session."""
        if run.state != "running" or run.worker_pid is None:  # a starting run has no child to judge
            return None
        if run.worker_host == self.host:
            alive, why = child_alive(run.worker_pid, run.started_at)
            if not alive:
                return why
        if trust_heartbeats and run.heartbeat_at is not None \
                and now - run.heartbeat_at > timedelta(seconds=self.heartbeat_timeout_s):
            age = (now - run.heartbeat_at).total_seconds()
            return (f"no heartbeat from worker child pid {run.worker_pid} on {run.worker_host} "
                    f"for {age:.0f} s (timeout {self.heartbeat_timeout_s:g} s)")
        return None

    def reconcile(self, claim_timeout_s: float | None = None) -> list[Action]:
        """One round; `claim_timeout_s` overrides the claim timeout for this round (the daemon's
        start uses a short one: a crash between marking a run dispatched and sending its message
        leaves a run no message will ever claim, and a duplicate message is harmless)."""
        claim_timeout = self.claim_timeout_s if claim_timeout_s is None else float(claim_timeout_s)
        t = self._clock()
        # A daemon that was itself stopped (suspend, a long stall) for a good part of the timeout
        # cannot judge heartbeats this round: the children were frozen with it.
        trust = self._last_round is None or t - self._last_round < self.heartbeat_timeout_s / 2
        self._last_round = t
        now = utcnow()
        with self.registry.session(readonly=True) as s:
            rows = s.scalars(select(Run).where(Run.state.in_(runs.ACTIVE))).all()
            suspects = [r.id for r in rows if self._suspect(r, now, trust)]
            # heartbeat_at of a starting run is when its task was last sent
            unclaimed = [r.id for r in rows if r.state == "starting" and r.heartbeat_at is not None
                         and now - r.heartbeat_at > timedelta(seconds=claim_timeout)]
        actions: list[Action] = []
        for run_id in suspects:
            action = self._interrupt(run_id, trust)
            if action is not None:
                actions.append(action)
        for run_id in unclaimed:
            if self._resend is not None and self._resend(run_id):
                actions.append(Action(run_id, "resent", f"not claimed within {claim_timeout:g} s"))
        return actions

    def _interrupt(self, run_id: str, trust: bool) -> Action | None:
        # Re-checked under the write lock: the child may have finished (or beaten) meanwhile.
        with self.registry.session() as s:
            run = runs.get_run(s, run_id)
            if run.state != "running":
                return None
            why = self._suspect(run, utcnow(), trust)
            if why is None:
                return None
            if run.worker_host == self.host and run.worker_pid is not None:
                alive, _ = child_alive(run.worker_pid, run.started_at)
                if alive:  # hung but alive: it must not keep writing into run_dir
                    log.warning("run %s: killing hung worker child pid %d", run_id, run.worker_pid)
                    try:
                        self._kill(run.worker_pid)
                    except ProcessLookupError:
                        pass
                    why += "; the hung child was killed"
            pid, host = run.worker_pid, run.worker_host
            run = runs.mark_interrupted(s, run, why)
            log.warning("run %s (pid %s on %s) interrupted: %s -> %s (attempt %d of %d)", run_id, pid, host,
                        why, run.state, run.attempt, run.max_attempts)
            return Action(run_id, "interrupted", why)


__all__ = ["Action", "Reconciler", "child_alive"]
