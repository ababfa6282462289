"""The daemon: one loop that keeps the registry, the host and the worker in step.

    d = Daemon(settings, sink)        # sink: where run/system events go (daemon.events)
    d.start()                         # migrate the registry once, reconcile what a crash left
    d.run_forever(stop_event)         # tick every tick_s until stop_event is set
    d.stop()

Each tick, in this order:
1. monitor: memory, CPU, temperature; the throttle level (hysteresis, monitor.ThrottlePolicy);
   a level change is written on the active local run (+ a `throttle` run event) or, with no run,
   pushed as `system.throttle` directly;
2. remote reports: what the jobs of workers on other machines reported through Redis is applied
   to the registry (remote.py), before anything judges their heartbeats;
3. paused runs the daemon paused (thermal, memory, disk) are requeued when the host allows;
4. reconcile: runs whose worker child is gone are interrupted and requeued (reconcile.py);
5. continuous learning: the phase, and a chain queued on the inbox when enough new episodes came
   and the host is idle (continuous.py); then dispatch: the next queued run on every idle queue
   (dispatch.py), none on a hot host, none on a local queue while the app paused learning;
6. remote control: the control state of every running remote run is published to Redis;
7. retention: old runs' dirs pruned once a run has finished (disk_guard.py, settings.keep_runs);
   events: new run_events rows to the sink; `system.stats` every stats_every_s (the monitor's
   sample + "throttle_level"; by default settings.system_sample_s); the host's history: a sample
   every settings.system_sample_s into a one-hour ring and the registry (system_history.py;
   refilled from the registry at start);
8. sd_notify WATCHDOG (when systemd asked for it), after a tick that worked.

Which runs are remote: with remote_reports=True (`run_trainer.py daemon`) and a Redis URL, those
on a queue outside local_queues; their worker may be on another machine, where hope.db is out of
reach. `serve` keeps the default False: it runs the worker itself, so every queue is local.
A failing tick (the database locked past its busy timeout, a broker error) is logged and the next
tick tries again; the state is all in the registry, so nothing is lost by skipping one.
The daemon never imports torch.
"""
from __future__ import annotations

import logging
import threading
import time
from typing import Any, Iterable

from sqlalchemy import select

from daemon.autopromote import AutoPromoter
from daemon.continuous import ContinuousLearning
from daemon.dispatch import Dispatcher
from daemon.events import STATS_EVENT, THROTTLE_EVENT, EventSink, EventTailer, NullSink
from daemon.monitor import SystemMonitor, ThrottleChange, ThrottlePolicy
from daemon.reconcile import Reconciler
from daemon.remote import RemoteReports
from daemon.sdnotify import SdNotifier
from daemon.system_history import SystemHistory
from registry import runs
from registry.db import Registry
from registry.models import Run

log = logging.getLogger(__name__)

START_BATCHES = 200  # reports applied at start, in batches: a backlog of hours from a remote job
# A client may send requests as fast as it likes, and each wakes the daemon: a burst is answered by
# one tick per MIN_TICK_GAP_S, not one tick per request (a tick samples the system, reconciles, and
# dispatches, all in the process that also answers the robot).
MIN_TICK_GAP_S = 0.2
# Retention looks at every finished run the registry holds; runs finishing by the hundred (a flood
# of cancelled requests) make it look at most this often.
PRUNE_EVERY_S = 10.0


class Daemon:
    def __init__(self, settings: Any, sink: EventSink | None = None, *, tick_s: float = 0.5,
                 stats_every_s: float | None = None, heartbeat_timeout_s: float = 30.0, claim_timeout_s: float = 600.0,
                 memory_retry_s: float = 60.0, local_queues: Iterable[str] = ("pi",),
                 monitor: SystemMonitor | None = None, policy: ThrottlePolicy | None = None,
                 celery_app: Any = None, notifier: SdNotifier | None = None, host: str | None = None,
                 registry: Any = None, send: Any = None, remote_reports: bool = False, redis_client: Any = None):
        self.settings = settings
        self.sink = sink or NullSink()
        self.tick_s = float(tick_s)
        # the live chart gets a point per history sample unless asked otherwise
        self.stats_every_s = float(getattr(settings, "system_sample_s", 5.0) if stats_every_s is None else stats_every_s)
        self.heartbeat_timeout_s = float(heartbeat_timeout_s)
        self.claim_timeout_s = float(claim_timeout_s)
        self.memory_retry_s = float(memory_retry_s)
        self.local_queues = tuple(local_queues)
        self.remote_reports = bool(remote_reports and settings.redis_url)
        self._redis_client = redis_client  # tests may pass one (fakeredis); else built from settings.redis_url
        self.monitor = monitor or SystemMonitor(settings)
        self.policy = policy or ThrottlePolicy.from_settings(settings)
        self.notifier = notifier or SdNotifier()
        self.host = host
        self._celery_app = celery_app
        self._send = send  # (run_id, attempt, queue, task_id) -> None instead of Celery (tests)
        self.registry = registry
        self._own_registry = registry is None
        self.dispatcher: Dispatcher | None = None
        self.reconciler: Reconciler | None = None
        self.tailer: EventTailer | None = None
        self.remote: RemoteReports | None = None
        self.autopromoter: AutoPromoter | None = None
        self.learning: ContinuousLearning | None = None
        self.history: SystemHistory | None = None
        self._remote_failures = 0
        self.last_sample: dict[str, Any] | None = None
        self._stats_at: float | None = None
        self._pruned_at: float | None = None
        self._failures = 0
        self.ticks = 0
        self._status = ""
        self._wake = threading.Event()

    # -- lifecycle ---------------------------------------------------------------------------

    def start(self) -> None:
        if self.registry is None:

            self.registry = Registry.open(self.settings, migrate=True)  # the daemon migrates once, here
        self.dispatcher = Dispatcher(self.registry, self.settings, celery_app=self._celery_app,
                                     local_queues=self.local_queues, memory_retry_s=self.memory_retry_s,
                                     remote_reports=self.remote_reports, send=self._send)
        self.reconciler = Reconciler(self.registry, host=self.host, heartbeat_timeout_s=self.heartbeat_timeout_s,
                                     claim_timeout_s=self.claim_timeout_s, resend=self.dispatcher.resend)
        self.tailer = EventTailer(self.registry, self.sink)
        self.autopromoter = AutoPromoter(self.settings, self.registry)
        self.learning = ContinuousLearning(self.settings, self.registry, local_queues=self.local_queues,
                                           disk_guard=self.dispatcher.disk, autopromoter=self.autopromoter)
        self.learning.start()
        self._start_history()
        if self.remote_reports:
            client = self._redis_client
            if client is None:
                import redis  # lazy: loads redis

                client = redis.Redis.from_url(self.settings.redis_url, socket_timeout=10, socket_connect_timeout=10)
            self.remote = RemoteReports(self.registry, client, local_queues=self.local_queues)
            # What remote children said while we were down, before their heartbeats are judged.
            self.remote_step(lambda: self.remote.poll(batches=START_BATCHES))
        # What a crash (ours or a worker's) left behind; a dispatch this daemon committed but may
        # not have sent before it died is re-sent after heartbeat_timeout_s, not claim_timeout_s.
        for action in self.reconciler.reconcile(claim_timeout_s=min(self.claim_timeout_s, self.heartbeat_timeout_s)):
            log.info("start: run %s %s (%s)", action.run_id, action.action, action.why)
        log.info("daemon started: registry %s, queues local %s, broker %s, %s", self.registry.path,
                 ",".join(self.local_queues), "redis" if self.settings.redis_url else "embedded sqlite",
                 "jobs on other queues report through Redis" if self.remote_reports
                 else "every job writes the registry directly")

    def _start_history(self) -> None:
        self.history = SystemHistory(self.registry, getattr(self.settings, "system_sample_s", 5.0))
        try:
            log.info("system history: %d sample(s) of the last hour from the registry", self.history.refill())
        except Exception as exc:  # noqa: BLE001 - an empty chart is no reason not to start
            log.warning("system history: could not read the last hour from the registry: %s: %s",
                        type(exc).__name__, exc)

    def stop(self) -> None:
        self.notifier.stopping()
        if self.history is not None and self.registry is not None:
            self.history.flush()
        if self.autopromoter is not None:
            self.autopromoter.close()  # stops a gate still running (its child has its own session)
        if self.registry is not None and self._own_registry:
            self.registry.close()
            self.registry = None
        log.info("daemon stopped")

    def run_forever(self, stop_event: threading.Event) -> None:
        if self.dispatcher is None:
            self.start()
        try:
            status = self.status_text()
        except Exception:  # noqa: BLE001 - READY matters more than its status line
            status = "started"
        self.notifier.ready(status)
        while not stop_event.is_set():
            started = time.monotonic()
            self.safe_tick()
            if self._wake.wait(max(0.0, self.tick_s - (time.monotonic() - started))):
                self._wake.clear()
                stop_event.wait(max(0.0, MIN_TICK_GAP_S - (time.monotonic() - started)))

    def wake(self) -> None:
        """Tick now rather than at the next tick_s (the webapp calls it after an enqueue or a
        control request, so a new run starts without waiting). Safe from any thread."""
        self._wake.set()

    # -- one tick ----------------------------------------------------------------------------

    def safe_tick(self) -> bool:
        try:
            self.tick()
        except Exception:  # noqa: BLE001 - the next tick retries; say so loudly but once per streak
            self._failures += 1
            if self._failures == 1 or self._failures % 100 == 0:
                log.exception("daemon tick failed (%d in a row); retrying", self._failures)
            return False
        if self._failures:
            log.info("daemon tick works again after %d failures", self._failures)
        self._failures = 0
        self.notifier.maybe_watchdog()  # only a working loop keeps systemd's watchdog quiet
        return True

    def tick(self) -> None:
        assert self.dispatcher is not None and self.reconciler is not None and self.tailer is not None, \
            "Daemon.start() first"
        assert self.learning is not None and self.autopromoter is not None, "Daemon.start() first"
        sample = self.monitor.sample()
        self.last_sample = sample
        change = self.policy.update_from_sample(sample)
        self.apply_throttle(change)
        self._observe(sample)
        if self.remote is not None:
            self.remote_step(self.remote.poll)
        self.dispatcher.requeue_paused(self.policy.level, sample.get("mem_available_mb"))
        self.reconciler.reconcile()
        self.learning.tick(sample, self.policy.level)
        self.dispatcher.dispatch(self.policy.level)
        if self.remote is not None:
            self.remote_step(self.remote.publish_running)
        self.autopromoter.tick()  # returns at once; one promote child at a time
        now = time.monotonic()
        if self._pruned_at is None or now - self._pruned_at >= PRUNE_EVERY_S:
            self._pruned_at = now
            self.dispatcher.disk.maybe_prune()  # retention, once a run has finished (daemon/disk_guard.py)
        self.tailer.poll()
        if self._stats_at is None or now - self._stats_at >= self.stats_every_s:
            self._stats_at = now
            self.tailer.push(STATS_EVENT, {**sample, "throttle_level": self.policy.level})
        self.ticks += 1
        self._update_status()

    def _observe(self, sample: dict[str, Any]) -> None:
        if self.history is None:
            return
        try:
            self.history.observe(sample, self.policy.level)  # its registry writes catch their own errors
        except Exception:  # noqa: BLE001 - a malformed sample must not stop the tick
            log.exception("system history: sample not recorded")

    def remote_step(self, step) -> None:
        """Redis being away must not stop the rest of the tick (local runs, monitors, events):
        the reports wait in Redis, and the remote runs' heartbeats judge them meanwhile."""
        import redis  # lazy: loads redis

        try:
            step()
        except redis.RedisError as exc:
            self._remote_failures += 1
            if self._remote_failures == 1 or self._remote_failures % 100 == 0:
                log.warning("remote workers: Redis unreachable (%d in a row): %s: %s", self._remote_failures,
                            type(exc).__name__, exc)
            return
        if self._remote_failures:
            log.info("remote workers: Redis reachable again after %d failures", self._remote_failures)
        self._remote_failures = 0

    def apply_throttle(self, change: ThrottleChange | None) -> None:
        """Keep throttle_level of every running local run equal to the policy's level. Checked
        every tick (not only on a change): a run dispatched or claimed meanwhile gets it too."""
        level = self.policy.level
        if change is not None:
            log.info("throttle level %d -> %d: %s", change.previous, change.level, change.reason)
        with self.registry.session(readonly=True) as s:
            stale = s.scalars(select(Run.id).where(Run.state.in_(runs.ACTIVE), Run.queue.in_(self.local_queues),
                                                   Run.throttle_level != level)).all()
        written = False
        for run_id in stale:
            with self.registry.session() as s:
                run = runs.get_run(s, run_id)
                if run.state not in runs.ACTIVE or run.throttle_level == level:
                    continue
                previous = run.throttle_level
                run.throttle_level = level
                reason = change.reason if change is not None else "the host's current throttle level"
                runs.add_event(s, run.id, "throttle", {
                    "level": level, "previous": previous, "reason": reason, "source": "daemon",
                    "temp_c": (self.last_sample or {}).get("temp_c")})
                written = True
        if change is not None and not written:
            # No run to record it on: browsers still hear about it.
            assert self.tailer is not None, "Daemon.start() first"  # tick() asserts it before calling here
            self.tailer.push(THROTTLE_EVENT, {**change.to_json_obj(), "run_id": None, "source": "daemon"})

    # -- status ------------------------------------------------------------------------------

    def status_text(self) -> str:
        if self.registry is None:
            return "starting"
        with self.registry.session(readonly=True) as s:
            active = s.scalars(select(Run).where(Run.state.in_(runs.ACTIVE))).all()
            queued = len(s.scalars(select(Run.id).where(Run.state == "queued")).all())
        parts = [f"{r.id} {r.component} " + (f"waiting for a worker on queue {r.queue}" if r.state == "starting"
                                             else f"step {r.step}/{r.total_steps}") for r in active] or ["idle"]
        return "; ".join(parts) + f"; {queued} queued; throttle {self.policy.level}"

    def _update_status(self) -> None:
        if not self.notifier.enabled or self.ticks % max(1, int(5 / max(self.tick_s, 0.01))):
            return
        text = self.status_text()
        if text != self._status:
            self._status = text
            self.notifier.status(text)


__all__ = ["Daemon"]
