"""A model as a list of layers with parameters of their own, described without torch.

Each component's layers.py derives its model's layers from a configuration alone; the memory
estimate (train/estimate.py) reads the same description off a built torch module
(estimate.model_layers) or from a configuration, and tests/test_train_estimate.py holds the two
equal for every component. The builders below are the layer kinds the components are made of.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Layer:
    """A module with parameters of its own, as the estimate sees it: what model_layers() reads off a
    torch module and config_layers() derives from a configuration alone (they must agree: tested)."""
    kind: str  # the module's class name (Linear, Embedding, LayerNorm, Conv2d, ..., WindowSSM)
    params: tuple[tuple[int, ...], ...]  # the shapes of its own parameters
    trainable: bool
    conv: tuple[int, int, int, int, int | str, int, int] | None = None
    #      (in_channels, out_channels, kernel, stride, padding, dilation, output_padding) of a conv
    repeat: int = 1  # the same layer this many times (a stack's blocks): counted, not listed


def linear(n_in: int, n_out: int, trainable: bool) -> Layer:
    return Layer("Linear", ((n_out, n_in), (n_out,)), trainable)


def layer_norm(d: int, trainable: bool) -> Layer:
    return Layer("LayerNorm", ((d,), (d,)), trainable)


def gated_mlp(d: int, hidden: int, trainable: bool) -> list[Layer]:
    return [linear(d, hidden, trainable), linear(d, hidden, trainable), linear(hidden, d, trainable)]


def ssm(kind: str, d: int, n: int, trainable: bool) -> Layer:
    return Layer(kind, ((n,), (n, d), (d, n), (d,)), trainable)  # log_rate, B, C, D


def conv(kind: str, c_in: int, c_out: int, trainable: bool) -> Layer:
    weight = (c_in, c_out, 4, 4) if kind.startswith("ConvTranspose") else (c_out, c_in, 4, 4)
    return Layer(kind, (weight, (c_out,)), trainable, (c_in, c_out, 4, 2, 1, 1, 0))
