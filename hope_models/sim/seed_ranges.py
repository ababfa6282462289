"""Which simulator start states are new: the seed ranges evaluation, demos and imagined rollouts use.

A task seed fixes an episode's start state (joint angles, target position, on track the circle).
The seed space is split by convention:

    [0, 100 000)          evaluation (eval-reflex --seed S uses S .. S+N-1; default 0 .. 19)
    [100 000, 200 000)    expert demonstrations (sim-demos, recorder.DEFAULT_SEED_BASE)
    [200 000, ...)        imagined rollouts (DEFAULT_SEED_BASE here)

imagine_dataset refuses a seed range that overlaps the evaluation or demo ranges unless
allow_overlap=True, and with `demos=DIR...` it also refuses seeds that any recorded episode under
those dirs used (read from metadata.provenance.sim.seed / task), wherever they came from.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Iterable, Sequence

from hope_models.sim.recorder import DEFAULT_SEED_BASE as DEMO_SEED_BASE

DEFAULT_SEED_BASE = 200_000  # the first imagined rollout's seed
EVAL_SEED_RANGE = (0, DEMO_SEED_BASE)
DEMO_SEED_RANGE = (DEMO_SEED_BASE, DEFAULT_SEED_BASE)
# name -> [first, end): the ranges imagined rollouts stay out of by default
RESERVED_SEED_RANGES: dict[str, tuple[int, int]] = {
    "evaluation (eval-reflex held-out seeds)": EVAL_SEED_RANGE,
    "expert demonstrations (sim-demos)": DEMO_SEED_RANGE,
}


def reserved_overlaps(seed: int, episodes: int) -> list[str]:
    """Names of the reserved seed ranges that [seed, seed + episodes) overlaps."""
    return [name for name, (lo, hi) in RESERVED_SEED_RANGES.items() if seed < hi and lo < seed + episodes]


def demo_seeds(dirs: Iterable[str | Path]) -> dict[tuple[str, int], str]:
    """(task, seed) -> episode dir of every recorded sim episode under `dirs` (metadata.json files
    carrying provenance.sim.seed); other episodes are ignored."""
    found: dict[tuple[str, int], str] = {}
    for d in dirs:
        root = Path(d)
        if not root.exists():
            raise FileNotFoundError(f"{root}: demos dir not found")
        for meta_path in sorted(root.rglob("metadata.json")):
            try:
                meta = json.loads(meta_path.read_text(encoding="utf-8"))
            except (OSError, ValueError):
                continue
            sim = (meta.get("provenance") or {}).get("sim") if isinstance(meta, dict) else None
            if isinstance(sim, dict) and isinstance(sim.get("seed"), int) and isinstance(sim.get("task"), str):
                found[(sim["task"], sim["seed"])] = str(meta_path.parent)
    return found


def check_seeds(seed: int, episodes: int, task: str, demos: Sequence[str | Path] = (),
                allow_overlap: bool = False) -> None:
    """Raise ValueError (naming the range or the demo) when the imagined start states are not new."""
    if not allow_overlap:
        hit = reserved_overlaps(seed, episodes)
        if hit:
            lo, hi = RESERVED_SEED_RANGES[hit[0]]
            raise ValueError(f"seed={seed}: seeds {seed}..{seed + episodes - 1} overlap the {hit[0]} range "
                             f"[{lo}, {hi}); imagined rollouts start at {DEFAULT_SEED_BASE} by default "
                             "(or pass allow_overlap / --allow-overlap)")
    if demos:
        used = demo_seeds(demos)
        clash = [s for s in range(seed, seed + episodes) if (task, s) in used]
        if clash:
            raise ValueError(f"seed={seed}: {len(clash)} imagined start state(s) are demo start states, e.g. "
                             f"{task} seed {clash[0]} recorded in {used[(task, clash[0])]}; pick another --seed")
