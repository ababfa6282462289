"""`run_trainer.py sequential --components vqvae,fast_loop,mid_loop --data DS --steps N`: queue a chain.

One run per component, in order, sharing a sequence id: each starts only after the previous one
completed (each in its own worker child), and fast_loop / mid_loop read the codes of the chain's
vqvae run. If a member fails or is cancelled, the rest are cancelled with that reason. Prints the
run ids, one per line (`--json`: {"sequence_id", "runs": [{"id", "component", "state", "run_dir"}]}).
Like enqueue, it only writes the registry: it works whether the daemon is up or not.
"""
from __future__ import annotations

import argparse

from daemon.cli.enqueue import add_job_options, overrides_from_args
from daemon.cli.registry import CommandError, open_registry, print_json, run_command
from hope_models.components.chain import SequenceError, parse_sequence
from hope_models.train.config import add_flag
from registry.run_request import build_request, queue_sequence


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--components", required=True, metavar="LIST",
                        help="comma-separated components in training order, e.g. vqvae,fast_loop,mid_loop")
    add_job_options(parser)
    vq = parser.add_mutually_exclusive_group()
    add_flag(vq, "vqvae_dir", help="a trained VQ-VAE for a chain without vqvae (checkpoint dir or run dir)")
    vq.add_argument("--vqvae-run", metavar="RUN", default=None, help="or the id of a vqvae run in the registry")


def run(args: argparse.Namespace) -> int:
    def body() -> int:
        try:
            names = parse_sequence(args.components)
        except SequenceError as exc:
            raise CommandError(str(exc).replace("--sequential", "--components")) from None
        # the fields every member shares, checked as enqueue checks them
        req = build_request(component=names[0], data=args.data, steps=args.steps, queue=args.queue,
                            priority=args.priority, max_attempts=args.max_attempts, vqvae_dir=args.vqvae,
                            vqvae_run=args.vqvae_run, overrides=overrides_from_args(args))
        with open_registry() as (settings, registry):
            sequence_id, members = queue_sequence(
                registry, settings, names, req,
                show=lambda s, r: {"id": r.id, "component": r.component, "state": r.state, "run_dir": r.run_dir})
            out = {"sequence_id": sequence_id, "runs": members}
        if args.json:
            print_json(out)
        else:
            for r in out["runs"]:
                print(r["id"])
        return 0

    return run_command(body)
