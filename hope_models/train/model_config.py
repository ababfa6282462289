"""A component's model configuration and window from a run's `model_config`, without torch.

    r = resolve("fast_loop", spec, {"d_model": 64}, vq_cfg=None)   # -> Resolved(cfg, window, ...)

The configuration of each model is the defaults of its config dataclass (hope_models/models/
configs.py), the dims the dataset's feature spec fixes, and the request's overrides: any config
field, plus "window": {"duration_s", "k", "horizons_s"}. An unknown key, a value of the wrong type,
a dim that does not fit the spec or a configuration its model would refuse is a ValueError naming
it. components.build_component builds the model from the result; the webapp, the daemon and the
training loop resolve the same configuration before any model exists, to refuse a bad request at
the door and to estimate its memory (estimate.estimate_from_config) before a model is built.
"""
from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hope_models.data.features import FeatureSpec
from hope_models.data.windows import WindowSpec, window_spec
from hope_models.models.configs import FastLoopConfig, MidLoopConfig, VQVAEConfig
from hope_models.numbers import short
from hope_models.train.contract import COMPONENTS

# component -> (window scale, default window_spec kwargs)
DEFAULT_WINDOWS: dict[str, tuple[str, dict[str, Any]]] = {
    "vqvae": ("fast", {"k": 1}),  # one point: the anchor's own frame / observation
    "fast_loop": ("fast", {}),  # 100 ms, K=5
    "mid_loop": ("mid", {"horizons_s": (0.5, 1.0)}),  # 2 s, K=20 (100 ms grid): 5 and 10 grid steps ahead
}
CONFIG_CLASSES = {"vqvae": VQVAEConfig, "fast_loop": FastLoopConfig, "mid_loop": MidLoopConfig}
WINDOW_KEYS = ("duration_s", "k", "horizons_s")
# Far beyond any model that fits a Pi; it keeps the estimate's arithmetic in floats.
MAX_INT = 2**31 - 1
MAX_TUPLE = 64



@dataclass(frozen=True)
class Resolved:
    """What a component will be built from."""
    name: str
    cfg: Any  # VQVAEConfig | FastLoopConfig | MidLoopConfig, validated
    window: WindowSpec
    vq_cfg: VQVAEConfig | None = None  # the frozen VQ-VAE a fast_loop / mid_loop reads codes from

    @property
    def wants_frames(self) -> bool:
        vq = self.cfg if self.name == "vqvae" else self.vq_cfg
        return vq is not None and vq.input == "frame"


def check_keys(name: str, model_config: Any) -> None:
    """The checks that need no dataset: an object, known keys, a window object with known keys."""
    if name not in COMPONENTS:
        raise ValueError(f"component {name!r} is not one of {', '.join(COMPONENTS)}")
    if not isinstance(model_config, dict):
        raise ValueError(f"model_config must be an object (dict), got {type(model_config).__name__}")
    _refuse_unknown(name, set(model_config) - {"window"}, {f.name for f in dataclasses.fields(CONFIG_CLASSES[name])})
    over = model_config.get("window")
    if over is not None:
        if not isinstance(over, dict):
            raise ValueError(f"model_config.window must be an object with {', '.join(WINDOW_KEYS)}; got {short(over)}")
        unknown = sorted(str(k) for k in set(over) - set(WINDOW_KEYS) - {"scale"})
        if unknown:
            raise ValueError(f"model_config.window: unknown key(s) {short(unknown)}; valid: {', '.join(WINDOW_KEYS)}")


def _refuse_unknown(component: str, keys: set, names: set[str]) -> None:
    unknown = sorted(str(k) for k in keys - names)
    if unknown:
        raise ValueError(f"model_config for {component}: unknown key(s) {short(unknown)}; valid keys: "
                         f"{sorted(names) + ['window']}")


def make_config(cls, derived: dict[str, Any], overrides: dict[str, Any], component: str):
    """cls(**defaults | derived | overrides), validated; overriding a derived dim with another value is refused."""
    names = {f.name: f for f in dataclasses.fields(cls)}
    _refuse_unknown(component, set(overrides), set(names))
    values = dict(derived)
    for key, value in overrides.items():
        default = names[key].default
        if isinstance(default, tuple):
            if not isinstance(value, (list, tuple)) or len(value) > MAX_TUPLE:
                raise ValueError(f"model_config.{key}={short(value)} must be a list of at most {MAX_TUPLE} values")
            if any(isinstance(v, bool) or not isinstance(v, int) or abs(v) > MAX_INT for v in value):
                raise ValueError(f"model_config.{key}={short(value)} must be a list of integers")
            value = tuple(value)
        elif isinstance(default, bool) or isinstance(value, bool):
            raise ValueError(f"model_config.{key}={short(value)} has the wrong type")
        elif isinstance(default, int) and not isinstance(value, int):
            raise ValueError(f"model_config.{key}={short(value)} must be an integer")
        elif isinstance(default, int) and abs(value) > MAX_INT:
            raise ValueError(f"model_config.{key}={short(value)} is out of range (at most {MAX_INT})")
        elif isinstance(default, float) and not (isinstance(value, (int, float)) and math.isfinite(value)):
            raise ValueError(f"model_config.{key}={short(value)} must be a finite number")
        elif isinstance(default, str) and not isinstance(value, str):
            raise ValueError(f"model_config.{key}={short(value)} must be a string")
        if key in derived and value != derived[key]:
            raise ValueError(f"model_config.{key}={short(value)} does not fit: the {component} for this data needs "
                             f"{key}={derived[key]!r}")
        values[key] = float(value) if isinstance(default, float) else value
    cfg = cls(**values)
    cfg.validate()
    return cfg


def window_for(name: str, over: dict | None) -> WindowSpec:
    """The component's window: its default, with the overrides of model_config.window (its keys
    already checked by check_keys)."""
    scale, kwargs = DEFAULT_WINDOWS[name]
    kwargs = dict(kwargs)
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
    if name == "vqvae" and (spec.k != 1 or spec.horizons_s):
        raise ValueError("model_config.window: the vqvae reads one frame (k=1, no horizons)")
    if name == "fast_loop" and spec.horizons_s:
        raise ValueError("model_config.window.horizons_s: the fast_loop predicts the current action, not horizons")
    if name == "mid_loop" and not spec.horizons_s:
        raise ValueError("model_config.window.horizons_s: the mid_loop needs at least one horizon")
    return spec


def horizon_steps(spec: WindowSpec) -> tuple[int, ...]:
    steps = []
    for h in spec.horizons_s:
        s = h / spec.grid_step_s
        if abs(s - round(s)) > 1e-6 or round(s) < 1:
            raise ValueError(f"horizons_s: {h} s is not a whole number of the mid window's {spec.grid_step_s:g} s "
                             "grid steps (choose duration_s/k so that it is)")
        steps.append(int(round(s)))
    return tuple(steps)


def resolve(name: str, spec: FeatureSpec, model_config: dict | None, vq_cfg: VQVAEConfig | None = None) -> Resolved:
    """The configuration `name` gets for a dataset with this feature spec (see the module doc);
    `vq_cfg` is the frozen VQ-VAE's (fast_loop: optional, mid_loop: required; vqvae: ignored)."""
    check_keys(name, {} if model_config is None else model_config)
    overrides = dict(model_config or {})
    window = window_for(name, overrides.pop("window", None))
    if name == "vqvae":
        frame = spec.frame
        derived: dict[str, Any] = {"obs_dim": spec.obs_dim}
        want = overrides.get("input", "frame" if frame is not None else "vector")
        if want == "frame":
            if frame is None:
                raise ValueError("model_config.input='frame' but the feature spec has no frame feature")
            derived["frame_shape"] = tuple(frame.shape)
        return Resolved(name, make_config(VQVAEConfig, {"input": want, **derived}, overrides, name), window)
    if name == "fast_loop":
        # window_k follows the window: the policy is window-exact over the K points it is trained on
        cfg = make_config(FastLoopConfig, {"obs_dim": spec.obs_dim, "act_dim": spec.act_dim, "window_k": window.k,
                                           "n_codes": 0 if vq_cfg is None else vq_cfg.n_codes}, overrides, name)
        return Resolved(name, cfg, window, vq_cfg)
    if vq_cfg is None:
        raise ValueError("mid_loop needs vqvae_dir: the checkpoint dir (model.safetensors + config.json) of a "
                         "trained VQ-VAE whose codes it predicts; train the vqvae component first")
    cfg = make_config(MidLoopConfig, {"act_dim": spec.act_dim, "n_codes": vq_cfg.n_codes,
                                      "horizon_steps": horizon_steps(window)}, overrides, name)
    return Resolved(name, cfg, window, vq_cfg)


def vqvae_config_of(obj: Any, where: str) -> VQVAEConfig:
    """The VQVAEConfig a vqvae checkpoint's config.json (already parsed) describes."""
    if not isinstance(obj, dict) or obj.get("component") != "vqvae" or not isinstance(obj.get("model_config"), dict):
        raise ValueError(f"{where}: not the config.json of a vqvae checkpoint")
    return make_config(VQVAEConfig, {}, obj["model_config"], "vqvae")


def read_vqvae_config(ckpt_dir: str | Path) -> VQVAEConfig:
    """The VQVAEConfig of a vqvae checkpoint dir, from its config.json alone (no weights, no torch)."""
    from hope_models.checkpoint_format import CONFIG_FILE, CheckpointError, read_json_object

    path = Path(ckpt_dir) / CONFIG_FILE
    try:
        obj = read_json_object(path)  # untrusted: a FIFO, a huge or deeply nested file is refused
    except FileNotFoundError:
        raise ValueError(f"{path}: missing (not a checkpoint dir)") from None
    except (CheckpointError, OSError) as exc:
        raise ValueError(str(exc) if isinstance(exc, CheckpointError) else f"{path}: {exc}") from None
    return vqvae_config_of(obj, str(path))


__all__ = ["CONFIG_CLASSES", "DEFAULT_WINDOWS", "Resolved", "check_keys", "horizon_steps", "make_config",
           "read_vqvae_config", "resolve", "short", "vqvae_config_of", "window_for"]
