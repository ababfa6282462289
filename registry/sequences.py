"""Chains: one queued run per component, in order, sharing a sequence id (`sequential`,
`POST /api/training/sequential`, the demo). Each member starts only after the previous one
completed (runs.next_dispatchable); one that fails or is cancelled cancels the rest."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable

from hope_models.components import COMPONENTS, TOKENIZER
from hope_models.components.chain import SequenceError, parse_sequence, tokenizer_missing
from registry import runs
from registry.models import Run, new_run_id


def create_sequence(s: Any, components: Iterable[str] | str, base_config: dict[str, Any], *, total_steps: int,
                    runs_dir: Any, queue: str = "pi", priority: int = 0, max_attempts: int = 3,
                    sequence_id: str | None = None) -> list[Run]:
    """Queue a chain: one run per component, in order, sharing a sequence id (indices 0..n-1).
    Each member starts only after the previous one completed (next_dispatchable), and one that
    fails or is cancelled cancels the rest. A member that reads VQ-VAE codes, after the tokenizer's
    member, gets config["vqvae_run"] = that member's id (the worker resolves it to its run dir)."""
    text = components if isinstance(components, str) else ",".join(components)
    try:
        names = parse_sequence(text)
    except SequenceError as exc:
        raise runs.RunError(str(exc).replace("--sequential", "components")) from None
    missing = tokenizer_missing(names, bool(base_config.get("vqvae_dir") or base_config.get("vqvae_run")))
    if missing:
        raise runs.RunError(f"components: {missing} needs a trained VQ-VAE: put {TOKENIZER} before it in the chain, "
                            "or give vqvae_dir / vqvae_run")
    seq = sequence_id or "s" + new_run_id()[1:]
    created: list[Run] = []
    vqvae_run: str | None = None
    for index, name in enumerate(names):
        cfg = dict(base_config)
        reads = COMPONENTS[name].reads_vqvae != "never"
        if reads and vqvae_run is not None:
            cfg.pop("vqvae_dir", None)
            cfg["vqvae_run"] = vqvae_run
        if not reads:
            cfg.pop("vqvae_dir", None)
            cfg.pop("vqvae_run", None)
        run_id = new_run_id()
        run = runs.create_run(s, component=name, config=cfg, total_steps=total_steps,
                              run_dir=str(Path(runs_dir) / run_id), queue=queue, priority=priority,
                              max_attempts=max_attempts, sequence_id=seq, sequence_index=index, run_id=run_id)
        if name == TOKENIZER:
            vqvae_run = run.id
        created.append(run)
    return created
