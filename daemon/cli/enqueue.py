"""`run_trainer.py enqueue`: queue one training run for the daemon; prints its run id.

    run_trainer.py enqueue --component fast_loop --data DS --steps 2000 [--seed 0 ...] [--queue pi] [--json]

It only writes the registry, so it works whether the daemon is up or not: the run starts when the
daemon sees it (exactly one run trains at a time per queue, by priority then age). The options
mirror `train`'s; everything is checked here, as POST /api/runs checks it (registry/run_request.py:
a path that holds no usable episodes, a model_config the component or the memory budget cannot
take is refused now, not minutes later in the worker). `--json` prints {"id", "state", "run_dir"}.
"""
from __future__ import annotations

import argparse
from typing import Any

from daemon.cli.registry import open_registry, print_json, run_command
from hope_models.components import COMPONENTS
from hope_models.numbers import NumberError, int_from_text
from hope_models.train.config import DEFAULT_REQUEST_STEPS, OPTIONS, REQUEST_FIELDS, add_flag, add_flags, dest_of
from registry.run_request import build_request, queue_run


def _int(text: str) -> int:
    """A whole number by the one rule (hope_models/numbers.py); build_request checks its bounds."""
    try:
        return int_from_text("value", text)
    except NumberError as exc:
        raise argparse.ArgumentTypeError(exc.reason) from None


def add_job_options(parser: argparse.ArgumentParser) -> None:
    """Options shared by enqueue and sequential: what to train on and how (TrainConfig's request
    options, train/config.py), and where it queues; all optional except --data."""
    add_flag(parser, "data", required=True, help=OPTIONS["data"].help + " (made absolute)")
    add_flag(parser, "steps", default=DEFAULT_REQUEST_STEPS,
             help=f"total optimizer steps (default {DEFAULT_REQUEST_STEPS})")
    add_flags(parser, "request", skip=("vqvae_dir",))
    parser.add_argument("--queue", default="pi", help="the worker queue that trains it (default pi)")
    parser.add_argument("--priority", type=_int, default=0, help="higher runs first (default 0)")
    parser.add_argument("--max-attempts", type=_int, default=3, metavar="K",
                        help="attempts before a run whose worker keeps dying is failed (default 3)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")


# run config override -> the argparse attribute it comes from (both from train/config.py)
OVERRIDE_ARGS = {name: dest_of(name) for name in REQUEST_FIELDS if name != "vqvae_dir"}


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    """The TrainConfig options given on the command line (the run's config overrides); vqvae_dir
    is not one: a run request names it on its own (vqvae_dir / vqvae_run)."""
    return {key: getattr(args, attr) for key, attr in OVERRIDE_ARGS.items() if getattr(args, attr, None) is not None}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--component", required=True, choices=COMPONENTS, help="the component to train")
    add_job_options(parser)
    vq = parser.add_mutually_exclusive_group()
    add_flag(vq, "vqvae_dir")
    vq.add_argument("--vqvae-run", metavar="RUN", default=None,
                    help="or the id of a vqvae run in the registry (it must complete first)")


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        req = build_request(component=args.component, data=args.data, steps=args.steps, queue=args.queue,
                            priority=args.priority, max_attempts=args.max_attempts, vqvae_dir=args.vqvae,
                            vqvae_run=args.vqvae_run, overrides=overrides_from_args(args))
        with open_registry() as (settings, registry):
            out = queue_run(registry, settings, req, show=lambda s, r: {"id": r.id, "state": r.state,
                                                                        "run_dir": r.run_dir})
        if args.json:
            print_json(out)
        else:
            print(out["id"])
        return 0

    return run_command(body)
