"""`hope-trainer demo`: the whole loop on this machine, through the real services, in one command.

    hope-trainer demo [--episodes 50] [--steps N] [--eval-episodes 20] [--exit] [--port 8765]
    hope-trainer demo --camera [...]      the same loop on the camera observation (demo/camera.py)

1. records expert demonstrations in the simulated reacher (DART noise 1.0, seeds from 100000) into
   $HOPE_HOME/demo/reach-<N>-dart<noise>/ (reused when already there);
2. starts what `serve` starts, in this process (hope_trainer/commands/serve.py's Serve: the webapp, the daemon,
   BrainService and the worker child on the embedded broker);
3. queues the chain vqvae, fast_loop, mid_loop through the registry, as `hope-trainer sequential`
   does, and shows each run's progress in the terminal while the worker trains it;
4. auto-promotion gates every completed run (finite weights, validation loss, the vqvae's and the
   mid_loop's held-out figures against their baselines, the sim reflex);
   as soon as BrainService serves the new fast_loop, one inference goes through the HTTP API with
   the token (that first answer closes the loop: its run's loop-closure time is recorded);
5. evaluates the promoted fast_loop in closed loop on held-out seeds 0..N-1 with the expert and a
   random policy (`eval-reflex --checkpoint promoted`, a child process);
6. prints the summary table, writes it as JSON to $HOPE_HOME/demo/summary.json, prints the Robot
   Editor URL and token, and keeps serving until Ctrl-C (`--exit`: stops after the summary).
   While it serves, continuous learning is on (auto_train, daemon/continuous.py): episodes the
   Continuon app hands off land in the inbox, and once auto_train_min_new_episodes new ones came a
   chain trains on them by itself. Until the summary it is off, whatever the settings say: the
   demo's own data is not in the inbox, and an auto chain must not change what the demo measures.

Exit 0 when every run completed, the gate promoted each of them (the vqvae and the mid_loop only
when they beat their baselines on held-out episodes: hope_models/promote/baselines.py), the
fast_loop was served, and its mean return is at least --target-return (900); 1 otherwise, saying what fell short; 2 when it cannot start (port taken,
settings); 130 after Ctrl-C before the summary. This process never imports torch or MuJoCo: the
recording, training, gating and evaluation all run in child processes.

--camera runs the loop on the camera observation (the joints and a 64x64 top-down frame), each
component with its own step count from hope_trainer/demo/camera.py's CAMERA recipe (--steps, when
given, replaces them all), writes $HOPE_HOME/demo/camera/summary.json, and stops at the first stage
that fails, naming it (exit 1). It refuses (exit 2) fewer than 3 episodes and a $HOPE_HOME whose
promoted models read no camera (BrainService would refuse the camera models beside them).

Steps (hope_trainer/demo/chain.py's STATE_STEPS; --steps gives every member the same count): the
vqvae and the fast_loop 4000, the mid_loop 1000. Measured on 2 busy cores, a fast_loop reading the
chain's VQ-VAE codes, trained on 50 DART demos, scored 978 (2000 steps), 984 (4000) and 981
(10 000) on seeds 0-19. The mid_loop is the slow member, and its held-out figures are best near
1000 steps and only worse after (docs/training.md, "How many steps"): 4000 cost minutes for a
worse predictor.
"""
from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
from pathlib import Path
from typing import Any

from hope_models.cli.argtypes import positive_int
from hope_models.durable import atomic_write
from hope_models.settings import SettingsError
from hope_trainer.commands.serve import add_listen_arguments, listen_settings, setup_logging
from hope_trainer.demo.camera import CameraDemo, camera_problem, served_layout_problem
from hope_trainer.demo.report import format_summary, verdict
from hope_trainer.demo.session import Demo
from hope_trainer.demo.shared import DemoError, Interrupted, say
from registry.run_request import RunRequestError
from webapp.server import ServerError

log = logging.getLogger("hope.demo")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--episodes", type=positive_int, default=50, help="expert demonstrations to record (default 50)")
    parser.add_argument("--noise", type=float, default=1.0, help="DART noise of the demonstrations (default 1.0)")
    parser.add_argument("--steps", type=positive_int, default=None,
                        help="training steps of every component (default: each component's own, 4000 for the "
                             "vqvae and the fast_loop and 1000 for the mid_loop; with --camera, the camera recipe's)")
    parser.add_argument("--seed", type=int, default=0, help="training seed (default 0)")
    parser.add_argument("--eval-episodes", type=positive_int, default=20,
                        help="held-out reacher seeds 0..N-1 the reflex is evaluated on (default 20)")
    parser.add_argument("--target-return", type=float, default=900.0,
                        help="the mean return the promoted fast_loop must reach (default 900)")
    add_listen_arguments(parser)
    parser.add_argument("--queue", default="pi", help="the queue the demo's runs and its worker use (default pi)")
    parser.add_argument("--exit", action="store_true", help="stop after the summary instead of serving on")
    parser.add_argument("--camera", action="store_true",
                        help="the camera observation: joints + a 64x64 top-down frame instead of the target offset "
                             "(grid VQ-VAE, Fast Loop over its codes, grid Mid Loop; hope_trainer/demo/camera.py)")


def _run_demo(demo: Any) -> tuple[int, dict[str, Any] | None]:
    """The demo up to its summary: (exit code, summary), the summary None when it stopped early."""
    from registry.db import RegistryError  # lazy: loads sqlalchemy
    from registry.runs import RunError  # lazy: loads sqlalchemy
    from webapp.auth import TokenError  # lazy: loads flask

    try:
        return 0, demo.run()
    except Interrupted:
        print("\ninterrupted: stopping (the running job checkpoints and goes back to the queue; "
              "`run_trainer.py serve` resumes it)", file=sys.stderr, flush=True)
        code = 130
    except (RegistryError, TokenError, ServerError, SettingsError, RunRequestError, RunError, OSError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        code = 2
    except DemoError as exc:
        print(f"error: {exc}", file=sys.stderr)
        code = 1
    demo.stop()
    return code, None


def _report(summary: dict[str, Any], out: Path, target_return: float) -> bool:
    """Judge the summary, write it to `out` ($HOPE_HOME/demo/summary.json) and print it; True when it passed."""
    problems = verdict(summary, target_return)
    log.info("demo finished in %.0f s: %s", summary["timings"]["total"], "; ".join(problems) or "ok")
    summary["ok"] = not problems
    summary["problems"] = problems
    atomic_write(out, json.dumps(summary, indent=1))
    say(format_summary(summary))
    say("")
    if problems:
        say("The demo fell short:\n" + "\n".join(f"  - {p}" for p in problems))
    else:
        say(f"The promoted fast_loop reaches {summary['reflex']['mean_return']:.1f} on held-out seeds "
            f"(target {target_return:g}). Whole demo {summary['timings']['total'] / 60:.1f} min.")
    say(f"\nsummary: {out}")
    return not problems


def run(args: argparse.Namespace) -> int:
    problem = camera_problem(args) if args.camera else None
    if problem:
        print(f"error: {problem}", file=sys.stderr)
        return 2
    try:
        settings = listen_settings(args)
    except SettingsError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    problem = served_layout_problem(settings.home) if args.camera else None
    if problem:
        print(f"error: the camera demo cannot start: {problem}", file=sys.stderr)
        return 2
    if not settings.auto_promote:
        say("note: auto_promote is off in the settings; the demo turns it on for this process (it gates each run)")
        settings.auto_promote = True
    setup_logging(settings.home, console_level=logging.WARNING, settings=settings)
    settings.auto_train = False  # the daemon reads it each tick: nothing starts by itself before the summary
    demo = CameraDemo(settings, args) if args.camera else Demo(settings, args)

    def on_signal(signum, _frame):
        if demo.serve is not None and demo.shutdown.is_set():
            demo.serve.force.set()  # a second Ctrl-C: do not wait for the running job
        demo.shutdown.set()
        if demo.serve is not None:
            demo.serve.shutdown.set()

    previous = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    say(f"HOPE Seed Trainer demo: state in {settings.home}\n")
    try:
        code, summary = _run_demo(demo)
        if summary is None:
            return code
        code = 0 if _report(summary, demo.summary_path(), args.target_return) else 1
        say(f"Robot Editor: {demo.url}  token: {demo.token}")
        if args.exit:
            demo.stop()
            return code
        settings.auto_train = True  # continuous learning while it serves (see the module doc)
        say(f"continuous learning is on: episodes the Continuon app hands off go to {settings.inbox_dir}; "
            f"after {settings.auto_train_min_new_episodes} new trainable ones, "
            f"{','.join(settings.auto_train_components)} train on them by itself (GET /api/learning/status)")
        say("serving until Ctrl-C (runs, models, live progress of new runs, inference and the reflex view)")
        while not demo.shutdown.is_set():
            demo.shutdown.wait(0.5)
        demo.stop()
        return code
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
