"""Pre-flight memory estimate: refuse a configuration that cannot fit the job's budget before it
starts, with the estimate in the message.

The estimate of a training process's peak RSS is a sum of parts (MB = 2^20 bytes):

  params       4 B x every parameter (float32), frozen ones included (a frozen VQ-VAE inside
               fast_loop / mid_loop)
  gradients    4 B x every trainable parameter
  optimizer    8 B x every trainable parameter (AdamW's two moments)
  activations  ACT_FACTOR x 4 B x batch_size x activation floats per sample, where a sample's
               floats are the sum over the model's leaf modules of what each one outputs for it:
                 Linear  out_features per token          Embedding  embedding_dim per token
                 Norm    its width per token             Conv1d/2d, ConvTranspose2d  out_channels
                         x output H x W per frame, the spatial size followed through the convs in
                         the order they are registered, from FRAME_HW (64) at an RGB input conv
                 any other module with its own parameters (the SSM layer): the sum of each own
                         parameter's widest axis per token (the diagonal SSM's log_rate [N],
                         B [N, d], C [d, N], D [d]: its state, input, output and skip vectors)
               tokens per sample = window_k (the window's grid points; + horizons for the frozen
               encoder of future frames), or what the layer states (Layer.per_point x window_k,
               e.g. once per cell of a grid, or a fixed Layer.per_sample, e.g. a decoder run
               only where targets are scored). Trainable modules keep their outputs for backward; a
               frozen module (no trainable parameter) runs without grad, so only its largest
               single output counts (x FROZEN_FACTOR, the tensor and the next one being made).
               A model may override all this with a method
               activation_floats_per_sample(window_k) -> float.
  batch        the window arrays: the loader builds loader_chunk batches at once (8 in the loop), each
               obs/act float32 and, for a component that reads images, uint8 frames; plus the batch
               in use converted for the model (obs/act x2, frames as float32 x4)
  runtime      RUNTIME_MB: measured RSS of a process that imported torch, numpy and this project
               and ran a first training step (torch loads its CPU kernels lazily then); a
               component on frames adds CONV_RUNTIME_MB for the convolution kernels
  cache        the data cache's resident budget (DEFAULT_RESIDENT_BUDGET_MB, 64 MB: mapped step
               arrays count as RSS)

ACT_FACTOR and RUNTIME_MB were calibrated here (x86-64, torch 2.13 CPU) by measuring the peak RSS
delta of real forward/backward steps (tests/test_train_estimate.py re-checks the fit, within
0.5x-2x); on the Pi's aarch64 torch the runtime differs by some tens of MB, well inside the
soft limit's 10% margin of a 3 GiB budget.

Two ways in, one formula: estimate_memory() reads the layers off a built torch module (any model,
e.g. a test's stand-in), estimate_from_config() derives the same layers from a configuration
(model_config.resolve) with no model and no torch. The training loop runs the latter before it
builds anything, and the webapp and the daemon run it on a request (registry/run_request.py): a model
too big for the budget is refused before it can take the memory it would be refused for.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from hope_models.components import spec_of
from hope_models.components.layers import Layer
from hope_models.train.guards import validate_budget_mb

MB = 1024 * 1024
FLOAT_BYTES = 4
ADAMW_STATES = 2
ACT_FACTOR = 3.0  # peak activation memory / sum of layer outputs (saved for backward + grad buffers)
FROZEN_FACTOR = 2.0
# import torch (~200 MB) + the first step's lazily loaded kernels + project, measured at ~236 MB; torch's
# compiler (~70 MB more) stays unloaded in a job (tests/test_compiler_unloaded.py)
RUNTIME_MB = 250.0
CONV_RUNTIME_MB = 20.0  # the conv kernels a frame model loads on its first step
LOADER_CHUNK = 8  # batches the loop's WindowLoader builds per call
FRAME_HW = 64
FRAME_BYTES = FRAME_HW * FRAME_HW * 3


class MemoryBudgetError(RuntimeError):
    """A configuration's estimated memory exceeds the job's budget; the message gives the estimate."""


@dataclass(frozen=True)
class MemoryEstimate:
    component: str
    total_mb: float
    breakdown: dict[str, float]  # MB per part: params, gradients, optimizer, activations, batch, runtime, cache
    batch_size: int
    window_k: int
    details: dict[str, Any] = field(default_factory=dict)  # parameter counts, activation floats per sample

    def describe(self) -> str:
        parts = ", ".join(f"{name} {mb:.1f}" if mb < 10 else f"{name} {mb:.0f}"
                          for name, mb in self.breakdown.items())
        return f"estimated {self.total_mb:.0f} MB ({parts} MB)"

    def to_json_obj(self) -> dict[str, Any]:
        return {"component": self.component, "total_mb": round(self.total_mb, 1),
                "breakdown": {k: round(v, 2) for k, v in self.breakdown.items()},
                "batch_size": self.batch_size, "window_k": self.window_k, "details": self.details}


CONVS = ("Conv1d", "Conv2d", "ConvTranspose1d", "ConvTranspose2d")


def model_layers(model: Any) -> list[Layer]:
    """The layers of a torch module, in registration order (the order the convs see the image)."""
    out = []
    for path, m in model.named_modules():
        own = list(m.parameters(recurse=False))
        if not own:
            continue
        name = type(m).__name__
        conv = None
        if name in CONVS:
            padding = m.padding if isinstance(m.padding, str) else m.padding[0]
            conv = (m.in_channels, m.out_channels, m.kernel_size[0], m.stride[0], padding, m.dilation[0],
                    m.output_padding[0])
        out.append(Layer(name, tuple(tuple(p.shape) for p in own), any(p.requires_grad for p in own), conv,
                         name=path, per_point=int(getattr(m, "estimate_per_point", 1)),
                         per_sample=int(getattr(m, "estimate_per_sample", 0))))
    return out


def _conv_out(h: float, kind: str, conv: tuple) -> float:
    """Output height of a (square) conv given the input height, from the module's settings."""
    _, _, k, s, p, d, output_padding = conv
    if isinstance(p, str):  # "same" keeps the size at stride 1, "valid" pads nothing
        p = (d * (k - 1)) // 2 if p == "same" else 0
    if kind.startswith("ConvTranspose"):
        return (h - 1) * s - 2 * p + d * (k - 1) + output_padding + 1
    return math.floor((h + 2 * p - d * (k - 1) - 1) / s + 1)


def _leaf_outputs(layers: list[Layer]) -> list[tuple[float, float, bool, int]]:
    """(floats per token, floats per frame, trainable, repeat) of every layer."""
    out = []
    h: float = FRAME_HW
    for layer in layers:
        kind, own = layer.kind, layer.params
        if layer.conv is not None:
            if kind.endswith("2d") and layer.conv[0] == 3 and not kind.startswith("ConvTranspose"):
                h = FRAME_HW  # an RGB input conv starts a new image path (an encoder)
            h = max(1.0, _conv_out(h, kind, layer.conv))
            spatial = h * h if kind.endswith("2d") else h
            per = (0.0, layer.conv[1] * spatial)
        elif kind == "Linear":
            per = (float(own[0][0]), 0.0)  # weight [out, in]
        elif kind == "Embedding":
            per = (float(own[0][1]), 0.0)  # weight [num, dim]
        elif "Norm" in kind:
            per = (float(math.prod(own[0])), 0.0)
        else:  # e.g. the SSM layer's own decay/B/C/D: each yields about one vector of its widest axis
            per = (float(sum(max(shape, default=1) for shape in own)), 0.0)
        out.append((*per, layer.trainable, layer.repeat))
    return out


def activation_floats_per_sample(layers: list[Layer], window_k: int, frames: bool,
                                 horizons: int = 0) -> tuple[float, float]:
    """(kept for backward, frozen transient peak) floats per sample; see the module doc."""
    frames_per_sample = window_k if frames else 0
    kept = 0.0
    frozen_peak = 0.0
    for layer, (per_token, per_frame, trainable, repeat) in zip(layers, _leaf_outputs(layers), strict=True):
        if trainable:
            tokens = layer.per_sample or layer.per_point * window_k
            kept += repeat * (per_token * tokens + per_frame * max(1, frames_per_sample))
        else:
            tokens = window_k + horizons
            frozen_peak = max(frozen_peak, per_token * tokens + per_frame * max(1, frames_per_sample + horizons))
    return kept, frozen_peak


def cache_resident_mb(cache: Any) -> float:
    """What an open DatasetCache's mapped rows can add to RSS (nothing for rows read with pread),
    capped at the cache's resident budget: the `cache` part of an estimate."""
    from hope_models.data.cache import DEFAULT_RESIDENT_BUDGET_MB  # lazy: loads mcap, numpy
    return min(cache.resident_bytes, DEFAULT_RESIDENT_BUDGET_MB * MB) / MB


def estimate_memory(component_name: str, model: Any, batch_size: int, window_k: int, obs_dim: int,
                    act_dim: int, frames: bool, *, horizons: int = 0, cache_mb: float | None = None,
                    runtime_mb: float | None = None, loader_chunk: int = LOADER_CHUNK) -> MemoryEstimate:
    """Estimated peak RSS of training a built `model` (a torch module) with this batch and window."""
    custom = getattr(model, "activation_floats_per_sample", None)
    return _estimate(component_name, model_layers(model), batch_size, window_k, obs_dim, act_dim, frames,
                     horizons=horizons, cache_mb=cache_mb, runtime_mb=runtime_mb, loader_chunk=loader_chunk,
                     custom_kept=float(custom(window_k)) if callable(custom) else None)


def estimate_from_config(resolved: Any, batch_size: int, obs_dim: int, act_dim: int, *,
                         cache_mb: float | None = None, runtime_mb: float | None = None,
                         loader_chunk: int = LOADER_CHUNK) -> MemoryEstimate:
    """The same estimate from a model_config.Resolved, before (or without) building the model:
    no torch, so the webapp, the daemon and the CLI refuse what cannot fit at the door."""
    win = resolved.window
    return _estimate(resolved.name, config_layers(resolved), batch_size, win.k, obs_dim, act_dim,
                     resolved.wants_frames, horizons=len(win.horizons_s), cache_mb=cache_mb, runtime_mb=runtime_mb,
                     loader_chunk=loader_chunk)


def checkpoint_mb_from_config(resolved: Any, obs_dim: int, act_dim: int) -> float:
    """What a checkpoint of the model `resolved` describes takes on disk, in MB: its weights (all
    of them, frozen ones too) and AdamW's moments of the trainable ones (the JSON files are small)."""
    est = estimate_from_config(resolved, 1, obs_dim, act_dim, cache_mb=0.0, runtime_mb=0.0)
    return est.breakdown["params"] + est.breakdown["optimizer"]


def _estimate(component_name: str, layers: list[Layer], batch_size: int, window_k: int, obs_dim: int,
              act_dim: int, frames: bool, *, horizons: int, cache_mb: float | None, runtime_mb: float | None,
              loader_chunk: int, custom_kept: float | None = None) -> MemoryEstimate:
    for name, value in (("batch_size", batch_size), ("window_k", window_k)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} = {value!r} must be a positive integer")
    if cache_mb is None:
        from hope_models.data.cache import DEFAULT_RESIDENT_BUDGET_MB  # lazy: loads mcap, numpy
        cache_mb = float(DEFAULT_RESIDENT_BUDGET_MB)
    n_params = sum(layer.repeat * math.prod(shape) for layer in layers for shape in layer.params)
    n_train = sum(layer.repeat * math.prod(shape) for layer in layers if layer.trainable for shape in layer.params)
    if custom_kept is not None:
        kept, frozen = custom_kept, 0.0
    else:
        kept, frozen = activation_floats_per_sample(layers, window_k, frames, horizons)
    act_bytes = FLOAT_BYTES * batch_size * (ACT_FACTOR * kept + FROZEN_FACTOR * frozen)
    if runtime_mb is None:
        runtime_mb = RUNTIME_MB + (CONV_RUNTIME_MB if frames else 0.0)
    vec = batch_size * window_k * (obs_dim + act_dim) * FLOAT_BYTES
    img = batch_size * (window_k + horizons) * FRAME_BYTES if frames else 0
    batch_bytes = max(1, loader_chunk) * (vec + img) + 2 * vec + FLOAT_BYTES * img
    breakdown = {
        "params": n_params * FLOAT_BYTES / MB,
        "gradients": n_train * FLOAT_BYTES / MB,
        "optimizer": n_train * FLOAT_BYTES * ADAMW_STATES / MB,
        "activations": act_bytes / MB,
        "batch": batch_bytes / MB,
        "runtime": float(runtime_mb),
        "cache": float(cache_mb),
    }
    details = {"parameters": n_params, "trainable_parameters": n_train,
               "activation_floats_per_sample": kept, "frozen_floats_per_sample": frozen,
               "act_factor": ACT_FACTOR, "horizons": horizons, "frames": bool(frames), "loader_chunk": loader_chunk}
    return MemoryEstimate(component_name, sum(breakdown.values()), breakdown, batch_size, window_k, details)


def config_layers(resolved: Any) -> list[Layer]:
    """The layers of the model a components.resolve.Resolved describes, from its component's layers.py."""
    return spec_of(resolved.name).layers(resolved.cfg, resolved.vq_cfg)


def check_fits(estimate: MemoryEstimate, budget_mb: float, soft_fraction: float = 0.9) -> MemoryEstimate:
    """Raise MemoryBudgetError if the estimate exceeds the memory guard's soft limit
    (soft_fraction x budget: where a running job would pause), else return the estimate."""
    budget = validate_budget_mb(budget_mb)
    limit = budget * soft_fraction
    if estimate.total_mb <= limit:
        return estimate
    biggest = max((k for k in ("activations", "batch", "optimizer", "params")),
                  key=lambda k: estimate.breakdown[k])
    hint = (f"lower --batch-size (now {estimate.batch_size}) or use a smaller model (model_config)"
            if biggest in ("activations", "batch") else "use a smaller model (model_config)")
    raise MemoryBudgetError(
        f"{estimate.component}: {estimate.describe()} exceeds the budget of {budget:.0f} MB "
        f"(the memory guard pauses training at {soft_fraction:.0%} of it, {limit:.0f} MB); "
        f"{hint}, or raise the budget with --memory-budget-mb / HOPE_MEMORY_BUDGET_MB")
