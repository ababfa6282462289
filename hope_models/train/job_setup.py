"""Setting a job up before its first step: the dataset cache, the VQ-VAE it reads, the memory
pre-flight, and whether a run dir's checkpoint may be resumed. Each refusal is a TrainSetupError
naming the parameter or path; everything here runs before the run dir exists or torch trains."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Callable

from hope_models import checkpoints as ckpt
from hope_models.components import spec_of
from hope_models.disk import is_disk_full
from hope_models.settings import load_settings
from hope_models.train.config import TrainConfig
from hope_models.train.contract import TrainSetupError
from hope_models.train.dataset_dir import dataset_dir_for

LOADER_CHUNK = 8  # window batches built per vectorised call (the pre-flight estimate counts them)


def torch_settings(torch, threads: int) -> None:
    """How every torch job here computes (`torch` passed in: this module imports no torch)."""
    torch.set_num_threads(threads)
    # A peaked softmax (a keypoint's cells, far from it) makes subnormal floats, which cost a CPU
    # 10-15x per operation (measured on the Fast Loop's keypoint drawing) and carry no signal.
    torch.set_flush_denormal(True)
    # torch.use_deterministic_algorithms also sets torch.compile's flag, whose import loads that
    # compiler (hope_models/train/adamw.py says what it costs a job): the flag is set where the kernels read it.
    setter = getattr(torch._C, "_set_deterministic_algorithms", None)
    if setter is None:
        torch.use_deterministic_algorithms(True)
    else:
        setter(True, warn_only=False)


def open_dataset(cfg: TrainConfig, log: Callable[[str, str], None]):
    """The compiled cache of cfg.data (built on first use) and its build info; TrainSetupError
    names the path when it holds nothing to train on."""
    from hope_models.data.cache import CacheError, load_or_build  # lazy: loads mcap, numpy
    from hope_models.data.features import FeatureSpecError  # lazy: loads numpy

    if cfg.cache_dir:
        cache_root = Path(cfg.cache_dir)
    else:
        cache_root = load_settings().cache_dir
    data_dir = dataset_dir_for(cfg.data, cache_root)
    try:
        cache, info = load_or_build(data_dir, cache_root, cfg.spec_path)
    except (CacheError, FeatureSpecError) as exc:
        raise TrainSetupError(f"--data {cfg.data}: {exc}") from None
    except OSError as exc:
        if is_disk_full(exc):  # not a usage error: the job pauses (loop.train says where, how much is free)
            raise
        raise TrainSetupError(f"--data {cfg.data}: {exc.filename or ''} {exc.strerror or exc}") from None
    if cache.n_episodes == 0 or cache.n_steps == 0:
        excluded = cache.manifest.get("excluded", [])
        why = f" ({len(excluded)} excluded, e.g. {excluded[0]['reason']})" if excluded else ""
        raise TrainSetupError(f"--data {cfg.data}: no usable episodes{why}")
    for note in info.notes:
        log(f"dataset cache: {note}", "warning")
    return cache, info


def resolve_vqvae(cfg: TrainConfig) -> Path | None:
    """The VQ-VAE checkpoint dir cfg.vqvae_dir names (a checkpoint or a run dir), or None."""
    if not cfg.vqvae_dir:
        return None
    try:
        return ckpt.resolve_checkpoint_dir(cfg.vqvae_dir)
    except ckpt.CheckpointError as exc:
        raise TrainSetupError(f"--vqvae {cfg.vqvae_dir}: {exc}") from None


def check_resume_matches(cfg: TrainConfig, loaded: ckpt.LoadedCheckpoint, run_dir: Path,
                         log: Callable[[str, str], None]) -> None:
    """A run dir's checkpoint may be resumed only with the same math (TrainConfig.identity())."""
    saved = loaded.config.get("train", {})
    if not isinstance(saved, dict):  # config.json is read as untrusted: a clear error, not a traceback
        raise TrainSetupError(f"{loaded.path / ckpt.CONFIG_FILE}: 'train' must be an object, got "
                              f"{type(saved).__name__}; choose a new --run-dir")
    mine = json.loads(json.dumps(cfg.identity()))  # tuples -> lists, as saved
    diffs = [f"{k}: {saved.get(k)!r} in the run dir, {v!r} now" for k, v in mine.items() if saved.get(k) != v]
    if diffs:
        raise TrainSetupError(
            f"{run_dir} holds a run with other settings ({'; '.join(diffs)}); re-run with the same "
            "arguments to resume it, or choose a new --run-dir")
    if saved.get("threads") != cfg.threads:
        log(f"resuming with threads={cfg.threads} (the run started with {saved.get('threads')}); "
            "the weights may differ in the last bits from an uninterrupted run", "warning")
    if saved.get("steps") != cfg.steps:
        log(f"--steps changed from {saved.get('steps')} to {cfg.steps}: the cosine schedule "
            "follows the new total from here", "warning")


def estimate_from_config(cfg: TrainConfig, cache, vqvae_dir: Path | None):
    """The memory estimate of the component cfg describes, from its configuration: nothing is
    built, so a model too big for the budget is refused before it can take the memory."""
    from hope_models.components.resolve import read_vqvae_config, resolve  # lazy: loads numpy
    from hope_models.train import estimate  # lazy: loads psutil

    try:
        vq = read_vqvae_config(vqvae_dir) if vqvae_dir is not None and spec_of(cfg.component).reads_codes \
            else None
        resolved = resolve(cfg.component, cache.spec, dict(cfg.model_config), vq)
    except ValueError as exc:
        raise TrainSetupError(f"cannot build {cfg.component}: {exc}") from None
    return estimate.estimate_from_config(resolved, cfg.batch_size, cache.spec.obs_dim, cache.spec.act_dim,
                                         cache_mb=estimate.cache_resident_mb(cache), loader_chunk=LOADER_CHUNK)


def estimate_built(cfg: TrainConfig, component, cache):
    """A stand-in factory's component is known only once built: its estimate from the model."""
    from hope_models.train.estimate import cache_resident_mb, estimate_memory  # lazy: loads psutil

    win = component.window
    return estimate_memory(cfg.component, component.model, cfg.batch_size, win.k, cache.spec.obs_dim,
                           cache.spec.act_dim, bool(component.wants_frames), horizons=len(win.horizons_s),
                           cache_mb=cache_resident_mb(cache), loader_chunk=LOADER_CHUNK)


def check_budget(cfg: TrainConfig, est) -> None:
    """Refuse, before the first step, a configuration whose estimated memory cannot fit the budget."""
    from hope_models.train.estimate import MemoryBudgetError, check_fits  # lazy: loads psutil

    try:
        check_fits(est, cfg.memory_budget_mb, cfg.memory_soft_fraction)
    except MemoryBudgetError as exc:
        raise TrainSetupError(str(exc)) from None
