"""Tiny real checkpoints for the promotion tests (test_gate.py, test_promotion.py).

One set of sim reacher demos (12 DART episodes of 200 steps) and fast_loops trained on it for a
few steps (seconds each, one thread): "good" (150 steps) and "weak" (3 steps) differ clearly in
validation loss and reflex return; "synthetic" is a fast_loop on a synthetic dataset whose fields
do not fit the reacher data. Helpers poison a checkpoint with NaN (manifest rewritten so it still
verifies) and put runs into the registry as completed.
"""
from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

from hope_models.train.loop import TrainConfig, train

GOOD_STEPS = 150
WEAK_STEPS = 3


def train_fast_loop(root: Path, name: str, steps: int, data: Path) -> Path:
    """Train a fast_loop into root/runs/<name>; returns its final checkpoint dir."""
    result = train(TrainConfig(component="fast_loop", data=str(data), run_dir=str(root / "runs" / name), steps=steps,
                               batch_size=32, threads=1, cache_dir=str(root / "cache"), thermal_zone=None,
                               vcgencmd=None, log_every=50, checkpoint_every_steps=10_000))
    assert result.outcome == "completed", result.message
    return Path(result.checkpoint)


def build_models(root: Path) -> dict[str, Path]:
    from hope_models.data.synthetic import generate_dataset
    from hope_models.sim.recorder import record_dataset

    record_dataset(root / "demos", 12, task="reach", noise=1.0, steps=200)
    generate_dataset(root / "synth", 3000, obs_dim=5, act_dim=2, rates_hz=(50,), episode_seconds=(8.0, 12.0))
    return {
        "demos": root / "demos",
        "good": train_fast_loop(root, "good", GOOD_STEPS, root / "demos"),
        "weak": train_fast_loop(root, "weak", WEAK_STEPS, root / "demos"),
        "synthetic": train_fast_loop(root, "synthetic", 20, root / "synth"),
    }


def copy_run(ckpt: Path, root: Path, name: str) -> Path:
    """A copy of checkpoint dir `ckpt` as the only checkpoint of a new run root/runs/<name>."""
    dest = root / "runs" / name / "checkpoints" / ckpt.name
    dest.parent.mkdir(parents=True)
    shutil.copytree(ckpt, dest)
    return dest


def _rewrite_manifest(ckpt: Path, fname: str) -> None:
    manifest = json.loads((ckpt / "manifest.json").read_text())
    data = (ckpt / fname).read_bytes()
    manifest["files"][fname] = {"sha256": hashlib.sha256(data).hexdigest(), "size": len(data)}
    (ckpt / "manifest.json").write_text(json.dumps(manifest))


def write_config(ckpt: Path, config: dict | str) -> None:
    """Replace the checkpoint's config.json (an object, or raw text), manifest re-hashed so the
    edit reaches the code under test instead of stopping at the manifest check."""
    (ckpt / "config.json").write_text(config if isinstance(config, str) else json.dumps(config))
    _rewrite_manifest(ckpt, "config.json")


def poison_with_nan(ckpt: Path) -> str:
    """Put a NaN into the first floating tensor of model.safetensors; returns its name."""
    import torch
    from safetensors.torch import load_file, save_file

    tensors = load_file(str(ckpt / "model.safetensors"))
    name = next(k for k, v in sorted(tensors.items()) if v.is_floating_point() and v.numel())
    t = tensors[name].clone()
    t.view(-1)[0] = float("nan")
    tensors[name] = t
    save_file(tensors, str(ckpt / "model.safetensors"), metadata={"format": "hope.checkpoint/1"})
    _rewrite_manifest(ckpt, "model.safetensors")
    assert not bool(torch.isfinite(t).all())
    return name


def completed_run(registry, run_dir: Path, component: str = "fast_loop", data: str | Path = "x") -> str:
    """A run row for run_dir, taken through running to completed (finished_at = now). `data` is the
    run's dataset as the registry holds it, which `promote RUN` gates on."""
    from registry import runs

    with registry.session() as s:
        run = runs.create_run(s, component=component, config={"data": str(data)}, total_steps=10,
                              run_dir=str(run_dir))
        runs.transition(s, run, "starting")
        runs.transition(s, run, "running")
        runs.transition(s, run, "completed", reason="trainer")
        return run.id
