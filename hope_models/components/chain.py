"""A chain of components trained one after the other ("vqvae,fast_loop,mid_loop"): the text
`--sequential`, the API's `components` and the demo give, checked against the table. The
tokenizer comes before the components that read its codes; one that needs them and has neither
the chain's tokenizer before it nor a given one cannot start."""
from __future__ import annotations

from hope_models.components import COMPONENTS, NEEDS_VQVAE, TOKENIZER


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
    if TOKENIZER in names and any(COMPONENTS[n].reads_vqvae != "never" for n in names[:names.index(TOKENIZER)]):
        raise SequenceError(f"--sequential: {TOKENIZER} must come before the components that read its codes")
    return names


def tokenizer_missing(names: list[str], has_vqvae: bool) -> str | None:
    """The first component of a chain that needs a trained VQ-VAE and has none (neither the chain's
    tokenizer before it nor one given), or None."""
    for i, name in enumerate(names):
        if name in NEEDS_VQVAE and TOKENIZER not in names[:i] and not has_vqvae:
            return name
    return None
