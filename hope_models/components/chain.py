"""A chain of components trained one after the other ("vqvae,fast_loop,mid_loop"): the text
`--sequential`, the API's `components` and the demo give, checked against the table. The
tokenizer comes before the components that read its codes; one that needs them and has neither
the chain's tokenizer before it nor a given one cannot start.

plan_chain is the one decision of where each member's VQ-VAE comes from; the two runners only
execute its plan: `train --sequential` (hope_models/train/sequential.py: a child process per
member, `--vqvae` a checkpoint dir) and create_sequence (registry/sequences.py: a queued run per
member, config["vqvae_run"] the tokenizer member's run id)."""
from __future__ import annotations

from dataclasses import dataclass

from hope_models.components import COMPONENTS, NEEDS_VQVAE, TOKENIZER

# Where a member's VQ-VAE comes from.
VQVAE_NONE = "none"      # it trains without one: it never reads codes, or reads them optionally and has none
VQVAE_GIVEN = "given"    # the one the request names (a dir, a run)
VQVAE_MEMBER = "member"  # the tokenizer trained earlier in this chain


class SequenceError(ValueError):
    """The chain cannot start (unknown component, a reader of codes before the tokenizer, ...)."""


def parse_sequence(text: str) -> list[str]:
    """The components of "a,b,c" in order; the tokenizer before any component that reads its codes."""
    parts = [n.strip() for n in text.split(",")]
    names = [n for n in parts if n]
    if not names:
        raise SequenceError(f"--sequential needs at least one component, e.g. {','.join(COMPONENTS)}")
    if len(names) != len(parts):  # "vqvae,,fast_loop" is a typo, not a shorter chain
        raise SequenceError(f"--sequential {text[:100]!r}: an empty component name (two commas in a row, or a "
                            "comma at an end)")
    unknown = [n for n in names if n not in COMPONENTS]
    if unknown:
        raise SequenceError(f"--sequential: unknown component(s) {', '.join(unknown)} "
                            f"(known: {', '.join(COMPONENTS)})")
    if len(set(names)) != len(names):
        raise SequenceError(f"--sequential {text}: a component is listed twice")
    if TOKENIZER in names and any(COMPONENTS[n].reads_codes for n in names[:names.index(TOKENIZER)]):
        raise SequenceError(f"--sequential: {TOKENIZER} must come before the components that read its codes")
    return names


def tokenizer_missing(names: list[str], has_vqvae: bool) -> str | None:
    """The first component of a chain that needs a trained VQ-VAE and has none (neither the chain's
    tokenizer before it nor one given), or None."""
    return first_missing(plan_chain(names, given=has_vqvae))


def first_missing(plan: list["ChainStep"]) -> str | None:
    """The first member of a plan that needs a VQ-VAE and has none, or None."""
    return next((step.name for step in plan if step.missing), None)


@dataclass(frozen=True)
class ChainStep:
    """One member of a planned chain."""
    name: str
    vqvae: str                      # VQVAE_NONE, VQVAE_GIVEN or VQVAE_MEMBER
    member: int | None = None       # with VQVAE_MEMBER: the index in the chain of the member it reads
    reads_vqvae: bool = False       # whether the component reads codes at all (its spec's reads_vqvae)
    missing: bool = False           # it needs a VQ-VAE and has none: it cannot start


def plan_chain(names: list[str], *, given: bool, given_first: bool = False) -> list[ChainStep]:
    """For each member of a parsed chain (parse_sequence), in order: where its VQ-VAE comes from.

    A member that reads codes gets the chain's tokenizer trained before it, else the given one
    (`given`: the request names one), else none; with `given_first` a given one wins over the
    chain's tokenizer (`train --sequential --vqvae DIR`). A member that never reads codes gets
    none whatever is given. One that needs codes and has neither is `missing` (tokenizer_missing
    names the first); each runner refuses it with its own message."""
    steps: list[ChainStep] = []
    tokenizer: int | None = None
    for index, name in enumerate(names):
        reads = COMPONENTS[name].reads_codes
        if not reads:
            step = ChainStep(name, VQVAE_NONE)
        elif given and (given_first or tokenizer is None):
            step = ChainStep(name, VQVAE_GIVEN, reads_vqvae=True)
        elif tokenizer is not None:
            step = ChainStep(name, VQVAE_MEMBER, member=tokenizer, reads_vqvae=True)
        else:
            step = ChainStep(name, VQVAE_NONE, reads_vqvae=True, missing=name in NEEDS_VQVAE)
        steps.append(step)
        if name == TOKENIZER:
            tokenizer = index
    return steps
