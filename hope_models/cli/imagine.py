"""`run_trainer.py imagine --out DIR --episodes N`: imagined rollouts by offline search, stored as RLDS.

    run_trainer.py imagine --out datasets/imag50 --episodes 50 [--method dart|cem] [--task reach|track]
                           [--seed S] [--noise SIGMA] [--demos DIR ...] [--frames] [--json]

Each episode starts from a task seed in [S, S+N) (default S = 200000, outside the evaluation seeds
0..99999 and the demo seeds 100000..199999; see hope_models/sim/imagine.py), is searched by DART
(the expert with noise injected into what is executed, labelled with the expert's correction) or
CEM (sampling-based MPC with the simulator as the model), and is written as a canonical RLDS dir
with provenance origin `imagined:<method>` and the tag `continuon.imagined`, validated with the
train profile. Exit 0 on success, 2 for a usage error (bad option, seeds overlapping the reserved
ranges or the given demos, an episode dir that already exists).
"""
from __future__ import annotations

import argparse
import json
import sys

from hope_models.cli.argtypes import non_negative_float, non_negative_int, positive_int


def add_arguments(parser: argparse.ArgumentParser) -> None:
    # defaults are repeated here (not imported) so that parsing never imports dm_control
    parser.add_argument("--out", required=True, metavar="DIR", help="dataset dir the episode dirs are written into")
    parser.add_argument("--episodes", required=True, type=positive_int, metavar="N", help="rollouts to imagine")
    parser.add_argument("--method", choices=("dart", "cem"), default="dart",
                        help="dart: noise-perturbed expert, labelled with the expert's correction (default); "
                             "cem: cross-entropy-method MPC with the simulator as the model")
    parser.add_argument("--task", choices=("reach", "track"), default="reach")
    parser.add_argument("--seed", type=non_negative_int, default=200_000,
                        help="first task seed; episode i uses seed+i (default 200000: outside the eval and demo seeds)")
    parser.add_argument("--noise", type=non_negative_float, default=None, metavar="SIGMA",
                        help="std of the Gaussian noise added to the executed command while the label stays the "
                             "searcher's action (DART); default 2.0; 0 records the search's own trajectories")
    parser.add_argument("--steps", type=positive_int, default=1000, help="control steps per episode (default 1000)")
    parser.add_argument("--horizon", type=positive_int, default=None, help="cem: planning horizon in steps (12)")
    parser.add_argument("--population", type=positive_int, default=None, help="cem: candidates per iteration (32)")
    parser.add_argument("--iterations", type=positive_int, default=None, help="cem: refits per control step (2)")
    parser.add_argument("--elites", type=positive_int, default=None, help="cem: elites per refit (6)")
    parser.add_argument("--demos", nargs="+", metavar="DIR", default=(),
                        help="recorded demos whose start states (task, seed) must not be reused")
    parser.add_argument("--allow-overlap", action="store_true",
                        help="allow seeds inside the reserved evaluation / demo ranges")
    parser.add_argument("--frames", action="store_true", help="also store 64x64 frames as .npy blobs (MUJOCO_GL=egl)")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")


def run(args: argparse.Namespace) -> int:
    from hope_models.sim import reacher

    if args.frames:
        try:
            reacher._gl_backend(True)  # before dm_control is imported
        except RuntimeError as exc:
            print(f"imagine: {exc}", file=sys.stderr)
            return 2
    from hope_models.sim.imagine import CEMConfig, imagine_dataset

    if args.steps > reacher.EPISODE_STEPS:
        print(f"imagine: --steps {args.steps} must be at most {reacher.EPISODE_STEPS}", file=sys.stderr)
        return 2
    cem = CEMConfig()
    for name in ("horizon", "population", "iterations", "elites"):
        if getattr(args, name) is not None:
            setattr(cem, name, getattr(args, name))

    def progress(ep) -> None:
        if not args.json:
            print(f"{ep.episode_id}: seed {ep.seed}, return {ep.ret:.0f}, {ep.steps} steps", flush=True)

    try:
        result = imagine_dataset(args.out, args.episodes, seed=args.seed, method=args.method, task=args.task,
                                 noise=args.noise, cem=cem, steps=args.steps, frames=args.frames, demos=args.demos,
                                 allow_overlap=args.allow_overlap, progress=progress)
    except (ValueError, FileExistsError, FileNotFoundError, NotADirectoryError) as exc:
        if args.json:
            print(json.dumps({"outcome": "error", "message": str(exc)}))
        print(f"imagine: {exc}", file=sys.stderr)
        return 2
    if args.json:
        print(json.dumps({"outcome": "completed", **result.to_json_obj()}))
    else:
        print(f"imagined {len(result.episodes)} {args.task} rollouts ({result.to_json_obj()['origin']}, seeds "
              f"{args.seed}..{args.seed + len(result.episodes) - 1}) into {result.out_dir}: mean return "
              f"{result.mean_return:.1f}, {result.elapsed_s:.1f} s")
    return 0
