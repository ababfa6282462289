#!/usr/bin/env python3
"""The demo's Mid Loop (state observation) step by step: steps/s and the end-of-job validation,
optionally against another checkout of the code in alternating rounds.

The recipe is `make demo`'s: batch 64, seed 0, lr 1e-3 with the loop's schedule over --total steps,
the VQ-VAE the chain trained, one thread unless --threads. A round builds the component as the
trainer does (same seed, sampler, window loader, AdamW groups, clipping), runs --warm steps, times
--steps steps, then times `validation_metrics` (the 8 batches the run reports and the gate reads)
and prints one JSON line: steps/s, the last loss (equal between two checkouts that compute the
same thing), the validation seconds and the held-out observation errors.

    python bench/mid_loop_demo.py --data D --vqvae VQ_RUN [--cache-dir C] [--steps 150] [--threads 1]
    python bench/mid_loop_demo.py ... --against /path/to/other/checkout --rounds 3
    python bench/mid_loop_demo.py ... --against-threads 2 --rounds 3

With --against, each round runs once in a child with that checkout first on PYTHONPATH and once
with this one, back to back (which goes first alternates), and the summary is the median of the
per-round ratios (this / that): the machine is shared, so only ratios measured side by side mean
anything. --against-threads N does the same with this checkout at N threads as "that". It prints
figures; it is not a test.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def one_round(a) -> dict:
    import numpy as np
    import torch

    from hope_models.checkpoints import resolve_checkpoint_dir
    from hope_models.components.build import build_component
    from hope_models.data.cache import load_or_build
    from hope_models.data.windows import WindowLoader
    from hope_models.train import job_setup, validation
    from hope_models.train.config import TrainConfig
    from hope_models.train.schedule import lr_at
    from hope_models.train.validation import ValidationSetup, anchor_sampler, validation_metrics

    job_setup.torch_settings(torch, a.threads)
    cache, _ = load_or_build(a.data, a.cache_dir)
    torch.manual_seed(0)
    np.random.seed(0)
    comp = build_component("mid_loop", cache.spec, vqvae_dir=resolve_checkpoint_dir(a.vqvae),
                           data_fingerprint=cache.fingerprint)
    cfg = TrainConfig(component="mid_loop", data=a.data, run_dir="unused", steps=a.total)
    model = comp.model
    t0 = time.perf_counter()
    sampler = anchor_sampler(cache, comp, "train", batch_size=64, seed=0, imagined_ratio=0.0, val_fraction=0.1)
    loader = WindowLoader(cache, sampler, comp.window, chunk=job_setup.LOADER_CHUNK, frames=bool(comp.wants_frames),
                          codes=validation.code_table(comp, cache))
    setup_s = time.perf_counter() - t0
    decay = [p for p in model.parameters() if p.requires_grad and p.dim() >= 2]
    flat = [p for p in model.parameters() if p.requires_grad and p.dim() < 2]
    opt = torch.optim.AdamW([{"params": decay, "weight_decay": 0.01}, {"params": flat, "weight_decay": 0.0}],
                            lr=1e-3, betas=(0.9, 0.95), eps=1e-8)
    model.train()
    loss_v = float("nan")

    def step(s: int) -> float:
        for g in opt.param_groups:
            g["lr"] = lr_at(s, cfg)
        loss, _ = comp.loss(next(loader))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(decay + flat, 1.0)
        opt.step()
        comp.after_step(s)
        return float(loss.detach())

    for s in range(1, a.warm + 1):
        step(s)
    t0 = time.perf_counter()
    for s in range(a.warm + 1, a.warm + a.steps + 1):
        loss_v = step(s)
    train_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    val = validation_metrics(comp, cache, ValidationSetup(batch_size=64))
    val_s = time.perf_counter() - t0
    return {"code": str(Path(str(sys.modules["hope_models"].__file__)).parents[1]), "steps_per_s": a.steps / train_s,
            "ms_per_step": 1000 * train_s / a.steps, "last_loss": loss_v, "setup_s": setup_s, "val_s": val_s,
            "held_out": {k: round(v, 4) for k, v in val.items() if k.startswith(("obs_mse_", "copy_last_obs_mse_"))}}


def compare(a) -> None:
    here = (str(REPO), a.threads)
    there = (str(Path(a.against).resolve()), a.threads) if a.against else (str(REPO), a.against_threads)
    argv = [sys.executable, str(Path(__file__).resolve()), "--data", a.data, "--vqvae", a.vqvae, "--steps",
            str(a.steps), "--warm", str(a.warm), "--total", str(a.total)]
    if a.cache_dir:
        argv += ["--cache-dir", a.cache_dir]
    rows: list[dict] = []
    for r in range(a.rounds):
        out = {}
        for tree, threads in ([there, here] if r % 2 == 0 else [here, there]):
            env = {**os.environ, "PYTHONPATH": tree}
            line = subprocess.run([*argv, "--threads", str(threads)], env=env, check=True, capture_output=True,
                                  text=True).stdout.strip().splitlines()[-1]
            out[(tree, threads)] = json.loads(line)
        row = {"round": r + 1, "that_steps_per_s": out[there]["steps_per_s"], "this_steps_per_s": out[here]["steps_per_s"],
               "ratio": out[here]["steps_per_s"] / out[there]["steps_per_s"],
               "val_s": [out[there]["val_s"], out[here]["val_s"]],
               "same_loss": out[here]["last_loss"] == out[there]["last_loss"]}
        rows.append(row)
        print(json.dumps(row), flush=True)
    print(json.dumps({"median_ratio": statistics.median(r["ratio"] for r in rows),
                      "that_median": statistics.median(r["that_steps_per_s"] for r in rows),
                      "this_median": statistics.median(r["this_steps_per_s"] for r in rows)}))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--data", required=True, help="the demo's recorded episodes (run_trainer.py sim-demos)")
    p.add_argument("--vqvae", required=True, help="the VQ-VAE run dir or checkpoint the Mid Loop reads")
    p.add_argument("--cache-dir", default=None)
    p.add_argument("--steps", type=int, default=150, help="timed steps")
    p.add_argument("--warm", type=int, default=10, help="steps before timing starts")
    p.add_argument("--total", type=int, default=4000, help="the schedule's length (the demo's --steps)")
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--against", default=None, help="another checkout to compare with, round by round")
    p.add_argument("--against-threads", type=int, default=None, help="or this checkout at N threads")
    p.add_argument("--rounds", type=int, default=3)
    a = p.parse_args()
    if a.against or a.against_threads:
        compare(a)
    else:
        print(json.dumps(one_round(a)), flush=True)


if __name__ == "__main__":
    main()
