"""`run_trainer.py sim-demos`: record reacher episodes (expert demonstrations or play) as canonical RLDS.

    run_trainer.py sim-demos --episodes 50 --out ~/datasets/reach50 [--task reach|track]
        [--seed 100000] [--policy expert|play] [--noise 1.0] [--frames]
        [--observation state|camera] [--frame-size 64|96] [--json]

Episode i uses seed S+i (default S = 100000, away from eval-reflex's default held-out seeds 0..N-1).
--noise SIGMA drives the env with the expert's action plus N(0, SIGMA^2) while the recorded
action.command stays the expert's (DART); expert demos default to 1.0, the recipe docs/reflex.md
measures (50 demos without noise clone into a reflex that misses the target on some seeds);
--noise 0 records clean demos. --frames adds a 64x64 top-down frame per step as
blobs/step_NNNNNN_rgb.npy (needs MUJOCO_GL=egl, set automatically unless you set MUJOCO_GL).
--observation camera records what a robot has instead of the engineered state: the joints and the
camera frame (observation.camera, 64x64 or --frame-size 96), no target_offset; the expert still
acts on the state and the simulator still scores the episode (reacher.camera_observation).
--policy play records play instead: smooth random exploration with no expert label (recorder.py,
expert.PlayPolicy), episode ids <prefix>-<task>-play-s<seed>, tagged "play"; world models and the
VQ-VAE learn from it, the fast_loop never clones it. Play records no noise; an explicit --noise
above 0 with play is a usage error (the expert's default noise does not apply to it).
Exit 0 on success, 2 for a usage error (an episode dir that already exists, a bad value, frames
without a GL backend, a --noise above 0 with --policy play).
"""
from __future__ import annotations

import argparse
import json
import sys
import time

from hope_models.child_result import add_result_argument, write_result
from hope_models.cli.argtypes import non_negative_float, non_negative_int, positive_int

# The recipe's DART noise for expert demos (docs/reflex.md, "What the recipe needs"): without it the
# demos hold ~20 informative steps each and a reflex cloned from the defaults missed the 900 target.
DEFAULT_EXPERT_NOISE = 1.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from hope_models.sim.reacher import RENDER_STYLE, RENDER_STYLES, TASKS  # lazy: loads numpy

    parser.add_argument("--episodes", type=positive_int, required=True, help="episodes to record")
    parser.add_argument("--out", required=True, metavar="DIR", help="dataset dir the episode dirs are written into")
    parser.add_argument("--task", choices=TASKS, default="reach", help="reach (dm_control reacher/easy) or track "
                        "(the target moves along a circle); default reach")
    parser.add_argument("--seed", type=non_negative_int, default=None,
                        help="seed of the first episode (default 100000; eval-reflex evaluates seeds 0..N-1 by default)")
    parser.add_argument("--noise", type=non_negative_float, default=None, metavar="SIGMA",
                        help="DART noise: std of the Gaussian added to the executed action (the recorded label stays "
                             f"the expert's); default {DEFAULT_EXPERT_NOISE:g} for expert demos (the documented "
                             "recipe), 0 = clean demos; play takes none")
    parser.add_argument("--policy", choices=("expert", "play"), default="expert",
                        help="expert: demonstrations (default); play: smooth random exploration without labels, "
                             "for the world model and the VQ-VAE (the fast_loop never clones it)")
    parser.add_argument("--steps", type=positive_int, default=None,
                        help="steps per episode (default and maximum 1000 = 20 s; fewer for a quick look)")
    parser.add_argument("--frames", action="store_true", help="also store a 64x64 RGB frame per step (MUJOCO_GL=egl)")
    parser.add_argument("--observation", choices=("state", "camera"), default="state",
                        help="state: joints + target_offset (the engineered state, default); camera: what a robot "
                             "has, the joints and the camera frame, nothing about the target (MUJOCO_GL=egl)")
    parser.add_argument("--frame-size", type=int, choices=(64, 96), default=64,
                        help="side of the camera frames in pixels (default 64)")
    parser.add_argument("--render", choices=RENDER_STYLES, default=RENDER_STYLE,
                        help=f"how frames are drawn (default {RENDER_STYLE}: no shadows or floor reflection, ~7x "
                             "cheaper to render; shaded: MuJoCo's defaults, as recordings before 2026-12-07)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")
    add_result_argument(parser)


def run(args: argparse.Namespace) -> int:
    from hope_models.sim.recorder import DEFAULT_SEED_BASE, record_dataset  # lazy: loads numpy

    seed = DEFAULT_SEED_BASE if args.seed is None else args.seed
    play = args.policy == "play"
    if play and args.noise:
        msg = (f"--noise {args.noise:g} with --policy play: play has no expert label for DART noise to keep, "
               "its executed command already is the exploration; drop --noise")
        write_result(args.result_file, {"ok": False, "error": msg})
        if args.json:
            print(json.dumps({"ok": False, "error": msg}))
        print(f"error: {msg}", file=sys.stderr)
        return 2
    # None = not given: the recipe's noise for the expert, none for play (which has no label to keep)
    noise = args.noise if args.noise is not None else (0.0 if play else DEFAULT_EXPERT_NOISE)
    started = time.perf_counter()

    def progress(rec) -> None:
        if not args.json:
            print(f"{rec.episode_id}: return {rec.ret:.0f}, {rec.steps} steps -> {rec.path}", file=sys.stderr)

    try:
        result = record_dataset(args.out, args.episodes, seed=seed, task=args.task, frames=args.frames,
                                noise=noise or None, progress=progress, policy="play" if play else None,
                                observation=args.observation, frame_size=args.frame_size, render_style=args.render,
                                **({} if args.steps is None else {"steps": args.steps}))
    except (FileExistsError, NotADirectoryError, ValueError, RuntimeError) as exc:
        write_result(args.result_file, {"ok": False, "error": str(exc)})
        if args.json:
            print(json.dumps({"ok": False, "error": str(exc)}))
        print(f"error: {exc}", file=sys.stderr)
        return 2
    out = {
        "ok": True,
        "out": str(result.out_dir),
        "task": args.task,
        "seeds": [seed, seed + args.episodes - 1],
        "policy": args.policy,
        "noise": noise,
        "frames": bool(args.frames) or args.observation == "camera",
        "observation": args.observation,
        **({"frame_size": args.frame_size, "render": args.render} if args.frames or args.observation == "camera" else {}),
        "mean_return": round(result.mean_return, 3),
        "episodes": [{"episode_id": e.episode_id, "path": str(e.path), "seed": e.seed, "return": e.ret,
                      "steps": e.steps} for e in result.episodes],
        "elapsed_s": round(time.perf_counter() - started, 2),
    }
    write_result(args.result_file, out)
    if args.json:
        print(json.dumps(out))
    else:
        kind = f"{args.task} play" if play else args.task
        print(f"recorded {len(result.episodes)} {kind} episodes (seeds {seed}-{seed + args.episodes - 1}, "
              f"noise {noise:g}{', frames' if args.frames else ''}"
              f"{', camera observation' if args.observation == 'camera' else ''}) into {result.out_dir}; "
              f"mean return {result.mean_return:.1f}")
    return 0
