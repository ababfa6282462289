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

from hope_models.cli.argtypes import json_object, non_negative_int, positive_float, positive_int
from hope_models.train.contract import COMPONENTS

# TrainConfig override -> the CLI attribute it comes from
OVERRIDE_ARGS = {
    "seed": "seed",
    "batch_size": "batch_size",
    "lr": "lr",
    "warmup": "warmup",
    "threads": "threads",
    "checkpoint_every_steps": "checkpoint_every",
    "checkpoint_every_s": "checkpoint_seconds",
    "keep_last": "keep",
    "log_every": "log_every",
    "memory_budget_mb": "memory_budget_mb",
    "imagined_ratio": "imagined_ratio",
    "model_config": "model_config",
}


def _int(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None


def add_job_options(parser: argparse.ArgumentParser) -> None:
    """Options shared by enqueue and sequential: what to train on and how; all optional except --data."""
    from registry.run_request import DEFAULT_STEPS

    parser.add_argument("--data", required=True, metavar="PATH",
                        help="RLDS dataset dir, episode dir or episode file (made absolute)")
    parser.add_argument("--steps", type=positive_int, default=DEFAULT_STEPS,
                        help=f"total optimizer steps (default {DEFAULT_STEPS})")
    parser.add_argument("--seed", type=non_negative_int, default=None, help="default 0")
    parser.add_argument("--batch-size", type=positive_int, default=None, help="default 64")
    parser.add_argument("--lr", type=positive_float, default=None, help="peak learning rate (default 1e-3)")
    parser.add_argument("--warmup", type=non_negative_int, default=None, help="warmup steps (default 100)")
    parser.add_argument("--threads", type=positive_int, default=None, help="torch threads (default 1: small models on shared cores)")
    parser.add_argument("--checkpoint-every", type=positive_int, default=None, metavar="N",
                        help="checkpoint every N steps (default 500)")
    parser.add_argument("--checkpoint-seconds", type=positive_float, default=None, metavar="T",
                        help="and every T seconds (default 300)")
    parser.add_argument("--keep", type=positive_int, default=None, metavar="K", help="keep the last K checkpoints")
    parser.add_argument("--log-every", type=positive_int, default=None, metavar="N", help="metrics every N steps")
    parser.add_argument("--memory-budget-mb", type=positive_float, default=None,
                        help="the job's memory budget (default: settings, 3072)")
    parser.add_argument("--imagined-ratio", type=float, default=None, help="share of imagined episodes in a batch")
    parser.add_argument("--model-config", type=json_object, default=None, metavar="JSON",
                        help="model config overrides, e.g. '{\"d_model\": 64}'")
    parser.add_argument("--queue", default="pi", help="the worker queue that trains it (default pi)")
    parser.add_argument("--priority", type=_int, default=0, help="higher runs first (default 0)")
    parser.add_argument("--max-attempts", type=positive_int, default=3, metavar="K",
                        help="attempts before a run whose worker keeps dying is failed (default 3)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")


def overrides_from_args(args: argparse.Namespace) -> dict[str, Any]:
    return {key: getattr(args, attr) for key, attr in OVERRIDE_ARGS.items() if getattr(args, attr, None) is not None}


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--component", required=True, choices=COMPONENTS, help="the component to train")
    add_job_options(parser)
    vq = parser.add_mutually_exclusive_group()
    vq.add_argument("--vqvae", metavar="DIR", default=None,
                    help="a trained VQ-VAE (checkpoint dir or run dir) whose codes fast_loop/mid_loop read")
    vq.add_argument("--vqvae-run", metavar="RUN", default=None,
                    help="or the id of a vqvae run in the registry (it must complete first)")


def run(args: argparse.Namespace) -> int:
    from daemon.cli.registry import open_registry, print_json, run_command
    from registry.run_request import build_request, queue_run

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
