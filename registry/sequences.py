"""Chains: one queued run per component, in order, sharing a sequence id (`sequential`,
`POST /api/training/sequential`, the demo). Each member starts only after the previous one
completed (runs.next_dispatchable); one that fails or is cancelled cancels the rest. Where each
member's VQ-VAE comes from is hope_models/components/chain.py's plan_chain; this only executes it."""
from __future__ import annotations

from pathlib import Path
from typing import Any, Iterable, Mapping

from hope_models.components import TOKENIZER
from hope_models.components.chain import VQVAE_MEMBER, SequenceError, first_missing, parse_sequence, plan_chain
from registry import runs
from registry.models import Run, new_run_id


def create_sequence(s: Any, components: Iterable[str] | str, base_config: dict[str, Any], *, total_steps: int,
                    runs_dir: Any, queue: str = "pi", priority: int = 0, max_attempts: int = 3,
                    sequence_id: str | None = None,
                    member_configs: Mapping[str, Mapping[str, Any]] | None = None) -> list[Run]:
    """Queue a chain: one run per component, in order, sharing a sequence id (indices 0..n-1).
    Each member starts only after the previous one completed (next_dispatchable), and one that
    fails or is cancelled cancels the rest. A member that reads VQ-VAE codes, after the tokenizer's
    member, gets config["vqvae_run"] = that member's id (the worker resolves it to its run dir).
    `member_configs` (component -> config) replaces base_config for the members it names, whose
    total_steps is then that config's "steps": a chain whose members train with steps, rates or
    model_configs of their own (the camera demo's)."""
    text = components if isinstance(components, str) else ",".join(components)
    try:
        names = parse_sequence(text)
    except SequenceError as exc:
        raise runs.RunError(str(exc).replace("--sequential", "components")) from None
    plan = plan_chain(names, given=bool(base_config.get("vqvae_dir") or base_config.get("vqvae_run")))
    missing = first_missing(plan)
    if missing:
        raise runs.RunError(f"components: {missing} needs a trained VQ-VAE: put {TOKENIZER} before it in the chain, "
                            "or give vqvae_dir / vqvae_run")
    seq = sequence_id or "s" + new_run_id()[1:]
    created: list[Run] = []
    for index, step in enumerate(plan):
        own = (member_configs or {}).get(step.name)
        cfg = dict(base_config if own is None else own)  # a given vqvae_dir / vqvae_run stays as given
        steps = total_steps if own is None else own.get("steps", total_steps)
        if step.vqvae == VQVAE_MEMBER and step.member is not None:
            cfg.pop("vqvae_dir", None)
            cfg["vqvae_run"] = created[step.member].id
        elif not step.reads_vqvae:
            cfg.pop("vqvae_dir", None)
            cfg.pop("vqvae_run", None)
        run_id = new_run_id()
        run = runs.create_run(s, component=step.name, config=cfg, total_steps=steps,
                              run_dir=str(Path(runs_dir) / run_id), queue=queue, priority=priority,
                              max_attempts=max_attempts, sequence_id=seq, sequence_index=index, run_id=run_id)
        created.append(run)
    return created
