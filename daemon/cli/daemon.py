"""`run_trainer.py daemon`: the supervisor as a service (systemd hope-daemon.service, Type=notify).

    run_trainer.py daemon [--tick-s 0.5] [--heartbeat-timeout-s 30] [--log-level info]

Migrates the registry once, reconciles what a crash left, then ticks: monitors, throttle, requeue,
dispatch, events (see daemon/service.py). Events go to browsers through the Socket.IO message
queue on settings.redis_url (the webapp relays them); with the embedded broker and no Redis they
stay in the registry (use `serve`, which hosts the webapp and the daemon in one process).
sd_notify: READY=1 once started, WATCHDOG=1 at half WatchdogSec after ticks that worked,
STATUS= the active run, STOPPING=1 on SIGTERM/SIGINT, which stop it cleanly (exit 0). Stopping the
daemon does not stop a training job: the worker is its own service, and a restarted daemon finds
the run where it is.

Queues outside --local-queues are served by workers that may run on other machines (a desktop
with `run_trainer.py worker -Q gpu`): with a Redis URL, their jobs report through Redis and this
daemon writes their reports into the registry (docs/scale-out.md).
"""
from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading

from daemon.events import EventSink, NullSink, RedisEmitterSink
from daemon.sdnotify import SdNotifier
from hope_models.cli.argtypes import positive_float
from hope_models.log_format import configure_logging, journal_prefix
from hope_models.malloc_arenas import limit_malloc_arenas
from hope_models.settings import SettingsError, load_settings


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--tick-s", type=positive_float, default=0.5, metavar="S",
                        help="seconds between two rounds of monitor/dispatch/reconcile (default 0.5)")
    parser.add_argument("--heartbeat-timeout-s", type=positive_float, default=30.0, metavar="S",
                        help="a running job silent for this long is taken for dead and requeued (default 30)")
    parser.add_argument("--claim-timeout-s", type=positive_float, default=600.0, metavar="S",
                        help="a sent task not picked up for this long is sent again (default 600)")
    parser.add_argument("--stats-every-s", type=positive_float, default=None, metavar="S",
                        help="system.stats event interval (default: system_sample_s, HOPE_SYSTEM_SAMPLE_S, 5)")
    parser.add_argument("--local-queues", default="pi", metavar="LIST",
                        help="comma-separated queues whose worker runs on this host: this host's temperature "
                             "and memory govern them, and their jobs write the registry directly. Jobs on "
                             "other queues report through Redis, from any machine (default pi)")
    parser.add_argument("--log-level", default="info", choices=("debug", "info", "warning", "error"))


def run(args: argparse.Namespace) -> int:
    from registry.db import RegistryError  # lazy: loads sqlalchemy

    limit_malloc_arenas()  # a long-lived service: hope_models/malloc_arenas.py
    # under systemd each line carries its journal priority (<3> err ...), elsewhere a timestamp
    configure_logging(getattr(logging, args.log_level.upper()))
    log = logging.getLogger("daemon")
    try:
        settings = load_settings()
    except SettingsError as exc:
        print(f"{journal_prefix()}error: {exc}", file=sys.stderr)
        return 2

    from daemon.service import Daemon  # lazy: loads mcap, numpy, psutil, sqlalchemy

    sink: EventSink
    if settings.redis_url:
        sink = RedisEmitterSink(settings.redis_url)
    else:
        log.info("no redis_url: run events stay in the registry (the embedded mode pushes them from `serve`)")
        sink = NullSink()
    queues = [q.strip() for q in args.local_queues.split(",") if q.strip()]
    notifier = SdNotifier()
    daemon = Daemon(settings, sink, tick_s=args.tick_s, stats_every_s=args.stats_every_s,
                    heartbeat_timeout_s=args.heartbeat_timeout_s, claim_timeout_s=args.claim_timeout_s,
                    local_queues=queues, notifier=notifier, remote_reports=True)
    stop = threading.Event()

    def on_signal(signum, frame):
        log.info("%s: stopping", signal.Signals(signum).name)
        stop.set()

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)
    try:
        daemon.start()
    except (RegistryError, OSError) as exc:
        print(f"{journal_prefix()}error: {exc}", file=sys.stderr)
        return 2
    try:
        daemon.run_forever(stop)
    finally:
        daemon.stop()
    return 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="run_trainer.py daemon", description=__doc__.splitlines()[0])
    add_arguments(parser)
    return run(parser.parse_args(argv))


if __name__ == "__main__":
    sys.exit(main())
