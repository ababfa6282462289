"""The HOPE v1 seed components, one folder each, and the one table the house reads them from.

    COMPONENTS["mid_loop"].reads_vqvae      # "required"
    for name, spec in COMPONENTS.items(): ...

A component is its folder (vqvae/, fast_loop/, mid_loop/: config, torch model, loss, NumPy
serving form, checkpoint check, held-out figures) and its ComponentSpec (spec.py) in the
folder's __init__.py; adding one is a folder and a row below (tests/test_fourth_component.py). Nothing outside this package asks a
component by its name: it asks the spec (tests/test_component_unit.py holds the house to it).
Torch-free: the daemon, the webapp and a worker's parent import this table.
"""
from __future__ import annotations

import importlib
from collections.abc import Iterator, Mapping

from hope_models.components.spec import ComponentSpec


class ComponentTable(Mapping):
    """name -> ComponentSpec, read-only, in its rows' order. Anything that is not a string (a
    request's list or object) is simply not in it, rather than a TypeError."""

    def __init__(self, specs: list[ComponentSpec]):
        self._specs = {spec.name: spec for spec in specs}

    def __getitem__(self, name: str) -> ComponentSpec:
        return self._specs[name]

    def __contains__(self, name: object) -> bool:
        return isinstance(name, str) and name in self._specs

    def __iter__(self) -> Iterator[str]:
        return iter(self._specs)

    def __len__(self) -> int:
        return len(self._specs)


def _table(*folders: str) -> ComponentTable:
    return ComponentTable([importlib.import_module(f"{__name__}.{folder}").SPEC for folder in folders])


# One row per component, in training order: a component comes after the tokenizer whose codes it
# reads. A row is the folder's name; its __init__.py holds the SPEC.
COMPONENTS = _table(
    "vqvae",
    "fast_loop",
    "mid_loop",
)



def _the_one(role: str) -> str:
    names = [name for name, spec in COMPONENTS.items() if getattr(spec, role)]
    if len(names) != 1:
        raise ImportError(f"hope_models.components: exactly one component has the role {role!r}, not {names}")
    return names[0]


# The roles the house asks for by what they do, not by name: the tokenizer whose codes the others
# read, the one that acts (the reflex: its action answers, sim rollouts), the one that predicts
# (surprise, imagination).
TOKENIZER: str = _the_one("tokenizer")
ACTOR: str = _the_one("acts")
PREDICTOR: str = _the_one("predicts")
# Components that cannot train without a frozen tokenizer (they predict its codes).
NEEDS_VQVAE = frozenset(name for name, spec in COMPONENTS.items() if spec.reads_vqvae == "required")


class UnknownComponent(ValueError):
    """A component name that is not in the table; the message lists the valid ones."""


def spec_of(name: object) -> ComponentSpec:
    """The spec of a component by name, or UnknownComponent naming the valid ones."""
    if name not in COMPONENTS:
        raise UnknownComponent(f"component {name!r} is not one of {', '.join(COMPONENTS)}")
    return COMPONENTS[name]


__all__ = ["ACTOR", "COMPONENTS", "ComponentTable", "NEEDS_VQVAE", "PREDICTOR", "TOKENIZER", "ComponentSpec", "UnknownComponent", "spec_of"]
