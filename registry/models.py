"""The registry's tables: runs, their events, trained models (candidates and promotions), the
continuous-learning state (one row: paused from the app, the daemon's phase, the last auto run),
the host's sampled history (system_samples) and the Celery workers that beat (workers).

Times are timezone-aware UTC datetimes in Python. SQLite has no datetime type, so they are stored
as naive UTC text ("YYYY-MM-DD HH:MM:SS.ffffff", SQLAlchemy's format), which sorts in time order.
The migrations in migrations/versions must produce exactly this schema (tests/test_migrations.py
compares them).
"""
from __future__ import annotations

import secrets
from datetime import datetime, timezone
from typing import Any

from sqlalchemy import JSON, Boolean, DateTime, Float, ForeignKey, Index, Integer, MetaData, String, Text, text
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column
from sqlalchemy.types import TypeDecorator

NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


def utcnow() -> datetime:
    return datetime.now(timezone.utc)


def new_run_id(now: datetime | None = None) -> str:
    """"r-YYYYmmdd-HHMMSS-<6 hex>": sorts by creation time, readable in logs, unique enough."""
    now = (now or utcnow()).astimezone(timezone.utc)
    return f"r-{now:%Y%m%d-%H%M%S}-{secrets.token_hex(3)}"


def iso(value: datetime | None) -> str | None:
    return value.isoformat() if value is not None else None


class UTCDateTime(TypeDecorator):
    """Aware UTC datetimes in, aware UTC datetimes out; naive values are refused (they are bugs)."""

    impl = DateTime
    cache_ok = True

    def process_bind_param(self, value: datetime | None, dialect) -> datetime | None:
        if value is None:
            return None
        if value.tzinfo is None or value.utcoffset() is None:
            raise ValueError(f"naive datetime {value!r}: the registry stores timezone-aware UTC times only")
        return value.astimezone(timezone.utc).replace(tzinfo=None)

    def process_result_value(self, value: datetime | None, dialect) -> datetime | None:
        return value.replace(tzinfo=timezone.utc) if value is not None else None


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)


class Run(Base):
    __tablename__ = "runs"

    id: Mapped[str] = mapped_column(String(64), primary_key=True)
    component: Mapped[str] = mapped_column(String(32))
    # TrainConfig overrides (data, steps, seed, ...) plus "vqvae_run" for chains.
    config: Mapped[dict[str, Any]] = mapped_column(JSON)
    dataset_fingerprint: Mapped[str | None] = mapped_column(String(128))
    queue: Mapped[str] = mapped_column(String(64), default="pi", server_default="pi")
    priority: Mapped[int] = mapped_column(Integer, default=0, server_default="0")  # higher first
    sequence_id: Mapped[str | None] = mapped_column(String(64), index=True)
    sequence_index: Mapped[int | None] = mapped_column(Integer)
    state: Mapped[str] = mapped_column(String(16))
    pause_reason: Mapped[str | None] = mapped_column(String(16))  # user | thermal | memory | shutdown | disk
    desired_state: Mapped[str] = mapped_column(String(16), default="run", server_default="run")  # run|pause|cancel
    requested_reason: Mapped[str | None] = mapped_column(String(16))  # why desired_state was set: user | shutdown
    throttle_level: Mapped[int] = mapped_column(Integer, default=0, server_default="0")  # 0..2, set by the daemon
    step: Mapped[int] = mapped_column(Integer, default=0, server_default="0")
    total_steps: Mapped[int] = mapped_column(Integer)
    last_checkpoint: Mapped[str | None] = mapped_column(Text)
    error_message: Mapped[str | None] = mapped_column(Text)
    attempt: Mapped[int] = mapped_column(Integer, default=1, server_default="1")
    max_attempts: Mapped[int] = mapped_column(Integer, default=3, server_default="3")
    celery_task_id: Mapped[str | None] = mapped_column(String(64))
    worker_host: Mapped[str | None] = mapped_column(String(255))
    worker_pid: Mapped[int | None] = mapped_column(Integer)
    run_dir: Mapped[str] = mapped_column(Text)
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    queued_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    # this attempt's task was first sent (state starting; a re-send keeps it): what `waiting` counts from
    dispatched_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    started_at: Mapped[datetime | None] = mapped_column(UTCDateTime)  # this attempt's child claimed the run
    finished_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow, onupdate=utcnow)
    heartbeat_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    loss: Mapped[float | None] = mapped_column(Float)  # last progress loss
    steps_per_s: Mapped[float | None] = mapped_column(Float)
    # The loop closure: when a served model made by this run first answered an inference, and
    # how long after the run finished that was (registry.promotion.record_first_inference).
    first_inference_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    loop_closure_s: Mapped[float | None] = mapped_column(Float)

    __table_args__ = (Index("ix_runs_dispatch", "state", "queue", "priority", "created_at"),)

    def __repr__(self) -> str:
        return f"<Run {self.id} {self.component} {self.state} step {self.step}/{self.total_steps}>"

    def waiting_text(self) -> str | None:
        """Why a starting run (sent, not claimed by any worker child) does not train yet, and
        since when; for a queued run the daemon holds back (too little disk space: daemon/disk_guard.py)
        its reason; None in every other state (registry/runs.py has the states)."""
        if self.state == "queued":
            return self.error_message  # only the daemon's hold sets it on a queued run
        if self.state != "starting":
            return None
        since = f" since {self.dispatched_at:%Y-%m-%d %H:%M:%S} UTC" if self.dispatched_at is not None else ""
        return (f"waiting for a worker on queue '{self.queue}'{since}: no worker has taken it yet "
                f"(start one with: run_trainer.py worker -Q {self.queue})")

    def to_json_obj(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "component": self.component,
            "state": self.state,
            "waiting": self.waiting_text(),
            "step": self.step,
            "total_steps": self.total_steps,
            "pause_reason": self.pause_reason,
            "desired_state": self.desired_state,
            "requested_reason": self.requested_reason,
            "throttle_level": self.throttle_level,
            "attempt": self.attempt,
            "max_attempts": self.max_attempts,
            "queue": self.queue,
            "priority": self.priority,
            "sequence_id": self.sequence_id,
            "sequence_index": self.sequence_index,
            "loss": self.loss,
            "steps_per_s": self.steps_per_s,
            "error": self.error_message if self.state != "queued" else None,
            "last_checkpoint": self.last_checkpoint,
            "run_dir": self.run_dir,
            "dataset_fingerprint": self.dataset_fingerprint,
            "worker_host": self.worker_host,
            "worker_pid": self.worker_pid,
            "created_at": iso(self.created_at),
            "queued_at": iso(self.queued_at),
            "dispatched_at": iso(self.dispatched_at),
            "started_at": iso(self.started_at),
            "finished_at": iso(self.finished_at),
            "updated_at": iso(self.updated_at),
            "heartbeat_at": iso(self.heartbeat_at),
            "first_inference_at": iso(self.first_inference_at),
            "loop_closure_s": self.loop_closure_s,
            "config": self.config,
        }


class RunEvent(Base):
    __tablename__ = "run_events"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    run_id: Mapped[str] = mapped_column(ForeignKey("runs.id", ondelete="CASCADE"), index=True)
    time: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)
    kind: Mapped[str] = mapped_column(String(16))  # progress | log | state | throttle | checkpoint | metric
    payload: Mapped[dict[str, Any]] = mapped_column(JSON)

    def __repr__(self) -> str:
        return f"<RunEvent {self.id} {self.run_id} {self.kind}>"

    def to_json_obj(self) -> dict[str, Any]:
        return {"id": self.id, "run_id": self.run_id, "time": iso(self.time), "kind": self.kind, "payload": self.payload}


class Model(Base):
    """One candidate checkpoint of a component, gated once; promoted_at is set while it is served.

    The history of a component is its rows: refused candidates keep their gate_result (why), a
    demoted one its demoted_at, and previous_model_id says what was served before this one was
    promoted, which is what a rollback goes back to (registry/promotion.py)."""

    __tablename__ = "models"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    component: Mapped[str] = mapped_column(String(32))
    checkpoint_path: Mapped[str] = mapped_column(Text)
    # "<run>@<step>:<sha12>" (hope_models.checkpoint_format.version_name); null only for rows
    # written before revision 0002
    version: Mapped[str | None] = mapped_column(String(200))
    run_id: Mapped[str | None] = mapped_column(ForeignKey("runs.id", ondelete="SET NULL"), index=True)
    metrics: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))
    gate_result: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))
    promoted_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    demoted_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    previous_model_id: Mapped[int | None] = mapped_column(ForeignKey("models.id", ondelete="SET NULL"))
    created_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow)

    # At most one promoted model per component (the BrainService loads that one).
    __table_args__ = (
        Index(
            "uq_models_promoted_component",
            "component",
            unique=True,
            sqlite_where=text("promoted_at IS NOT NULL"),
        ),
    )

    def __repr__(self) -> str:
        return f"<Model {self.id} {self.component} promoted={self.promoted_at is not None}>"

    def to_json_obj(self) -> dict[str, Any]:
        return {
            "id": self.id,
            "component": self.component,
            "checkpoint_path": self.checkpoint_path,
            "version": self.version,
            "run_id": self.run_id,
            "metrics": self.metrics,
            "gate_result": self.gate_result,
            "promoted": self.promoted_at is not None,
            "promoted_at": iso(self.promoted_at),
            "demoted_at": iso(self.demoted_at),
            "previous_model_id": self.previous_model_id,
            "created_at": iso(self.created_at),
        }


class LearningState(Base):
    """The one row (id 1) of continuous learning that the daemon and the webapp share (they may be
    two processes): whether the app paused learning and which runs that pause paused, the daemon's
    last decision (phase), and the last auto run with the episodes it was started for
    (registry/learning.py reads and writes it; daemon/continuous.py decides)."""

    __tablename__ = "learning_state"

    id: Mapped[int] = mapped_column(Integer, primary_key=True)
    paused: Mapped[bool] = mapped_column(Boolean, default=False, server_default="0")
    paused_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    # the runs this pause paused (a resume resumes exactly those)
    paused_runs: Mapped[list[str] | None] = mapped_column(JSON(none_as_null=True))
    # the queues the daemon treats as local (its worker shares this host), written at its start
    local_queues: Mapped[list[str] | None] = mapped_column(JSON(none_as_null=True))
    phase: Mapped[str] = mapped_column(String(32), default="idle", server_default="idle")
    phase_detail: Mapped[str | None] = mapped_column(Text)
    phase_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    decision: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))
    # per component, the ids of the inbox episodes the last auto run of it was queued for
    watermark: Mapped[dict[str, Any] | None] = mapped_column(JSON(none_as_null=True))
    last_auto_sequence_id: Mapped[str | None] = mapped_column(String(64))
    last_auto_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    last_auto_reason: Mapped[str | None] = mapped_column(Text)
    # the app's last reset (registry/learning.reset): the watermark forgotten, surprise history after it
    reset_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    updated_at: Mapped[datetime] = mapped_column(UTCDateTime, default=utcnow, onupdate=utcnow)

    def __repr__(self) -> str:
        return f"<LearningState paused={self.paused} phase={self.phase!r}>"


class SystemSample(Base):
    """One sample of the daemon's host (daemon/system_history.py writes them, the last 24 h are
    kept; registry/system_samples.py reads them). Every measure may be null: a host without a
    thermal zone has no temp_c."""

    __tablename__ = "system_samples"

    id: Mapped[int] = mapped_column(Integer, primary_key=True, autoincrement=True)
    time: Mapped[datetime] = mapped_column(UTCDateTime, index=True)
    mem_percent: Mapped[float | None] = mapped_column(Float)
    mem_used_mb: Mapped[float | None] = mapped_column(Float)
    mem_available_mb: Mapped[float | None] = mapped_column(Float)
    mem_total_mb: Mapped[float | None] = mapped_column(Float)
    temp_c: Mapped[float | None] = mapped_column(Float)
    cpu_percent: Mapped[float | None] = mapped_column(Float)
    throttle_level: Mapped[int | None] = mapped_column(Integer)


class Worker(Base):
    """A Celery worker parent, by its node name ("pi@raspberrypi"): what it serves and when it last
    beat (workers/heartbeat.py; a remote one's beats arrive through Redis, daemon/remote.py).
    current_run_id is the run its pool child is executing, as the parent sees it."""

    __tablename__ = "workers"

    name: Mapped[str] = mapped_column(String(255), primary_key=True)
    host: Mapped[str] = mapped_column(String(255))
    pid: Mapped[int] = mapped_column(Integer)
    queues: Mapped[list[str]] = mapped_column(JSON)
    report: Mapped[str] = mapped_column(String(8))  # db | redis: how its jobs report (registry/report_protocol.py)
    heartbeat_s: Mapped[float] = mapped_column(Float)  # its beat interval: offline after 3 missed
    started_at: Mapped[datetime] = mapped_column(UTCDateTime)
    last_seen: Mapped[datetime] = mapped_column(UTCDateTime)
    stopped_at: Mapped[datetime | None] = mapped_column(UTCDateTime)
    current_run_id: Mapped[str | None] = mapped_column(String(64))

    def __repr__(self) -> str:
        return f"<Worker {self.name} {self.queues} last_seen={self.last_seen}>"
