"""The registry's side of the report protocol: RegistryChannel, a job's reports written straight
into the registry.

A job child on the registry's host uses it directly; the daemon uses it to apply the reports a
remote child sent through Redis (daemon/remote.py), so a report means the same whichever way it
travelled (registry/report_protocol.py). Nothing here imports torch.
"""
from __future__ import annotations

from contextlib import contextmanager
from datetime import datetime
from typing import TYPE_CHECKING, Any, Iterator

from sqlalchemy import select
from sqlalchemy.exc import OperationalError, SQLAlchemyError

from hope_models.components import TOKENIZER
from registry import runs
from registry.models import Run
from registry.report_protocol import REQUESTS, ChannelError, ControlRow, RunSnapshot, StaleDelivery

if TYPE_CHECKING:
    from registry.db import Registry


def resolve_vqvae_run(s, vqvae_run: str, for_run: str) -> str:
    """The run dir of `vqvae_run`, which must be a completed run of the tokenizer (RunError otherwise)."""
    other = s.get(Run, vqvae_run)
    if other is None:
        raise runs.RunError(f"run {for_run}: vqvae_run {vqvae_run} does not exist")
    if other.component != TOKENIZER or other.state != "completed":
        raise runs.RunError(f"run {for_run}: vqvae_run {vqvae_run} is a {other.state} {other.component} run, "
                            f"not a completed {TOKENIZER} run")
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

    def __init__(self, registry: Registry, run_id: str, task_id: str, attempt: int, pid: int, host: str, *,
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


__all__ = ["RegistryChannel", "resolve_vqvae_run", "snapshot_of"]
