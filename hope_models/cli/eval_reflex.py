"""`run_trainer.py eval-reflex`: a fast_loop in closed loop in the reacher, against the expert and random.

    run_trainer.py eval-reflex --checkpoint runs/reach [--episodes 20] [--seed 0] [--task reach|track] [--json]
    run_trainer.py eval-reflex --checkpoint promoted ...

The policy is stepped one tick per 20 ms control step with its recurrent state (ReflexPolicy), on
seeds S .. S+N-1; the expert and a uniform-random policy run on the same seeds. With --json one
object is printed:

    {"mean_return", "success_rate", "time_to_reach_s", "expert_mean_return", "random_mean_return",
     "episodes": N, "task", "seeds": [S, S+N-1], "checkpoint", "version", "expert_success_rate",
     "random_success_rate", "reached", "per_episode": [{"seed", "return", "success", "time_to_reach_s",
     "expert_return", "random_return"}], "elapsed_s"}

`--checkpoint promoted` reads the promotion pointer $HOPE_HOME/promoted/fast_loop.json, a JSON object
whose "checkpoint" names the checkpoint dir (absolute, or relative to $HOPE_HOME). Until a fast_loop
has been promoted there is none, and the command says so (exit 2).
Exit 0 after an evaluation, 2 for a usage error (no such checkpoint, not a fast_loop, a spec that
does not read the reacher's observation).
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

PROMOTED = "promoted"
POINTER_DIR = "promoted"
POINTER_FILE = "fast_loop.json"


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if v < 1:
        raise argparse.ArgumentTypeError(f"{v} must be >= 1")
    return v


def _non_negative_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
    if v < 0:
        raise argparse.ArgumentTypeError(f"{v} must be >= 0")
    return v


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from hope_models.sim.reacher import TASKS

    parser.add_argument("--checkpoint", required=True, metavar="PATH|promoted",
                        help="a fast_loop run dir or checkpoints/<step> dir, or 'promoted' for the promoted one")
    parser.add_argument("--episodes", type=_positive_int, default=20, help="episodes (seeds) to evaluate (default 20)")
    parser.add_argument("--seed", type=_non_negative_int, default=0,
                        help="first seed (default 0); seeds S..S+N-1, held out from sim-demos' default 100000+")
    parser.add_argument("--task", choices=TASKS, default="reach", help="reach or track (default reach)")
    parser.add_argument("--threads", type=_positive_int, default=1, help="torch threads (default 1: one tick is tiny)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON on stdout")


def resolve_promoted(home: Path) -> Path:
    """The checkpoint the fast_loop promotion pointer names; FileNotFoundError/ValueError with the reason."""
    pointer = home / POINTER_DIR / POINTER_FILE
    if not pointer.is_file():
        raise FileNotFoundError(f"no promoted fast_loop exists yet ({pointer} not found); promote a checkpoint first "
                                "or pass --checkpoint PATH (a fast_loop run dir or checkpoint dir)")
    try:
        obj = json.loads(pointer.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise ValueError(f"{pointer}: not readable JSON: {exc}") from None
    ckpt = obj.get("checkpoint") if isinstance(obj, dict) else None
    if not isinstance(ckpt, str) or not ckpt:
        raise ValueError(f"{pointer}: must be a JSON object with a 'checkpoint' path")
    path = Path(ckpt)
    return path if path.is_absolute() else home / path


def _fail(args, message: str) -> int:
    if args.json:
        print(json.dumps({"ok": False, "error": message}))
    print(f"error: {message}", file=sys.stderr)
    return 2


def run(args: argparse.Namespace) -> int:
    started = time.perf_counter()
    ckpt_arg = args.checkpoint
    if ckpt_arg == PROMOTED:
        from hope_models.settings import SettingsError, load_settings
        try:
            ckpt_arg = str(resolve_promoted(load_settings().home))
        except (FileNotFoundError, ValueError, SettingsError) as exc:
            return _fail(args, str(exc))

    import torch

    from hope_models.runtime.reflex_policy import ReflexPolicy, ReflexPolicyError
    from hope_models.sim.evaluate import evaluate_policy, expert_factory, json_number, random_factory

    torch.set_num_threads(args.threads)
    try:
        policy = ReflexPolicy.from_checkpoint(ckpt_arg)
    except ReflexPolicyError as exc:
        return _fail(args, str(exc))
    seeds = list(range(args.seed, args.seed + args.episodes))
    res = evaluate_policy(policy, seeds, args.task)
    expert = evaluate_policy(expert_factory, seeds, args.task)
    rand = evaluate_policy(random_factory, seeds, args.task)
    out = {
        "ok": True,
        "mean_return": json_number(res.mean_return),
        "success_rate": json_number(res.success_rate),
        "time_to_reach_s": json_number(res.time_to_reach_s),
        "expert_mean_return": json_number(expert.mean_return),
        "random_mean_return": json_number(rand.mean_return),
        "episodes": len(res.episodes),
        "task": args.task,
        "seeds": [seeds[0], seeds[-1]],
        "checkpoint": str(policy.checkpoint_dir),
        "version": policy.version,
        "reached": res.reached,
        "expert_success_rate": json_number(expert.success_rate),
        "random_success_rate": json_number(rand.success_rate),
        "per_episode": [
            {"seed": p.seed, "return": p.ret, "success": p.success, "time_to_reach_s": p.time_to_reach_s,
             "expert_return": e.ret, "random_return": r.ret}
            for p, e, r in zip(res.episodes, expert.episodes, rand.episodes)],
        "elapsed_s": round(time.perf_counter() - started, 2),
    }
    if args.json:
        print(json.dumps(out))
    else:
        ttr = "n/a" if res.time_to_reach_s is None else f"{res.time_to_reach_s:.2f} s"
        print(f"{policy.version} on {args.task}, seeds {seeds[0]}-{seeds[-1]}: mean return {res.mean_return:.1f} "
              f"(expert {expert.mean_return:.1f}, random {rand.mean_return:.1f}), success {res.success_rate:.0%}, "
              f"time to reach {ttr} ({res.reached}/{len(seeds)} reached)")
    return 0
