"""Tiny real fast_loop checkpoints for the inference-runtime tests (BrainService, the NumPy fast_loop).

Trained once per test run (shared by the xdist workers) with the real trainer, one thread, on small synthetic
datasets; about 10 s in all on an idle core:

    runs = brain_runs(tmp_path_factory)
    runs["alpha15"], runs["alpha30"]   two versions of one run (obs 6 -> act 2), d_model 16
    runs["big"]                        default model size (d_model 128, d_state 256), same data
    runs["vq"]                         a vector VQ-VAE checkpoint (not a fast_loop)
    runs["alpha_vq"]                   a fast_loop reading that VQ-VAE's codes
    runs["other"]                      a fast_loop for another robot (obs 8 -> act 3)

    whole = brain_whole_runs(tmp_path_factory)  (tests/test_brain_whole.py: all three components)
    whole["vq_a"], whole["vq_b"]       two versions of one vector VQ-VAE run (2 groups of 16 codes)
    whole["mid_a"], whole["mid_b"]     two versions of one mid_loop run reading vq_a (K=20, horizons 5, 10)
    whole["vq8"], whole["mid8"]        a VQ-VAE and a mid_loop for another robot (obs 8 -> act 3)

`promote_pointer(home, ckpt)` writes $HOPE_HOME/promoted/fast_loop.json the way the gate does
(hope_models.promoted), and `rewrite_manifest(ckpt)` re-hashes a checkpoint dir a test has
edited, so the edit reaches the check under test instead of stopping at the manifest.
"""
from __future__ import annotations

import hashlib
import json
from datetime import datetime, timezone
from pathlib import Path

_RUNS: dict[str, Path] = {}
SMALL = {"d_model": 16, "d_state": 32}


def _train(data: Path, run_dir: Path, cache: Path, component: str, steps: int, every: int,
           model_config: dict, vqvae_dir: Path | None = None) -> Path:
    from hope_models.train.loop import TrainConfig, train

    result = train(TrainConfig(component=component, data=str(data), run_dir=str(run_dir), steps=steps, seed=0,
                               batch_size=16, threads=1, checkpoint_every_steps=every, log_every=10,
                               cache_dir=str(cache), thermal_zone=None, vcgencmd=None, model_config=model_config,
                               vqvae_dir=None if vqvae_dir is None else str(vqvae_dir), val_batches=1))
    assert result.outcome == "completed", result.message
    return Path(result.checkpoint)


def brain_runs(tmp_path_factory) -> dict[str, Path]:
    """Trained once per test run (conftest.shared_build), whatever the number of xdist workers."""
    if _RUNS:
        return _RUNS
    from conftest import shared_build

    root = shared_build(tmp_path_factory, "brain", _build_runs)
    runs = {name: root / rel for name, rel in json.loads((root / "runs.json").read_text()).items()}
    assert (runs["alpha15"] / "model.safetensors").is_file()
    _RUNS.update(runs)
    return _RUNS


def _datasets(root: Path) -> None:
    """ds6 (6 -> 2) and ds8 (8 -> 3): both builds generate the same ones, so their models fit together."""
    from hope_models.data.synthetic import generate_dataset

    generate_dataset(root / "ds6", 1500, obs_dim=6, act_dim=2, episode_seconds=(5, 15), seed=1)
    generate_dataset(root / "ds8", 800, obs_dim=8, act_dim=3, episode_seconds=(5, 15), seed=2)


def _build_runs(root: Path) -> None:
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _datasets(root)
        cache = root / "cache"
        alpha30 = _train(root / "ds6", root / "runs" / "alpha", cache, "fast_loop", 30, 15, SMALL)
        runs = {"alpha30": alpha30, "alpha15": alpha30.parent / "00000015"}
        runs["big"] = _train(root / "ds6", root / "runs" / "big", cache, "fast_loop", 10, 10, {})
        runs["vq"] = _train(root / "ds6", root / "runs" / "vq", cache, "vqvae", 20, 20,
                            {"n_codes": 16, "code_dim": 8, "groups": 2, "hidden": 16})
        runs["alpha_vq"] = _train(root / "ds6", root / "runs" / "alpha_vq", cache, "fast_loop", 20, 20, SMALL,
                                  vqvae_dir=runs["vq"])
        runs["other"] = _train(root / "ds8", root / "runs" / "other", cache, "fast_loop", 10, 10, SMALL)
    finally:
        torch.set_num_threads(threads)
    (root / "runs.json").write_text(json.dumps({name: str(p.relative_to(root)) for name, p in runs.items()}))


_WHOLE: dict[str, Path] = {}
VQ_SMALL = {"n_codes": 16, "code_dim": 8, "groups": 2, "hidden": 16}
MID_SMALL = {"d_model": 16, "d_state": 16, "n_layers": 2}


def brain_whole_runs(tmp_path_factory) -> dict[str, Path]:
    """The vqvae and mid_loop checkpoints of brain_whole_runs (module doc), trained once per test run."""
    if _WHOLE:
        return _WHOLE
    from conftest import shared_build

    root = shared_build(tmp_path_factory, "brain-whole", _build_whole)
    _WHOLE.update({name: root / rel for name, rel in json.loads((root / "runs.json").read_text()).items()})
    return _WHOLE


def _build_whole(root: Path) -> None:
    import torch

    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        _datasets(root)  # the same data as brain_runs' ds6/ds8: the fast_loops there fit
        cache = root / "cache"
        vq_b = _train(root / "ds6", root / "runs" / "vq", cache, "vqvae", 60, 30, VQ_SMALL)
        runs = {"vq_a": vq_b.parent / "00000030", "vq_b": vq_b}
        # long enough to learn that codes persist (the surprise test needs a model that expects something)
        mid_b = _train(root / "ds6", root / "runs" / "mid", cache, "mid_loop", 200, 100, MID_SMALL,
                       vqvae_dir=runs["vq_a"])
        runs.update(mid_a=mid_b.parent / "00000100", mid_b=mid_b)
        runs["vq8"] = _train(root / "ds8", root / "runs" / "vq8", cache, "vqvae", 20, 20, VQ_SMALL)
        runs["mid8"] = _train(root / "ds8", root / "runs" / "mid8", cache, "mid_loop", 10, 10, MID_SMALL,
                              vqvae_dir=runs["vq8"])
    finally:
        torch.set_num_threads(threads)
    (root / "runs.json").write_text(json.dumps({name: str(p.relative_to(root)) for name, p in runs.items()}))


def promote_pointer(home: Path, ckpt: Path, component: str = "fast_loop", model_id: int = 1) -> dict:
    """Write the component's pointer to `ckpt` as the promotion code does; returns the pointer."""
    from hope_models.promoted import checkpoint_version, write_pointer

    version, sha = checkpoint_version(ckpt)
    obj = {"component": component, "checkpoint": str(Path(ckpt).resolve()), "version": version, "sha256": sha,
           "model_id": model_id, "run_id": None, "promoted_at": datetime.now(timezone.utc).isoformat()}
    write_pointer(home, component, obj)
    return obj


def serve_a_copy(home: Path, tmp_path_factory, name: str = "alpha30") -> Path:
    """The brain run `name` copied under `home`/runs and promoted there (what a real serve in
    `home` then serves); the copy's checkpoint dir."""
    import shutil

    ckpt = brain_runs(tmp_path_factory)[name]
    run_dir = home / "runs" / "alpha"
    shutil.copytree(ckpt.parents[1], run_dir)
    promote_pointer(home, run_dir / "checkpoints" / ckpt.name)
    return run_dir / "checkpoints" / ckpt.name


def overflowing_copy(src: Path, dst: Path, column: int = 0) -> tuple[Path, float]:
    """A copy of fast_loop checkpoint `src` that computes NaN from some valid observations: the
    obs_in weights reading observation value `column` are +-1e33 (finite, so the checkpoint loads),
    which overflows float32 to Inf once that value is far from its mean (1e6 is), while an
    observation holding exactly the mean there answers normally (normalised 0 x 1e33 = 0).
    Returns (the copy, that mean as the float the client sends)."""
    import shutil

    import numpy as np
    from safetensors.numpy import load_file, save_file

    shutil.copytree(src, dst)
    tensors = load_file(str(dst / "model.safetensors"))
    w = tensors["obs_in.weight"].copy()
    w[:, column] = np.where(np.arange(w.shape[0]) % 2 == 0, 1e33, -1e33).astype(np.float32)
    tensors["obs_in.weight"] = w
    save_file(tensors, str(dst / "model.safetensors"), metadata={"format": "hope.checkpoint/1"})
    rewrite_manifest(dst)
    mean = json.loads((dst / "config.json").read_text())["feature_spec"]["observation"]["mean"][column]
    return dst, float(np.float32(mean))


def rewrite_manifest(ckpt: Path) -> None:
    """Re-hash every file of an edited checkpoint dir into its manifest.json."""
    manifest = json.loads((ckpt / "manifest.json").read_text())
    for name in manifest["files"]:
        data = (ckpt / name).read_bytes()
        manifest["files"][name] = {"sha256": hashlib.sha256(data).hexdigest(), "size": len(data)}
    (ckpt / "manifest.json").write_text(json.dumps(manifest))
