#!/usr/bin/env python3
"""What drawing anchors by block does to training: a fast_loop's validation loss after N steps with
every anchor on its own (the default) and with 4 anchors a block (AnchorSampler anchors_per_block).

Prints figures; it is not a test. One run generates a synthetic dataset (--dataset-steps steps,
20-dim observations, 6-dim actions, 10/20/50 Hz), trains the VQ-VAE the fast_loop reads codes from
once, then for each seed a fast_loop through loop.train with each grouping of its training anchors
(the sampler factory of the loop wrapped in the child; validation keeps independent anchors, on
--val-batches batches), each in a fresh process. Same seed, same data, same validation batches.

    python bench/anchor_blocks.py [--steps 1500] [--seeds 0,1,2] [--dataset-steps 30000] [--out DIR]
"""
from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))


def child(component: str, data: str, run_dir: str, cache_dir: str, steps: int, seed: int, k: int,
          val_batches: int, vqvae_dir: str | None) -> dict:
    import hope_models.train.loop as loop
    from hope_models.data.sampler import AnchorSampler
    from hope_models.train.loop import TrainConfig, train

    factory = loop.anchor_sampler

    def grouped(cache, comp, split, **kw):
        if split != "train" or k == 1:
            return factory(cache, comp, split, **kw)
        win = comp.window
        return AnchorSampler(cache, kw["batch_size"], seed=kw["seed"], imagined_ratio=kw["imagined_ratio"],
                             split=split, val_fraction=kw["val_fraction"],
                             min_history_s=float(getattr(comp, "min_history_s", 0.0)),
                             horizon_s=float(getattr(comp, "horizon_s", max(win.horizons_s, default=0.0))),
                             exclude_play=bool(getattr(comp, "clones_actions", False)), anchors_per_block=k)

    loop.anchor_sampler = grouped  # type: ignore[assignment]  # the trainer's sampler factory, this child only
    cfg = TrainConfig(component=component, data=data, run_dir=run_dir, steps=steps, seed=seed,
                      cache_dir=cache_dir, val_batches=val_batches, vqvae_dir=vqvae_dir)
    r = train(cfg)
    if r.outcome != "completed":
        raise SystemExit(f"{component} (seed {seed}, {k} a block) ended {r.outcome}: {r.message}")
    return {"val": r.summary.get("val", {}), "final_loss": r.final_loss, "elapsed_s": r.elapsed_s}


def _run(*args: str) -> dict:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    proc = subprocess.run([sys.executable, __file__, "_child", *args], capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        raise SystemExit(f"child {args[0]} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--steps", type=int, default=1500, help="fast_loop optimizer steps per run")
    p.add_argument("--seeds", default="0,1,2")
    p.add_argument("--dataset-steps", type=int, default=30_000)
    p.add_argument("--val-batches", type=int, default=32)
    p.add_argument("--out", help="work dir (default: a temp dir, removed at the end)")
    a = p.parse_args(argv)
    from hope_models.data.synthetic import generate_dataset

    work = Path(a.out) if a.out else Path(tempfile.mkdtemp(prefix="hope-bench-blocks-"))
    try:
        data, cache, vq = work / "dataset", work / "cache", work / "vqvae"
        if not data.exists():
            generate_dataset(data, a.dataset_steps, obs_dim=20, act_dim=6, rates_hz=(10, 20, 50), seed=0)
        shutil.rmtree(vq, ignore_errors=True)
        _run("vqvae", str(data), str(vq), str(cache), "600", "0", "1", str(a.val_batches), "")
        print(f"{'seed':>4s} {'val mse, alone':>15s} {'val mse, 4 a block':>19s} {'ratio':>6s}")
        for seed in [int(s) for s in a.seeds.split(",")]:
            mse = []
            for k in (1, 4):
                run = work / f"fast_loop_s{seed}_k{k}"
                shutil.rmtree(run, ignore_errors=True)
                out = _run("fast_loop", str(data), str(run), str(cache), str(a.steps), str(seed), str(k),
                           str(a.val_batches), str(vq))
                mse.append(out["val"]["mse"])
            print(f"{seed:>4d} {mse[0]:>15.4f} {mse[1]:>19.4f} {mse[1] / mse[0]:>6.3f}", flush=True)
    finally:
        if not a.out:
            shutil.rmtree(work, ignore_errors=True)
    return 0


if __name__ == "__main__":
    if len(sys.argv) > 1 and sys.argv[1] == "_child":
        comp, data, run_dir, cache_dir, steps, seed, k, val_batches, vq = sys.argv[2:11]
        print(json.dumps(child(comp, data, run_dir, cache_dir, int(steps), int(seed), int(k), int(val_batches),
                               vq or None)))
        sys.exit(0)
    sys.exit(main())
