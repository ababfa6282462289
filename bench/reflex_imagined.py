"""What imagined rollouts are worth: a fast_loop trained on a few expert demos, with and without them.

    .venv/bin/python bench/reflex_imagined.py     # --demos 5 --imagined 50 --method dart --steps 2000 --seeds 0,1,2

1. Record `--demos` clean expert demonstrations (`sim-demos --noise 0`: task seeds 100000.., the
   recorder's default; clean, so the rollouts' noise is the only DART in the comparison).
2. Imagine `--imagined` rollouts into a copy of the demo dir (`imagine`: task seeds 200000.., `--method`
   dart or cem; `--demos` makes imagine refuse any demo start state).
3. For each training seed, train two fast_loops with the same seed, steps and hyperparameters
   (`train --component fast_loop`): A on the demos alone, B on the demos + the imagined rollouts mixed
   by `--imagined-ratio` (the sampler's share of imagined anchors in every batch).
4. Evaluate every run with `eval-reflex` on the same held-out seeds (0..19 by default), which also
   scores the expert and a uniform-random policy on those seeds.

Every step is the command a user would run (listed in the output), in a scratch dir (`--work`, default
a temp dir that is removed). Prints a table (with --json one JSON object). It is not a test.
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def sh(cmd: list[str], log: list[str], quiet: bool) -> dict:
    """Run `run_trainer.py <cmd> --json`; its JSON result (the last stdout line)."""
    shown = "python run_trainer.py " + " ".join(cmd)
    log.append(shown)
    if not quiet:
        print(f"$ {shown}", file=sys.stderr, flush=True)
    t0 = time.perf_counter()
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "disabled")}
    proc = subprocess.run([sys.executable, str(REPO / "run_trainer.py"), *cmd, "--json"], capture_output=True,
                          text=True, cwd=REPO, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"failed (exit {proc.returncode}): {shown}\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}")
    out = json.loads(proc.stdout.strip().splitlines()[-1])
    out["_wall_s"] = round(time.perf_counter() - t0, 1)
    return out


def _seeds(text: str) -> list[int]:
    try:
        seeds = [int(s) for s in text.split(",") if s.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a comma-separated list of integers") from None
    if not seeds or any(s < 0 for s in seeds):
        raise argparse.ArgumentTypeError(f"{text!r}: give one or more non-negative seeds")
    return seeds


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", choices=("reach", "track"), default="reach")
    ap.add_argument("--demos", type=int, default=5, help="expert demonstrations (default 5)")
    ap.add_argument("--imagined", type=int, default=50, help="imagined rollouts (default 50)")
    ap.add_argument("--method", choices=("dart", "cem"), default="dart")
    ap.add_argument("--noise", type=float, default=None, help="dart noise std (default: imagine's default)")
    ap.add_argument("--imagined-ratio", type=float, default=0.5, help="share of imagined anchors per batch (0.5)")
    ap.add_argument("--steps", type=int, default=2000, help="training steps of each fast_loop (default 2000)")
    ap.add_argument("--seeds", type=_seeds, default=[0, 1, 2],
                    help="training seeds; each trains both runs (default 0,1,2)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads per training run (default 1)")
    ap.add_argument("--eval-episodes", type=int, default=20)
    ap.add_argument("--eval-seed", type=int, default=0, help="first held-out evaluation seed (default 0)")
    ap.add_argument("--work", default=None, help="scratch dir (default: a temp dir, removed at the end)")
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()

    t_start = time.perf_counter()
    work = Path(args.work) if args.work else Path(tempfile.mkdtemp(prefix="reflex-imagined-"))
    log: list[str] = []
    q = args.json
    try:
        demos, mixed, cache = work / "demos", work / "demos_plus_imagined", work / "cache"
        for d in (demos, mixed, work / "runs"):
            if d.exists():
                shutil.rmtree(d)
        # --noise 0: sim-demos records DART demos by default; the figures measure what imagined rollouts
        # add to demos without noise
        rec = sh(["sim-demos", "--out", str(demos), "--episodes", str(args.demos), "--task", args.task,
                  "--noise", "0"], log, q)
        shutil.copytree(demos, mixed)  # the very same demo episodes, byte for byte
        imag_cmd = ["imagine", "--out", str(mixed), "--episodes", str(args.imagined), "--method", args.method,
                    "--task", args.task, "--demos", str(demos)]
        if args.noise is not None:
            imag_cmd += ["--noise", str(args.noise)]
        imag = sh(imag_cmd, log, q)
        arms = (("demos", demos, []), ("demos+imagined", mixed, ["--imagined-ratio", str(args.imagined_ratio)]))
        per_seed: dict[str, list[dict]] = {name: [] for name, _, _ in arms}
        baseline = None
        for seed in args.seeds:
            for name, data, extra in arms:
                run_dir = work / "runs" / f"{name.replace('+', '_')}_s{seed}"
                tr = sh(["train", "--component", "fast_loop", "--data", str(data), "--run-dir", str(run_dir),
                         "--steps", str(args.steps), "--seed", str(seed), "--threads", str(args.threads),
                         "--cache-dir", str(cache), "--checkpoint-every", str(args.steps), *extra], log, q)
                ev = sh(["eval-reflex", "--checkpoint", str(run_dir), "--episodes", str(args.eval_episodes),
                         "--seed", str(args.eval_seed), "--task", args.task], log, q)
                baseline = baseline or ev
                per_seed[name].append({"seed": seed, "mean_return": ev["mean_return"],
                                       "success_rate": ev["success_rate"], "time_to_reach_s": ev["time_to_reach_s"],
                                       "final_loss": tr.get("final_loss"), "train_s": tr["_wall_s"]})

        def agg(rows: list[dict]) -> dict:
            ttr = [r["time_to_reach_s"] for r in rows if r["time_to_reach_s"] is not None]
            return {"mean_return": round(statistics.fmean(r["mean_return"] for r in rows), 1),
                    "success_rate": round(statistics.fmean(r["success_rate"] for r in rows), 3),
                    "time_to_reach_s": round(statistics.fmean(ttr), 3) if ttr else None,
                    "per_seed": rows}

        result = {
            "task": args.task, "demos": args.demos, "imagined": args.imagined, "method": args.method,
            "imagined_origin": imag.get("origin"), "imagined_settings": imag.get("settings"),
            "imagined_mean_return": imag.get("mean_return"), "imagine_s": imag.get("elapsed_s"),
            "demo_mean_return": rec.get("mean_return"), "imagined_ratio": args.imagined_ratio,
            "train_steps": args.steps, "train_seeds": args.seeds,
            "eval_seeds": [args.eval_seed, args.eval_seed + args.eval_episodes - 1],
            "rows": {
                "expert": {"mean_return": baseline["expert_mean_return"],
                           "success_rate": baseline.get("expert_success_rate")},
                "random": {"mean_return": baseline["random_mean_return"],
                           "success_rate": baseline.get("random_success_rate")},
                **{name: agg(rows) for name, rows in per_seed.items()},
            },
            "commands": log,
            "wall_s": round(time.perf_counter() - t_start, 1),
        }
        if args.json:
            print(json.dumps(result))
        else:
            print(f"\nfast_loop on {args.demos} expert {args.task} demos vs the same + {args.imagined} imagined "
                  f"({imag.get('origin')}, {imag.get('settings')}, imagined ratio {args.imagined_ratio}); "
                  f"{args.steps} steps, training seeds {args.seeds}; eval-reflex on seeds "
                  f"{args.eval_seed}..{args.eval_seed + args.eval_episodes - 1}")
            print(f"{'policy':<18}{'mean return':>12}{'success':>9}{'reach s':>9}   per training seed (return/success)")
            for name, row in result["rows"].items():
                sr, tt = row.get("success_rate"), row.get("time_to_reach_s")
                seeds = "  ".join(f"{r['mean_return']:.0f}/{r['success_rate']:.2f}" for r in row.get("per_seed", []))
                print(f"{name:<18}{row['mean_return']:>12.1f}{'' if sr is None else f'{sr:.2f}':>9}"
                      f"{'' if tt is None else f'{tt:.2f}':>9}   {seeds}")
            print(f"total {result['wall_s']} s (imagining {imag.get('elapsed_s')} s)")
            print("commands:\n  " + "\n  ".join(log))
    finally:
        if not args.work:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
