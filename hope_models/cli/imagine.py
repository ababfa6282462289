"""`run_trainer.py imagine --out DIR --episodes N`: imagined rollouts by offline search, stored as RLDS.

    run_trainer.py imagine --out datasets/imag50 --episodes 50 [--method dart|cem] [--task reach|track]
                           [--seed S] [--noise SIGMA] [--demos DIR ...] [--frames] [--json]

    run_trainer.py imagine --method model --model RUN_DIR --demos DIR [--play DIR ...] --out DIR --episodes N

dart / cem search in the simulator: each episode starts from a task seed in [S, S+N) (default
S = 200000, outside the evaluation seeds 0..99999 and the demo seeds 100000..199999; see
hope_models/sim/imagine.py), is searched by DART (the expert with noise injected into what is
executed, labelled with the expert's correction) or CEM (sampling-based MPC with the simulator as
the model). model searches in a learned world model and never imports the simulator: a trained
mid_loop's action-conditioned heads, CEM inside them, start states and the goal from the recorded
--demos (and --play) episodes, --seed seeding the draws (hope_models/imagine/model_imagine.py); from a
camera world model (a grid mid_loop) the goal is read off the frames and each step gets a frame
(hope_models/imagine/frame_goal.py, camera_scene.py).
Every episode is written as a canonical RLDS dir with provenance origin `imagined:<method>` and
the tag `continuon.imagined`, validated with the train profile. Exit 0 on success, 2 for a usage
error (bad option, seeds overlapping the reserved ranges or the given demos, an episode dir that
already exists, no usable world model).
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
    parser.add_argument("--method", choices=("dart", "cem", "model"), default="dart",
                        help="dart: noise-perturbed expert, labelled with the expert's correction (default); "
                             "cem: cross-entropy-method MPC with the simulator as the model; "
                             "model: CEM in a learned world model (--model), no simulator")
    parser.add_argument("--model", metavar="RUN_DIR", default=None,
                        help="model: the world model, a trained mid_loop (a `train --sequential vqvae,mid_loop` "
                             "run dir, the mid_loop run dir or one of its checkpoints)")
    parser.add_argument("--play", nargs="+", metavar="DIR", default=None,
                        help="model: recorded play episodes to draw start states from too (default: the play "
                             "episodes of the dataset the world model was trained on, if it is still there)")
    parser.add_argument("--task", choices=("reach", "track"), default="reach")
    parser.add_argument("--seed", type=non_negative_int, default=200_000,
                        help="first task seed; episode i uses seed+i (default 200000: outside the eval and demo seeds)")
    parser.add_argument("--noise", type=non_negative_float, default=None, metavar="SIGMA",
                        help="std of the Gaussian noise added to the executed command while the label stays the "
                             "searcher's action (DART); default 2.0 (--method model: 0.5 per 100 ms grid step); 0 "
                             "records the search's own trajectories")
    parser.add_argument("--steps", type=positive_int, default=None,
                        help="control steps per episode (default 1000; model: 300)")
    parser.add_argument("--horizon", type=positive_int, default=None,
                        help="cem: planning horizon in steps (12); model: in grid steps of the world model (3)")
    parser.add_argument("--population", type=positive_int, default=None, help="cem: candidates per iteration (32)")
    parser.add_argument("--iterations", type=positive_int, default=None, help="cem: refits per control step (2)")
    parser.add_argument("--elites", type=positive_int, default=None, help="cem: elites per refit (6)")
    parser.add_argument("--demos", nargs="+", metavar="DIR", default=(),
                        help="recorded demos whose start states (task, seed) must not be reused; model: the demos "
                             "whose rewarded steps are the goal and whose states are start states (required)")
    parser.add_argument("--allow-overlap", action="store_true",
                        help="allow seeds inside the reserved evaluation / demo ranges")
    parser.add_argument("--frames", action="store_true", help="also store 64x64 frames as .npy blobs (MUJOCO_GL=egl)")
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")


def _error(args: argparse.Namespace, exc: Exception) -> int:
    if args.json:
        print(json.dumps({"outcome": "error", "message": str(exc)}))
    print(f"imagine: {exc}", file=sys.stderr)
    return 2


def run_model(args: argparse.Namespace) -> int:
    """--method model: nothing of the simulator is imported on this path (tests/test_imagine_model.py)."""
    from hope_models.imagine.model_imagine import DEFAULT_NOISE, imagine_model_dataset  # lazy: loads mcap, numpy, torch
    from hope_models.imagine.planner import PlanConfig  # lazy: loads mcap, numpy, torch

    if args.model is None:
        return _error(args, ValueError("--method model needs --model RUN_DIR (a trained mid_loop)"))
    if args.frames:
        return _error(args, ValueError("--frames: --method model writes a frame per step when its world model "
                                       "reads a camera (a grid mid_loop), and none otherwise"))
    plan = PlanConfig()
    for name in ("horizon", "population", "iterations", "elites"):
        if getattr(args, name) is not None:
            setattr(plan, name, getattr(args, name))

    def progress(rec) -> None:
        if not args.json:
            print(f"{rec['episode_id']}: from {rec['start']['episode_id']} step {rec['start']['step']}, "
                  f"{rec['steps']} steps, final goal distance {rec['final_goal_distance']:.2f}", flush=True)

    try:
        result = imagine_model_dataset(args.out, args.episodes, model=args.model, demos=args.demos, play=args.play,
                                       seed=args.seed, noise=DEFAULT_NOISE if args.noise is None else args.noise,
                                       steps=args.steps or 300, plan=plan, progress=progress)
    except (ValueError, FileExistsError, FileNotFoundError, NotADirectoryError) as exc:
        return _error(args, exc)
    obj = result.to_json_obj()
    if args.json:
        print(json.dumps({"outcome": "completed", **obj}))
    else:
        print(f"imagined {len(result.episodes)} rollouts in the world model {obj['settings']['model']} into "
              f"{result.out_dir}: mean final goal distance {obj['mean_final_goal_distance']}, {result.elapsed_s:.1f} s")
    return 0


def run(args: argparse.Namespace) -> int:
    if args.method == "model":
        return run_model(args)
    if args.model is not None or args.play:
        return _error(args, ValueError("--model and --play are for --method model"))
    from hope_models.sim import reacher  # lazy: loads numpy

    args.steps = args.steps or reacher.EPISODE_STEPS

    if args.frames:
        try:
            reacher._gl_backend(True)  # before dm_control is imported
        except RuntimeError as exc:
            print(f"imagine: {exc}", file=sys.stderr)
            return 2
    from hope_models.sim.imagine import CEMConfig, imagine_dataset  # lazy: loads mcap, numpy

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
        return _error(args, exc)
    if args.json:
        print(json.dumps({"outcome": "completed", **result.to_json_obj()}))
    else:
        print(f"imagined {len(result.episodes)} {args.task} rollouts ({result.to_json_obj()['origin']}, seeds "
              f"{args.seed}..{args.seed + len(result.episodes) - 1}) into {result.out_dir}: mean return "
              f"{result.mean_return:.1f}, {result.elapsed_s:.1f} s")
    return 0
