"""A component's model configuration and window from a run's `model_config`, without torch.

    r = resolve("fast_loop", spec, {"d_model": 64}, vq_cfg=None)   # -> Resolved(cfg, window, ...)

The configuration of each model is the defaults of its config dataclass (hope_models/components/
<name>/config.py), the dims the dataset's feature spec fixes, and the request's overrides: any config
field, plus "window": {"duration_s", "k", "horizons_s"}. An unknown key, a value of the wrong type,
a dim that does not fit the spec or a configuration its model would refuse is a ValueError naming
it. components/build.build_component builds the model from the result; the webapp, the daemon and the
training loop resolve the same configuration before any model exists, to refuse a bad request at
the door and to estimate its memory (estimate.estimate_from_config) before a model is built.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hope_models.checkpoint_format import CONFIG_FILE, CheckpointError, read_json_object
from hope_models.components import TOKENIZER, spec_of
from hope_models.components.config_fields import MAX_TUPLE, make_config, refuse_unknown
from hope_models.components.vqvae.config import VQVAEConfig
from hope_models.data.features import FeatureSpec
from hope_models.data.windows import WindowSpec, window_spec
from hope_models.numbers import short

WINDOW_KEYS = ("duration_s", "k", "horizons_s")


@dataclass(frozen=True)
class Resolved:
    """What a component will be built from."""
    name: str
    cfg: Any  # its spec's config_class, validated
    window: WindowSpec
    vq_cfg: VQVAEConfig | None = None  # the frozen VQ-VAE a fast_loop / mid_loop reads codes from

    @property
    def wants_frames(self) -> bool:
        vq = self.cfg if self.name == TOKENIZER else self.vq_cfg
        return vq is not None and vq.input == "frame"


def check_keys(name: str, model_config: Any) -> None:
    """The checks that need no dataset: an object, known keys, a window object with known keys."""
    spec = spec_of(name)
    if not isinstance(model_config, dict):
        raise ValueError(f"model_config must be an object (dict), got {type(model_config).__name__}")
    refuse_unknown(name, set(model_config) - {"window"}, {f.name for f in dataclasses.fields(spec.config_class)})
    over = model_config.get("window")
    if over is not None:
        if not isinstance(over, dict):
            raise ValueError(f"model_config.window must be an object with {', '.join(WINDOW_KEYS)}; got {short(over)}")
        unknown = sorted(str(k) for k in set(over) - set(WINDOW_KEYS) - {"scale"})
        if unknown:
            raise ValueError(f"model_config.window: unknown key(s) {short(unknown)}; valid: {', '.join(WINDOW_KEYS)}")


def window_for(name: str, over: dict | None) -> WindowSpec:
    """The component's window: its default, with the overrides of model_config.window (its keys
    already checked by check_keys)."""
    component = spec_of(name)
    scale, kwargs = component.window_scale, dict(component.window_defaults)
    if over is not None:
        over = dict(over)
        if over.pop("scale", scale) != scale:
            raise ValueError(f"model_config.window.scale must be {scale!r} for {name}")
        horizons = over.get("horizons_s", ())
        if (not isinstance(horizons, (list, tuple)) or len(horizons) > MAX_TUPLE
                or any(isinstance(h, bool) or not isinstance(h, (int, float)) for h in horizons)):
            raise ValueError(f"model_config.window.horizons_s={short(horizons)} must be a list of at most "
                             f"{MAX_TUPLE} numbers of seconds")
        kwargs.update(over)
    spec = window_spec(scale, kwargs.get("duration_s"), kwargs.get("k"), kwargs.get("horizons_s", ()))
    component.check_window(spec)
    return spec


def resolve(name: str, spec: FeatureSpec, model_config: dict | None, vq_cfg: VQVAEConfig | None = None) -> Resolved:
    """The configuration `name` gets for a dataset with this feature spec (see the module doc);
    `vq_cfg` is the frozen VQ-VAE's (read by a component whose spec's reads_vqvae is "optional" or
    "required"; ignored for one that reads none)."""
    check_keys(name, {} if model_config is None else model_config)
    component = spec_of(name)
    if spec.act_dim == 0 and not component.tokenizer:
        raise ValueError(f"{name} learns from actions, and this dataset has none (its feature spec's action group "
                         f"is empty: no numeric action field); only the {TOKENIZER} trains on it")
    overrides = dict(model_config or {})
    window = window_for(name, overrides.pop("window", None))
    if not component.reads_codes:
        vq_cfg = None
    elif component.reads_vqvae == "required" and vq_cfg is None:
        raise ValueError(f"{name} needs vqvae_dir: the checkpoint dir (model.safetensors + config.json) of a "
                         f"trained VQ-VAE whose codes it predicts; train the {TOKENIZER} component first")
    return Resolved(name, component.configure(spec, window, overrides, vq_cfg), window, vq_cfg)


def vqvae_config_of(obj: Any, where: str) -> VQVAEConfig:
    """The VQVAEConfig a vqvae checkpoint's config.json (already parsed) describes."""
    if not isinstance(obj, dict) or obj.get("component") != TOKENIZER or not isinstance(obj.get("model_config"), dict):
        raise ValueError(f"{where}: not the config.json of a {TOKENIZER} checkpoint")
    return make_config(VQVAEConfig, {}, obj["model_config"], TOKENIZER)


def read_vqvae_config(ckpt_dir: str | Path) -> VQVAEConfig:
    """The VQVAEConfig of a vqvae checkpoint dir, from its config.json alone (no weights, no torch)."""
    path = Path(ckpt_dir) / CONFIG_FILE
    try:
        obj = read_json_object(path)  # untrusted: a FIFO, a huge or deeply nested file is refused
    except FileNotFoundError:
        raise ValueError(f"{path}: missing (not a checkpoint dir)") from None
    except (CheckpointError, OSError) as exc:
        raise ValueError(str(exc) if isinstance(exc, CheckpointError) else f"{path}: {exc}") from None
    return vqvae_config_of(obj, str(path))


__all__ = ["Resolved", "check_keys", "read_vqvae_config", "resolve", "vqvae_config_of", "window_for"]
