"""Training-step benchmark: the trainer's overhead, and the peak RSS of each component.

1. Speed. fast_loop and mid_loop steps/s through the trainer (hope_models.train.loop.train with
   its memory guard, thermal governor, metrics.jsonl/.mcap and checkpoints all on) against a bare
   PyTorch loop of the same model, batch, windows and optimizer update (same seed, sampler, window
   loader, AdamW groups, learning-rate schedule, grad clipping and after_step hook), in the same
   process, alternating trainer and bare rounds to spread the noise of a shared machine over both.
   Steps/s are timed from step --warm to the last step of each round (setup and the end-of-job
   validation excluded; checkpoints and metrics inside the window included). Both paths end on the
   same loss, bit for bit, which shows they did the same work. Target: trainer/bare >= 0.95.
2. Memory. Each component (vqvae, fast_loop, mid_loop; optionally on 64x64 frames) trained at
   default sizes in its own fresh process through loop.train; its peak RSS against the job budget
   (3 GiB) and against the pre-flight estimate.

    .venv/bin/python bench/train_step.py            # --steps 300 --rounds 5 --threads 1

It prints figures; it is not a test.
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
sys.path.insert(0, str(REPO))

BUDGET_MB = 3072.0


# -- the memory child: one component, default sizes, its own process --------------------------------

def child_rss(args) -> None:
    from hope_models.checkpoints import resolve_checkpoint_dir
    from hope_models.components.build import build_component
    from hope_models.data.cache import load_or_build
    from hope_models.train.estimate import cache_resident_mb, estimate_memory
    from hope_models.train.loop import TrainConfig, train

    cfg = TrainConfig(component=args.child, data=args.data, run_dir=args.run_dir, steps=args.steps, seed=0,
                      threads=args.threads, cache_dir=args.cache_dir, vqvae_dir=args.vqvae_dir,
                      thermal_zone=args.zone, vcgencmd=None, memory_budget_mb=BUDGET_MB)
    t0 = time.perf_counter()
    result = train(cfg)
    wall = time.perf_counter() - t0
    # The estimate the trainer checked before its first step, recomputed after the peak was taken.
    cache, _ = load_or_build(args.data, args.cache_dir)
    vq = resolve_checkpoint_dir(args.vqvae_dir) if args.vqvae_dir else None
    comp = build_component(args.child, cache.spec, vqvae_dir=vq)
    w = comp.window
    est = estimate_memory(args.child, comp.model, cfg.batch_size, w.k, cache.spec.obs_dim, cache.spec.act_dim,
                          comp.wants_frames, horizons=len(w.horizons_s), cache_mb=cache_resident_mb(cache))
    print(json.dumps({"component": args.child, "outcome": result.outcome, "steps": result.steps,
                      "peak_rss_mb": result.peak_rss_mb, "estimate": est.to_json_obj(),
                      "frames": bool(comp.wants_frames), "wall_s": wall,
                      "params": sum(p.numel() for p in comp.model.parameters()),
                      "checkpoint": result.checkpoint, "first_loss": result.first_loss,
                      "final_loss": result.final_loss}))


def run_child(component: str, data: Path, run_dir: Path, cache_dir: Path, steps: int, threads: int,
              zone: Path, vqvae_dir: Path | None) -> dict:
    cmd = [sys.executable, __file__, "--child", component, "--data", str(data), "--run-dir", str(run_dir),
           "--cache-dir", str(cache_dir), "--steps", str(steps), "--threads", str(threads), "--zone", str(zone)]
    if vqvae_dir is not None:
        cmd += ["--vqvae-dir", str(vqvae_dir)]
    proc = subprocess.run(cmd, capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"{component} child failed:\n{proc.stderr[-4000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


# -- speed: the trainer against a bare loop ---------------------------------------------------------

def trainer_round(component, data, run_dir, cache_dir, vqvae_dir, steps, warm, threads, zone,
                  checkpoint_every) -> tuple[float, float, float]:
    """steps/s from step `warm` to the last step through loop.train, the last loss, and the share
    of the timed window spent writing checkpoints (as the trainer's checkpoint events report it)."""
    from hope_models.train.loop import TrainConfig, train

    marks: dict[int, float] = {}
    ckpt_s: dict[int, float] = {}

    def emit(kind, payload):
        if kind == "progress":
            marks[payload["step"]] = time.perf_counter()
        elif kind == "checkpoint":
            ckpt_s[payload["step"]] = payload["seconds"]

    cfg = TrainConfig(component=component, data=str(data), run_dir=str(run_dir), steps=steps, seed=0,
                      threads=threads, cache_dir=str(cache_dir), vqvae_dir=str(vqvae_dir), thermal_zone=str(zone),
                      vcgencmd=None, memory_budget_mb=BUDGET_MB, checkpoint_every_steps=checkpoint_every,
                      log_every=10, val_batches=1)
    result = train(cfg, emit=emit)
    if result.outcome != "completed":
        raise SystemExit(f"trainer round of {component} ended {result.outcome}: {result.message}")
    assert warm in marks and steps in marks, f"progress events at steps {sorted(marks)[:5]}..."
    window = marks[steps] - marks[warm]
    in_window = sum(v for k, v in ckpt_s.items() if warm < k <= steps)
    return (steps - warm) / window, result.final_loss, in_window / window


def bare_round(component, cache, vqvae_dir, steps, warm, threads) -> tuple[float, float]:
    """The same training math as loop.train with nothing around it: no guards, metrics or checkpoints."""
    import random

    import numpy as np
    import torch

    from hope_models.components.build import build_component
    from hope_models.data.sampler import AnchorSampler
    from hope_models.data.windows import WindowLoader
    from hope_models.train.loop import TrainConfig, lr_at

    cfg = TrainConfig(component=component, data="", run_dir="", steps=steps, seed=0)  # the trainer's defaults
    torch.set_num_threads(threads)
    torch.use_deterministic_algorithms(True)
    torch.manual_seed(cfg.seed)
    np.random.seed(cfg.seed)
    random.seed(cfg.seed)
    comp = build_component(component, cache.spec, vqvae_dir=vqvae_dir, data_fingerprint=cache.fingerprint)
    model, win = comp.model, comp.window
    sampler = AnchorSampler(cache, cfg.batch_size, seed=cfg.seed, imagined_ratio=cfg.imagined_ratio, split="train",
                            val_fraction=cfg.val_fraction, min_history_s=float(getattr(comp, "min_history_s", 0.0)),
                            horizon_s=float(getattr(comp, "horizon_s", max(win.horizons_s, default=0.0))))
    # as the trainer does: a loop over a frame tokenizer reads its codes from the cache's code table
    loader = WindowLoader(cache, sampler, win, chunk=8, frames=bool(comp.wants_frames), codes=comp.code_table(cache))
    decay = [p for p in model.parameters() if p.requires_grad and p.dim() >= 2]
    no_decay = [p for p in model.parameters() if p.requires_grad and p.dim() < 2]
    params = decay + no_decay
    groups = [{"params": decay, "weight_decay": cfg.weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
    opt = torch.optim.AdamW([g for g in groups if g["params"]], lr=cfg.lr, betas=(0.9, 0.95), eps=1e-8)
    model.train()
    t_warm = None
    loss_v = float("nan")
    for step in range(1, steps + 1):
        batch = next(loader)
        for g in opt.param_groups:
            g["lr"] = lr_at(step, cfg)
        loss, _ = comp.loss(batch)
        loss_v = float(loss.detach())
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, cfg.grad_clip)
        opt.step()
        comp.after_step(step)
        if step == warm:
            t_warm = time.perf_counter()
    return (steps - warm) / (time.perf_counter() - t_warm), loss_v


# -- main -------------------------------------------------------------------------------------------

def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=300, help="optimizer steps per speed round (default 300)")
    ap.add_argument("--rounds", type=int, default=5, help="trainer/bare round pairs per component (default 5)")
    ap.add_argument("--warm", type=int, default=20, help="steps before the timing starts (default 20)")
    ap.add_argument("--threads", type=int, default=1, help="torch threads, both paths (default 1)")
    ap.add_argument("--checkpoint-every", type=int, default=100, help="trainer checkpoint interval (default 100)")
    ap.add_argument("--dataset-steps", type=int, default=30000, help="steps of the generated dataset")
    ap.add_argument("--rss-steps", type=int, default=100, help="steps of each memory run (default 100)")
    ap.add_argument("--no-frames", action="store_true", help="skip the 64x64-frame memory rows")
    ap.add_argument("--out", help="work dir (default: a temp dir)")
    ap.add_argument("--keep", action="store_true", help="keep the work dir")
    # child mode (internal)
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--data", help=argparse.SUPPRESS)
    ap.add_argument("--run-dir", help=argparse.SUPPRESS)
    ap.add_argument("--cache-dir", help=argparse.SUPPRESS)
    ap.add_argument("--vqvae-dir", help=argparse.SUPPRESS)
    ap.add_argument("--zone", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child_rss(args)
        return
    if args.warm % 10 or not 0 < args.warm < args.steps or args.steps % 10:
        raise SystemExit("--warm and --steps must be multiples of 10 (the trainer logs every 10 steps), warm < steps")

    work = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="hope-train-bench-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        run(args, work)
    finally:
        if not args.keep and not args.out:
            shutil.rmtree(work, ignore_errors=True)


def run(args, work: Path) -> None:
    from hope_models.data import synthetic as gen
    from hope_models.data.cache import load_or_build

    t0 = time.perf_counter()
    data = work / "data"
    cache_dir = work / "cache"
    if not data.exists():
        gen.generate_dataset(data, args.dataset_steps, obs_dim=20, act_dim=6, seed=0)
    # A thermal zone that reads 45 C: the governor does its real reads (no sysfs zone on this machine).
    zone = work / "thermal_zone_temp"
    zone.write_text("45000\n")
    cache, _ = load_or_build(data, cache_dir)
    print(f"dataset: {cache.n_steps} steps, {cache.n_episodes} episodes, obs {cache.spec.obs_dim}, "
          f"act {cache.spec.act_dim} ({time.perf_counter() - t0:.1f} s)")

    # -- memory, one fresh process per component ---------------------------------------------------
    rows = []
    runs = work / "runs"
    vq = run_child("vqvae", data, runs / "vqvae", cache_dir, args.rss_steps, args.threads, zone, None)
    vq_dir = Path(vq["checkpoint"])
    rows.append(vq)
    for comp in ("fast_loop", "mid_loop"):
        rows.append(run_child(comp, data, runs / comp, cache_dir, args.rss_steps, args.threads, zone, vq_dir))
    if not args.no_frames:
        fdata = work / "data_frames"
        if not fdata.exists():
            gen.generate_dataset(fdata, 3000, obs_dim=20, act_dim=6, seed=1, frame_blobs=True)
        fvq = run_child("vqvae", fdata, runs / "vqvae_frames", cache_dir, args.rss_steps, args.threads, zone, None)
        rows.append(fvq)
        for comp in ("fast_loop", "mid_loop"):
            rows.append(run_child(comp, fdata, runs / f"{comp}_frames", cache_dir, args.rss_steps, args.threads,
                                  zone, Path(fvq["checkpoint"])))

    print(f"\nPeak RSS per component (batch 64, default model sizes, {args.rss_steps} steps, "
          f"own process each; budget {BUDGET_MB:.0f} MB)")
    print(f"{'component':<20}{'input':>8}{'params':>10}{'peak RSS MB':>13}{'estimate MB':>13}"
          f"{'est/peak':>10}{'of budget':>11}{'job s':>8}")
    for r in rows:
        est = r["estimate"]["total_mb"]
        print(f"{r['component']:<20}{'frames' if r['frames'] else 'vector':>8}{r['params']:>10,}"
              f"{r['peak_rss_mb']:>13.0f}{est:>13.0f}{est / r['peak_rss_mb']:>10.2f}"
              f"{r['peak_rss_mb'] / BUDGET_MB:>11.1%}{r['wall_s']:>8.1f}")

    # -- speed, alternating trainer and bare rounds --------------------------------------------------
    import torch

    torch.set_num_threads(args.threads)
    from hope_models.checkpoints import resolve_checkpoint_dir
    vq_ckpt = resolve_checkpoint_dir(vq_dir)
    print(f"\nSteps/s, trainer (guards + metrics + checkpoints every {args.checkpoint_every} steps) vs bare "
          f"PyTorch loop; {args.rounds} rounds x {args.steps} steps, timed from step {args.warm}, "
          f"threads {args.threads}")
    summary = {}
    for comp in ("fast_loop", "mid_loop"):
        trainer_sps, bare_sps, same, ckpt_share = [], [], [], []
        for r in range(args.rounds):
            order = ("trainer", "bare") if r % 2 == 0 else ("bare", "trainer")
            for mode in order:
                if mode == "trainer":
                    run_dir = work / "speed" / f"{comp}_{r}"
                    shutil.rmtree(run_dir, ignore_errors=True)
                    sps, t_loss, share = trainer_round(comp, data, run_dir, cache_dir, vq_ckpt, args.steps,
                                                       args.warm, args.threads, zone, args.checkpoint_every)
                    trainer_sps.append(sps)
                    ckpt_share.append(share)
                else:
                    sps, b_loss = bare_round(comp, cache, vq_ckpt, args.steps, args.warm, args.threads)
                    bare_sps.append(sps)
            same.append(t_loss == b_loss)
        t_med, b_med = statistics.median(trainer_sps), statistics.median(bare_sps)
        # Each round's two runs are back to back, so they share the machine's load of the moment: the
        # median of the per-round ratios is steadier than the ratio of the medians.
        ratios = [t / b for t, b in zip(trainer_sps, bare_sps, strict=True)]
        summary[comp] = statistics.median(ratios)
        print(f"  {comp:<10} trainer {', '.join(f'{s:.1f}' for s in trainer_sps)}  (median {t_med:.1f})")
        print(f"  {'':<10} bare    {', '.join(f'{s:.1f}' for s in bare_sps)}  (median {b_med:.1f})")
        print(f"  {'':<10} per-round ratio {', '.join(f'{r:.3f}' for r in ratios)}  (median {summary[comp]:.3f}; "
              f"ratio of medians {t_med / b_med:.3f})")
        print(f"  {'':<10} checkpoint writing: {statistics.median(ckpt_share):.1%} of the trainer's timed window "
              f"(median); same final loss in every round: {all(same)}")

    print("\ntarget                                   result")
    for comp, ratio in summary.items():
        print(f"  {comp:<9} trainer/bare >= 0.95   {ratio:.3f}  {'PASS' if ratio >= 0.95 else 'FAIL'}")
    worst = max(rows, key=lambda r: r["peak_rss_mb"])
    print(f"  peak RSS under the {BUDGET_MB:.0f} MB budget     {worst['peak_rss_mb']:.0f} MB ({worst['component']}, "
          f"{'frames' if worst['frames'] else 'vector'})  {'PASS' if worst['peak_rss_mb'] < BUDGET_MB else 'FAIL'}")
    print(f"\nwork dir: {work}  total {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    main()
