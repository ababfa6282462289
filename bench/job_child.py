#!/usr/bin/env python3
"""What a training job's process costs before it trains: wall time, CPU time and peak RSS of
`run_trainer.py train` for a few steps, this checkout against another one, in alternating rounds.

A job runs in a child that exits after it (workers/), so each job pays its process's start: the
imports, the dataset cache, the model (a fast_loop with its frozen VQ-VAE loads that checkpoint).
Two jobs are timed: a vqvae, and a fast_loop reading its codes. With --before DIR (a checkout of
an earlier commit, e.g. `git worktree add DIR <commit>`), DIR's own code runs the same commands on
the same data, interleaved with ours, and the table gives medians and the ratio.

    python bench/job_child.py [--before DIR] [--rounds 5] [--steps 20]

It prints figures; it is not a test.
"""
from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def _job(checkout: Path, argv: list[str]) -> tuple[float, float, float]:
    """(wall s, CPU s, peak RSS MB) of one `run_trainer.py train` from `checkout`."""
    env = {**os.environ, "PYTHONPATH": str(checkout), "OMP_NUM_THREADS": "1"}
    t0 = time.perf_counter()
    proc = subprocess.Popen([sys.executable, str(checkout / "run_trainer.py"), "train", *argv], cwd=checkout,
                            env=env, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    _, status, usage = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - t0
    proc.returncode = os.waitstatus_to_exitcode(status)
    if proc.returncode != 0:
        raise SystemExit(f"{checkout}: train {' '.join(argv)} exited {proc.returncode}: "
                         f"{proc.stderr.read().decode()[-2000:] if proc.stderr else ''}")
    return wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss / 1024


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--before", type=Path, help="another checkout, timed in the same rounds")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--steps", type=int, default=20)
    args = ap.parse_args()
    sys.path.insert(0, str(REPO))
    from hope_models.data.synthetic import generate_dataset

    checkouts = {"this": REPO, **({"before": args.before.resolve()} if args.before else {})}
    with tempfile.TemporaryDirectory(prefix="job-child-") as tmp:
        root = Path(tmp)
        generate_dataset(root / "ds", 3000, obs_dim=20, act_dim=6, seed=3, episode_seconds=(15, 30))
        common = ["--data", str(root / "ds"), "--cache-dir", str(root / "cache"), "--steps", str(args.steps),
                  "--threads", "1", "--thermal-zone", str(root / "none")]
        _job(REPO, ["--component", "vqvae", "--run-dir", str(root / "vq"), *common])  # the VQ-VAE both read, and the cache
        vq = sorted((root / "vq" / "checkpoints").glob("0*"))[-1]
        jobs = {"vqvae": ["--component", "vqvae"], "fast_loop + VQ-VAE": ["--component", "fast_loop", "--vqvae", str(vq)]}
        got: dict[tuple[str, str], list[tuple[float, float, float]]] = {}
        for r in range(args.rounds):
            for job, argv in jobs.items():
                for name, checkout in (checkouts.items() if r % 2 == 0 else reversed(checkouts.items())):
                    run_dir = root / f"run-{name}-{job[:4]}-{r}"
                    got.setdefault((job, name), []).append(_job(checkout, [*argv, "--run-dir", str(run_dir), *common]))
    print(f"{args.steps}-step jobs, {args.rounds} rounds, medians (load {os.getloadavg()[0]:.1f}):")
    print(f"{'job':22s} {'checkout':8s} {'wall s':>7s} {'CPU s':>7s} {'peak RSS MB':>12s}")
    for job in jobs:
        med = {}
        for name in checkouts:
            rows = got[(job, name)]
            med[name] = [statistics.median(x[i] for x in rows) for i in range(3)]
            print(f"{job:22s} {name:8s} {med[name][0]:7.2f} {med[name][1]:7.2f} {med[name][2]:12.0f}")
        if "before" in med:
            b, t = med["before"], med["this"]
            print(f"{job:22s} {'ratio':8s} {b[0] / t[0]:6.2f}x {b[1] / t[1]:6.2f}x {t[2] - b[2]:+11.0f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
