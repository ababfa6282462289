"""Initial parameter values a model computes while it is built, skipped on the meta device.

components/build.py first builds a checkpoint's described model on the meta device (it allocates
nothing) to compare its shapes with the weights file. Arithmetic on meta tensors runs in torch's
Python meta kernels, and the first of them imports torch's compiler (torch._dynamo: ~1.5 s and
~70 MB in each process that loads a checkpoint). Only shapes matter on the meta device, so the
arithmetic is skipped there; on a real device the values come from the same operations and the
same random draws as before.
"""
from __future__ import annotations

from typing import Callable

import torch
from torch import nn


def on_meta() -> bool:
    """Whether tensors made now land on the meta device (a `with torch.device("meta")` block)."""
    return torch.empty(0).is_meta


def initial(shape: tuple[int, ...], value: Callable[[], torch.Tensor]) -> torch.Tensor:
    """value(), or an empty tensor of its shape on the meta device."""
    return torch.empty(shape) if on_meta() else value()


def embedding(rows: int, dim: int) -> nn.Embedding:
    """nn.Embedding(rows, dim) with its N(0, 1) rows: torch.randn draws what its reset_parameters does."""
    return nn.Embedding(rows, dim, _weight=initial((rows, dim), lambda: torch.randn(rows, dim)))


__all__ = ["embedding", "initial", "on_meta"]
