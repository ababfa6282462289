"""What a run was made from, written once per attempt when training starts: `<run_dir>/provenance.json`.

    {"format": 1, "written_at": unix s, "component",
     "config":  the attempt's full TrainConfig (TrainConfig.to_json_obj()),
     "dataset": {"path", "cache", "fingerprint", "episodes", "steps", "imagined_episodes",
                 "imagined_share", "imagined_ratio"},
     "vqvae":   {"dir", "run_id", "version"} | null (a vqvae run, or a component that reads none),
     "code":    {"version", "git_commit", "git_dirty"}}

The dataset figures are the compiled cache's (what the sampler draws from): `imagined_episodes`
are the episodes the imagination pipeline wrote (their origin says `imagined:...`; the cache
build marks them in imagined.npy), `imagined_share` their share of the episodes, `imagined_ratio`
the share of a batch the config asks for. The code version is the installed package's; the git
commit and dirty flag only when the package runs from a git checkout (null otherwise, never
guessed). A resumed attempt writes the file again: it says what the latest attempt ran with.

Cost at run start: two `git` calls (2 s timeout each) and the VQ-VAE weights' sha256 (the
version string), which components.py hashes anyway. Torch-free; a failure to write is logged,
never fatal (provenance must not stop a run).
"""
from __future__ import annotations

import json
import logging
import subprocess
import threading
import time
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from hope_models.checkpoint_format import VQVAE_REF, CheckpointError, checkpoint_version
from hope_models.durable import atomic_write

log = logging.getLogger(__name__)

FILE = "provenance.json"
FORMAT = 1
PACKAGE = "hope-seed-trainer"
GIT_TIMEOUT_S = 2.0


def package_version() -> str | None:
    try:
        return version(PACKAGE)
    except PackageNotFoundError:
        return None


def _git(repo: Path, *args: str) -> str | None:
    """git's stdout, or None (no git, an error, or killed after GIT_TIMEOUT_S). The timeout is a
    timer that kills the child, not subprocess's timeout, whose wait polls with time.sleep (which
    the loop's tests count)."""
    try:
        proc = subprocess.Popen(["git", "-C", str(repo), *args], stdout=subprocess.PIPE,
                                stderr=subprocess.DEVNULL, stdin=subprocess.DEVNULL, text=True)
    except OSError:
        return None
    timer = threading.Timer(GIT_TIMEOUT_S, proc.kill)
    timer.start()
    try:
        out, _ = proc.communicate()
    finally:
        timer.cancel()
    return out if proc.returncode == 0 else None


def code_info() -> dict[str, Any]:
    """{"version", "git_commit", "git_dirty"} of the code running now."""
    repo = Path(__file__).resolve().parents[2]
    commit = dirty = None
    if (repo / ".git").exists():
        head = _git(repo, "rev-parse", "HEAD")
        commit = (head.strip() or None) if head is not None else None
        if commit is not None:
            status = _git(repo, "status", "--porcelain", "--untracked-files=no")
            dirty = bool(status.strip()) if status is not None else None
    return {"version": package_version(), "git_commit": commit, "git_dirty": dirty}


def dataset_info(cfg, cache) -> dict[str, Any]:
    episodes = int(cache.n_episodes)
    imagined = int(cache.imagined.sum())
    return {"path": str(cfg.data), "cache": str(cache.path), "fingerprint": getattr(cache, "fingerprint", None),
            "episodes": episodes, "steps": int(cache.n_steps), "imagined_episodes": imagined,
            "imagined_share": imagined / episodes if episodes else None,
            "imagined_ratio": getattr(cfg, "imagined_ratio", None)}


def vqvae_info(vqvae_dir: Path | None) -> dict[str, Any] | None:
    if vqvae_dir is None:
        return None

    ckpt = Path(vqvae_dir)
    run_id = ckpt.parent.parent.name if ckpt.parent.name == "checkpoints" else None
    try:
        version = checkpoint_version(ckpt)[0]
    except CheckpointError:
        version = None
    return {"dir": str(ckpt), "run_id": run_id, "version": version}


def write_provenance(run_dir: Path, cfg, cache, vqvae_dir: Path | None) -> None:
    """provenance.json for this attempt (atomic); logs and carries on when it cannot."""
    try:
        obj = {"format": FORMAT, "written_at": round(time.time(), 3), "component": cfg.component,
               "config": cfg.to_json_obj(), "dataset": dataset_info(cfg, cache), VQVAE_REF: vqvae_info(vqvae_dir),
               "code": code_info()}
        atomic_write(Path(run_dir) / FILE, json.dumps(obj, indent=1, default=str).encode("utf-8"))
    except Exception as exc:  # noqa: BLE001  provenance is a record, never a reason to stop training
        log.warning("%s: provenance not written: %s", run_dir, exc)


def read_provenance(run_dir: str | Path) -> dict[str, Any] | None:
    """The run dir's provenance.json, or None (absent, unreadable or not an object)."""
    try:
        obj = json.loads((Path(run_dir) / FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return obj if isinstance(obj, dict) else None
