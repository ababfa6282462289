"""A model as a list of layers with parameters of their own, described without torch.

Each component's layers.py derives its model's layers from a configuration alone: kind, name (the
module's path in the model, so `<name>.<param>` is its state_dict key), parameter shapes. Two
readers share that one description: the memory estimate (train/estimate.py), and the NumPy forms'
checks of a checkpoint's tensors (`tensors()`: name -> shape). tests/test_train_estimate.py holds
it equal to what a built torch module has (estimate.model_layers), for every component. The
builders below are the layer kinds the components are made of.
"""
from __future__ import annotations

from dataclasses import dataclass, replace


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
    name: str = ""  # the module's path in the model; a repeated layer's holds "{i}", its index
    # How often it runs per sample, for the activations (a torch module states it with the
    # attributes estimate_per_point / estimate_per_sample): per_point times at every window point
    # (a layer that reads each cell of a grid: G), or per_sample times whatever the window (a
    # decoder run only where targets are scored); per_sample 0: per_point times K.
    per_point: int = 1
    per_sample: int = 0


# The parameters of each kind, in the order `params` lists their shapes (torch's registration order).
PARAM_NAMES = {"Linear": ("weight", "bias"), "LayerNorm": ("weight", "bias"), "Embedding": ("weight",),
               "WindowSSM": ("log_rate", "B", "C", "D"), "DiagonalSSM": ("log_rate", "B", "C", "D"),
               "Conv2d": ("weight", "bias"), "ConvTranspose2d": ("weight", "bias"),
               "AddBackground": ("image",), "JointView": ("pivot",), "KeypointRender": ("background", "strength")}


def expand(layers: list[Layer]) -> list[Layer]:
    """One layer per repeat, each with its own name (the "{i}" filled in), repeat 1."""
    return [replace(layer, repeat=1, name=layer.name.format(i=i)) for layer in layers for i in range(layer.repeat)]


def tensors(layers: list[Layer]) -> dict[str, tuple[int, ...]]:
    """state_dict key -> shape of every parameter the layers hold."""
    out: dict[str, tuple[int, ...]] = {}
    for layer in expand(layers):
        for param, shape in zip(PARAM_NAMES[layer.kind], layer.params, strict=True):
            out[f"{layer.name}.{param}"] = tuple(shape)
    return out


def linear(n_in: int, n_out: int, trainable: bool, name: str = "") -> Layer:
    return Layer("Linear", ((n_out, n_in), (n_out,)), trainable, name=name)


def embedding(n: int, d: int, trainable: bool, name: str = "") -> Layer:
    return Layer("Embedding", ((n, d),), trainable, name=name)


def layer_norm(d: int, trainable: bool, name: str = "") -> Layer:
    return Layer("LayerNorm", ((d,), (d,)), trainable, name=name)


def gated_mlp(d: int, hidden: int, trainable: bool, name: str = "") -> list[Layer]:
    return [linear(d, hidden, trainable, f"{name}.w_gate"), linear(d, hidden, trainable, f"{name}.w_up"),
            linear(hidden, d, trainable, f"{name}.w_out")]


def ssm(kind: str, d: int, n: int, trainable: bool, name: str = "") -> Layer:
    return Layer(kind, ((n,), (n, d), (d, n), (d,)), trainable, name=name)  # log_rate, B, C, D


def conv(kind: str, c_in: int, c_out: int, trainable: bool, name: str = "", kernel: int = 4, stride: int = 2,
         padding: int = 1) -> Layer:
    """A square conv; the default is the frame models' 4x4 stride-2 (halving or doubling) one."""
    k = kernel
    weight = (c_in, c_out, k, k) if kind.startswith("ConvTranspose") else (c_out, c_in, k, k)
    return Layer(kind, (weight, (c_out,)), trainable, (c_in, c_out, k, stride, padding, 1, 0), name=name)
