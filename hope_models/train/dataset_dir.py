"""The directory the dataset cache reads for a run's `data`, whatever the user pointed at."""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

from hope_models.train.contract import TrainSetupError


def dataset_dir_for(data: str | os.PathLike, cache_root: Path) -> Path:
    """The dir load_or_build reads. A single episode file (JSON, JSONL, TFRecord, MCAP) gets a dir
    of its own holding a symlink to it, so the cache (which walks dirs) reads it through discover."""
    p = Path(data).expanduser()
    if not p.exists():
        raise TrainSetupError(f"--data {data}: no such file or directory")
    if p.is_dir():
        return p
    p = p.resolve()
    link_dir = cache_root / "sources" / hashlib.sha256(str(p).encode("utf-8")).hexdigest()[:16]
    link = link_dir / p.name
    link_dir.mkdir(parents=True, exist_ok=True)
    if not (link.is_symlink() and Path(os.readlink(link)) == p):
        # a symlink, not file data: durable.atomic_write does not apply; symlink + rename is atomic
        tmp = link_dir / f".{p.name}.{os.getpid()}.tmp"
        tmp.unlink(missing_ok=True)
        os.symlink(p, tmp)
        os.replace(tmp, link)
    return link_dir
