"""The one Celery task: train a run in this worker child. Thin on purpose: the work (claim,
control, events, outcome) is workers.job.run_job, which tests call directly too.

    hope.train_run(run_id, attempt, report="db" | "redis")

`report` is how the child reports its run (workers/report.py): "db" writes the registry on this
host; "redis" is for a worker on another machine, which reaches the daemon only through Redis.
The daemon decides it per queue when it sends the task; messages from before it default to "db".

The task body imports workers.job (and, through the trainer, torch) only when it runs, i.e. in the
prefork child; the worker parent that imports this module at start stays torch-free.
"""
from __future__ import annotations

from celery import shared_task

from hope_models.settings import load_settings
from registry.broker import TASK_TRAIN_RUN


@shared_task(name=TASK_TRAIN_RUN, bind=True, acks_late=True, ignore_result=True)
def train_run(self, run_id: str, attempt: int, report: str = "db") -> dict:
    from workers.job import run_job  # lazy: loads sqlalchemy

    settings = getattr(self.app, "hope_settings", None) or load_settings()
    return run_job(settings, run_id, int(attempt), task_id=self.request.id, report=report)
