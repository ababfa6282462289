"""A 2-thread training job beside other busy processes, with OpenMP's idle threads spinning (libgomp's
default, OMP_WAIT_POLICY=ACTIVE) or sleeping (PASSIVE, what hope_models/omp_wait.py sets): steps/s of
the real `train` command, rounds alternating in one run so the machine's noise falls on both.

    .venv/bin/python bench/omp_wait.py --data D/cam50 [--load 1] [--steps 120 --rounds 2]

--load N starts N busy processes (a Python loop each, what a robot's own work looks like to the
scheduler) for the whole run; --load 0 measures the cores as they are. The job is the camera demo's
grid VQ-VAE (`--threads 2`). Steps/s are read from each run's metrics.jsonl past step --warm. It
prints figures (JSON); it is not a test.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from bench.fast_loop_codes import steps_per_s  # noqa: E402

GRID_VQVAE = {"layout": "grid", "patch": 4, "n_codes": 256, "channels": 16, "decoder_channels": 32, "fg_weight": 10}


def train(data: Path, cache: Path, run: Path, steps: int, policy: str) -> None:
    cmd = [sys.executable, "run_trainer.py", "train", "--component", "vqvae", "--data", str(data), "--cache-dir",
           str(cache), "--run-dir", str(run), "--steps", str(steps), "--lr", "2e-3", "--threads", "2",
           "--log-every", "10", "--checkpoint-every", str(steps), "--model-config", json.dumps(GRID_VQVAE)]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True,
                          env={**os.environ, "OMP_WAIT_POLICY": policy})
    if proc.returncode != 0:
        raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-2000:]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--data", type=Path, required=True, help="a camera dataset (sim-demos --observation camera)")
    ap.add_argument("--load", type=int, default=1, help="busy processes beside the job (default 1)")
    ap.add_argument("--steps", type=int, default=120)
    ap.add_argument("--warm", type=int, default=20)
    ap.add_argument("--rounds", type=int, default=2)
    args = ap.parse_args()
    busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(args.load)]
    try:
        with tempfile.TemporaryDirectory(prefix="ompwait-") as tmp:
            root = Path(tmp)
            train(args.data, root / "cache", root / "prime", 5, "PASSIVE")  # the cache, untimed
            rates: dict[str, list[float]] = {"ACTIVE": [], "PASSIVE": []}
            for r in range(args.rounds):
                for policy in rates:
                    run = root / f"{policy}-{r}"
                    train(args.data, root / "cache", run, args.steps, policy)
                    rates[policy].append(round(steps_per_s(run, args.warm), 3))
    finally:
        for p in busy:
            p.kill()
    med = {k: statistics.median(v) for k, v in rates.items()}
    print(json.dumps({"steps_per_s": rates, "median": med, "passive_over_active": med["PASSIVE"] / med["ACTIVE"],
                      "load": args.load, "steps": args.steps}, indent=1))


if __name__ == "__main__":
    main()
