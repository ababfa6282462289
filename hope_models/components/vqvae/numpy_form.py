"""The VQ-VAE in NumPy: encode (vectors and camera frames), decode and decode_expected (vectors), and the promoted vqvae's runtime.

    vq = VQVAENumpy(tensors, groups=2, n_codes=16)          # prefix "vqvae." inside a fast/mid loop
    vq.codes(obs_n)              # normalised obs [..., obs_dim] -> group-local codes [..., G]
    VQVAENumpy(tensors, ..., frame=cfg).codes(frames)        # uint8 [..., H, W, 3] -> [..., G]
    vq.decode(codes)             # codes [..., G] -> reconstruction [..., obs_dim] (normalised)
    vq.decode_expected(probs)    # per-group code probabilities [..., G, n_codes] -> [..., obs_dim]

    model = VQVAERuntime.from_checkpoint(ckpt, expected_sha256=..., verify_manifest=True)
    model.codes_of(raw_observation)                          # what BrainService answers as `code`
    model.vq.codes(frame)                                    # a frame VQ-VAE: uint8 [H, W, 3] -> [G]

The arithmetic is hope_models/components/vqvae/model.py for input "vector" (tests/test_brain_whole.py checks
it equal to torch within 1e-5, codes exactly): encoder = Linear-SiLU-Linear-SiLU-Linear then a
LayerNorm without parameters; z cut into G slices, each the nearest row of its own codebook (rows
g * n_codes .. of the one [G * n_codes, code_dim / G] table; ties: the lowest index); decoder =
Linear-SiLU-Linear-SiLU-Linear of the G rows side by side, and decode_expected feeds it each
group's probability-weighted row. A frame VQ-VAE (input "frame", layout "flat" or "grid") encodes
uint8 camera frames with numpy_frame.FrameEncoder (its convs channels-last) and takes the nearest
row the same way, a grid's codebook shared by its cells (tests/test_frame_numpy.py: codes equal to
VQVAE.encode); its decoder (pictures) is not served. FastLoopNumpy and MidLoopNumpy hold one of
these for their frozen VQ-VAE (the Mid Loop: vector ones only, so far).
Torch-free.
"""
from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from hope_models.components.checkpoint_checks import (
    MAX_GROUPS,
    CheckpointRefused,
    check_header,
    check_trained,
    check_weights,
    read_component,
)
from hope_models.components.layers import tensors
from hope_models.components.numpy_layers import Linear, halved, layer_norm, silu_of_half
from hope_models.components.vqvae.config import VQVAEConfig
from hope_models.components.vqvae.layers import vqvae_layers
from hope_models.components.vqvae.numpy_frame import FrameEncoder, encoder_layers, frame_config
from hope_models.data.features import FeatureSpec, FeatureSpecError
from hope_models.data.spec_request import spec_from_json_obj

MAX_WIDTH = 1 << 14  # bounds what an untrusted config sizes (the reacher's VQ-VAE is 256 wide)


class VQVAENumpyError(CheckpointRefused):
    """This checkpoint's VQ-VAE cannot be run by the NumPy runtime; the message names the file and why."""


class VQVAENumpy:
    """The arithmetic of a trained vector VQ-VAE (its tensors under `prefix`). Immutable."""

    def __init__(self, tensors: dict[str, np.ndarray], *, groups: int, n_codes: int, prefix: str = "",
                 decoder: bool = True, frame: VQVAEConfig | None = None):
        t = tensors

        def lin(name: str) -> Linear:
            return Linear(np.ascontiguousarray(t[f"{prefix}{name}.weight"].T), t[f"{prefix}{name}.bias"])

        self.groups, self.n_codes = int(groups), int(n_codes)
        book = t[f"{prefix}codebook"]  # [G * n_codes, d]: group g owns rows g * n_codes ..
        self.codebook = np.ascontiguousarray(book.reshape(self.groups, self.n_codes, -1))  # [G, n, d]
        self._book_sq = (self.codebook * self.codebook).sum(-1)  # [G, n]
        self.code_dim = book.shape[1] * self.groups
        # A frame VQ-VAE (numpy_frame.py): its conv encoder; a grid's one codebook is shared by
        # every cell (stored once per cell), so the distances are computed against the first block.
        self.frame = None if frame is None else FrameEncoder(t, frame, prefix)
        self.frame_shape = None if self.frame is None else self.frame.frame_shape
        self.shared = frame is not None and frame.layout == "grid"
        if self.frame is not None:
            self._enc, self._dec = [], None  # the decoder of frames (pictures) is not served
            self.obs_dim = 0
            self.fingerprint = self.frame.fingerprint_with(self.codebook[:1] if self.shared else self.codebook)
            self._book0_t = np.ascontiguousarray(self.codebook[0].T)  # [d, n]
            return
        # the layers before a SiLU halved at load (silu_of_half: the same numbers in fewer ops)
        self._enc = [halved(lin("encoder.0.0")), halved(lin("encoder.0.2")), lin("encoder.0.4")]
        # the decoder is optional: a fast_loop reads codes only (its checkpoint need not carry one)
        self._dec = [halved(lin("decoder.0")), halved(lin("decoder.2")), lin("decoder.4")] if decoder else None
        # -2 c^T per group, [G, d, n]: the cross term of the distances as one batched product (x -2 is exact)
        self._book_m2t = np.ascontiguousarray(np.float32(-2.0) * self.codebook.transpose(0, 2, 1))
        self._mean_code = np.full(self.code_dim, 1.0 / self.code_dim, np.float32)
        self.obs_dim = self._enc[0].w_t.shape[0]

    def same_encoder(self, other: "VQVAENumpy") -> bool:
        """Whether `other` gives the same codes of every vector: the same encoder and codebook, array by array."""
        if self.frame is not None or other.frame is not None or (self.groups, self.n_codes) != (other.groups, other.n_codes):
            return False
        return (len(self._enc) == len(other._enc) and np.array_equal(self.codebook, other.codebook)
                and all(np.array_equal(a.w_t, b.w_t) and np.array_equal(a.b, b.b)
                        for a, b in zip(self._enc, other._enc, strict=True)))

    def encode(self, obs_n: np.ndarray) -> np.ndarray:
        """Normalised obs [..., obs_dim] -> z_e [..., code_dim] (after the parameter-free LayerNorm)."""
        return layer_norm(_mlp(self._enc, obs_n), self._mean_code)

    def codes(self, x: np.ndarray) -> np.ndarray:
        """Normalised obs [..., obs_dim] (a frame VQ-VAE: uint8 frames [..., H, W, 3]) -> the nearest
        row of each group's codebook, group-local [..., G] (ties: the lowest index, as torch)."""
        if self.frame is not None:
            zg = self.frame.encode(x)  # [..., G, d]
            if self.shared:  # VQVAE.nearest's shared branch: one [G, d] x [d, n] product
                d = (zg * zg).sum(-1, keepdims=True) - np.float32(2.0) * zg.dot(self._book0_t) + self._book_sq[0]
                return d.argmin(-1)
            zg = zg[..., None, :]  # [..., G, 1, d]
            d = (zg * zg).sum(-1) - np.float32(2.0) * (zg * self.codebook).sum(-1) + self._book_sq  # [..., G, n]
            return d.argmin(-1)
        z = self.encode(x)
        zg = z.reshape(*z.shape[:-1], self.groups, 1, -1)  # [..., G, 1, d]
        # |z|^2 - 2 z.c + |c|^2 as VQVAE.nearest, the cross term one batched product [G, 1, d] @ [G, d, n]
        d = np.matmul(zg, self._book_m2t)[..., 0, :]  # [..., G, n]
        d += (zg * zg).sum(-1)
        d += self._book_sq
        return d.argmin(-1)

    def _decode_z(self, z: np.ndarray) -> np.ndarray:
        if self._dec is None:
            raise ValueError("this VQ-VAE was loaded without its decoder (a frame VQ-VAE's is not in the NumPy form)")
        return _mlp(self._dec, z)

    def decode(self, codes: np.ndarray) -> np.ndarray:
        """Group-local codes [..., G] -> the reconstruction [..., obs_dim] (normalised units)."""
        rows = self.codebook[np.arange(self.groups), np.asarray(codes)]  # [..., G, d]
        return self._decode_z(rows.reshape(*rows.shape[:-2], self.code_dim))

    def decode_expected(self, probs: np.ndarray) -> np.ndarray:
        """Per-group code probabilities [..., G, n_codes] -> the decoder at the expected z_q [..., obs_dim]."""
        p = np.asarray(probs, dtype=np.float32)
        zq = np.matmul(p[..., None, :], self.codebook)[..., 0, :]  # [..., G, d]: each group's probability-weighted row
        return self._decode_z(zq.reshape(*zq.shape[:-2], self.code_dim))


def _mlp(layers: list[Linear], z: np.ndarray) -> np.ndarray:
    """Linear-SiLU-Linear-SiLU-Linear, the first two halved at load (numpy_layers.silu_of_half)."""
    for layer in layers[:-1]:
        z = silu_of_half(layer(z))
    return layers[-1](z)


class Normaliser:
    """A feature spec's statistics as the dataset cache applies them: float32 x * 1/std - mean/std."""

    def __init__(self, spec: FeatureSpec):
        obs_mean, obs_std, act_mean, act_std = spec.normalizer()
        self.obs_inv_std = (1.0 / obs_std).astype(np.float32)
        self.obs_shift = (obs_mean * self.obs_inv_std).astype(np.float32)
        self.obs_mean, self.obs_std = obs_mean.astype(np.float64), obs_std.astype(np.float64)
        self.act_inv_std = (1.0 / act_std).astype(np.float32)
        self.act_shift = (act_mean * self.act_inv_std).astype(np.float32)

    def obs(self, x: np.ndarray) -> np.ndarray:
        x32 = np.asarray(x, dtype=np.float32) * self.obs_inv_std
        x32 -= self.obs_shift
        return x32

    def act(self, a: np.ndarray) -> np.ndarray:
        a32 = np.asarray(a, dtype=np.float32) * self.act_inv_std
        a32 -= self.act_shift
        return a32

    def raw_obs(self, x_n: np.ndarray) -> np.ndarray:
        """Normalised observation -> raw units (float64), the inverse of obs()."""
        return np.asarray(x_n, dtype=np.float64) * self.obs_std + self.obs_mean


def check_vqvae_ref(vq_cfg: Any, obs_dim: int, where: Path, error: type[CheckpointRefused],
                    n_codes: int | None = None, frames: bool = False) -> tuple[int, int]:
    """A VQ-VAE model_config this runtime can run for observations of obs_dim values -> (groups, n_codes).
    frames: a frame VQ-VAE is accepted too (numpy_frame.frame_config checks it; obs_dim is not its input)."""
    if not isinstance(vq_cfg, dict):
        raise error(f"{where}: the VQ-VAE's model_config is missing or not an object")
    if frames and vq_cfg.get("input") == "frame":
        cfg = frame_config(vq_cfg, where, error, MAX_WIDTH)
        if n_codes is not None and cfg.n_codes != n_codes:
            raise error(f"{where}: the VQ-VAE's n_codes ({cfg.n_codes}) does not fit ({n_codes})")
        return cfg.groups, cfg.n_codes
    if vq_cfg.get("input") != "vector":
        raise error(f"{where}: a VQ-VAE with input {vq_cfg.get('input')!r} (camera frames); this part of the "
                    "inference runtime reads codes of observation vectors only")
    groups, n, d = vq_cfg.get("groups", 1), vq_cfg.get("n_codes"), vq_cfg.get("code_dim")
    for key, v, hi in (("groups", groups, MAX_GROUPS), ("n_codes", n, MAX_WIDTH), ("code_dim", d, MAX_WIDTH)):
        if isinstance(v, bool) or not isinstance(v, int) or not 1 <= v <= hi:
            raise error(f"{where}: vqvae model_config.{key}={v!r} must be an integer in 1-{hi}")
    if d % groups:
        raise error(f"{where}: vqvae code_dim={d} is not a multiple of groups={groups}")
    if vq_cfg.get("obs_dim") != obs_dim or (n_codes is not None and n != n_codes):
        raise error(f"{where}: the VQ-VAE's obs_dim/n_codes ({vq_cfg.get('obs_dim')}/{n}) do not fit "
                    f"({obs_dim}/{n_codes if n_codes is not None else n})")
    return groups, n


def check_vqvae_tensors(t: dict[str, np.ndarray], vq_cfg: dict[str, Any], where: Path, prefix: str,
                        error: type[CheckpointRefused], encoder_only: bool = False) -> dict[str, tuple[int, ...]]:
    """The VQ-VAE tensors under prefix: the shapes the NumPy form reads (returned, for the caller's
    misfit check), finite, and a trained codebook. encoder_only: the decoder is not wanted (a
    component that reads codes; a frame VQ-VAE's decoder is not served either way)."""
    g, n, d = vq_cfg.get("groups", 1), vq_cfg["n_codes"], vq_cfg["code_dim"]
    if vq_cfg.get("input") == "frame":  # check_vqvae_ref(frames=True) has checked this config
        layers = (encoder_layers if encoder_only else vqvae_layers)(frame_config(vq_cfg, where, error, MAX_WIDTH),
                                                                    prefix=prefix)
    else:
        w0 = t.get(f"{prefix}encoder.0.0.weight")
        # the width config.json names; one saved before it named it: the file's own
        hidden = vq_cfg.get("hidden") or (w0.shape[0] if w0 is not None and w0.ndim == 2 else -1)
        # the encoder and decoder from the layer description the memory estimate reads (layers.py)
        cfg = VQVAEConfig(input="vector", obs_dim=vq_cfg["obs_dim"], hidden=hidden, code_dim=d, n_codes=n, groups=g)
        layers = [layer for layer in vqvae_layers(cfg, prefix=prefix)
                  if not encoder_only or layer.name.startswith(f"{prefix}encoder.")]
    want = tensors(layers)
    want[f"{prefix}codebook"] = (g * n, d // g)
    # the rest of the file (other parts of the model, the EMA buffers) is the caller's to check
    check_weights(t, want, where, "the VQ-VAE's config", error, ignore=[k for k in t if k not in want])
    check_trained(t, prefix, where, "the VQ-VAE", error)
    return want


def frame_of(config: dict[str, Any]) -> VQVAEConfig | None:
    """The VQVAEConfig of a checked VQ-VAE model_config when it reads frames, else None."""
    return frame_config(config, "", CheckpointRefused, MAX_WIDTH) if config.get("input") == "frame" else None


def _check_config(config: Any, where: Path) -> FeatureSpec:
    check_header(config, where, "vqvae", VQVAENumpyError)
    try:
        spec = spec_from_json_obj(config.get("feature_spec"), f"{where}: feature_spec")
    except FeatureSpecError as exc:
        raise VQVAENumpyError(str(exc)) from None
    mc = config.get("model_config")
    check_vqvae_ref(mc, spec.obs_dim, where, VQVAENumpyError, frames=True)
    frame = frame_of(mc)
    if frame is not None and (spec.frame is None or tuple(spec.frame.shape) != frame.frame_shape):
        raise VQVAENumpyError(f"{where}: the VQ-VAE reads {list(frame.frame_shape)} frames, its feature_spec's frame "
                              f"is {None if spec.frame is None else list(spec.frame.shape)}")
    return spec


def _check_tensors(t: dict[str, np.ndarray], config: dict[str, Any], where: Path) -> None:
    want = check_vqvae_tensors(t, config["model_config"], where, "", VQVAENumpyError)
    # buffers of the EMA codebook and its counters are fine; anything else is another model
    extra = [k for k in t if k not in want and k not in ("ema_count", "ema_sum", "unused_steps", "idle_steps",
                                                         "initialized", "restarts")]
    if extra:
        raise VQVAENumpyError(f"{where}: weights the VQ-VAE config.json does not describe: {', '.join(extra[:5])}")


class VQVAERuntime:
    """The promoted vqvae component: raw observation (a frame VQ-VAE: the camera frame) -> its codes.
    Immutable after load."""

    name = "vqvae"

    def status_fields(self) -> dict:
        """What BrainService.status() adds for this component: the shape of its answer."""
        return {"groups": self.groups, "n_codes": self.n_codes, "sha256": self.sha256}

    def __init__(self, *, checkpoint: Path, config: dict[str, Any], spec: FeatureSpec,
                 tensors: dict[str, np.ndarray], sha256: str, version: str):
        self.checkpoint, self.config, self.spec, self.sha256, self.version = checkpoint, config, spec, sha256, version
        mc = config["model_config"]
        self.vq = VQVAENumpy(tensors, groups=int(mc.get("groups", 1)), n_codes=int(mc["n_codes"]),
                             frame=frame_of(mc))
        self.groups, self.n_codes = self.vq.groups, self.vq.n_codes
        self.obs_dim, self.act_dim = spec.obs_dim, spec.act_dim
        self.observation_fields = [(f.path, f.size) for f in spec.observation.fields]
        self.action_fields = [(f.path, f.size) for f in spec.action.fields]
        # a frame VQ-VAE reads the request's camera frame (BrainService: `frame`), not its values
        self.frame_shape = self.vq.frame_shape
        self.frame_vq = self.vq if self.frame_shape is not None else None
        self.fit_fields = (self.observation_fields, self.frame_shape)  # what a replacement must read alike
        self.norm = Normaliser(spec)
        self.vqvae_sha256 = None  # it is the VQ-VAE

    @classmethod
    def from_checkpoint(cls, path: str | Path, *, expected_sha256: str | None = None,
                        verify_manifest: bool = False) -> "VQVAERuntime":
        ck = read_component(path, _check_config, _check_tensors, VQVAENumpyError, expected_sha256=expected_sha256,
                            verify_manifest=verify_manifest)
        return cls(checkpoint=ck.path, config=ck.config, spec=ck.spec, tensors=ck.tensors, sha256=ck.sha256,
                   version=ck.version)

    def codes_of(self, values: np.ndarray) -> np.ndarray:
        """Raw observation [obs_dim] -> group-local codes [G] (a vector VQ-VAE; a frame VQ-VAE's codes
        are vq.codes(frame))."""
        if self.frame_shape is not None:
            raise ValueError(f"{self.version} reads camera frames: its codes are vq.codes(frame)")
        return self.vq.codes(self.norm.obs(values))

    def warm(self) -> None:
        if self.frame_shape is not None:
            self.vq.codes(np.zeros(self.frame_shape, np.uint8))
        else:
            self.codes_of(np.zeros(self.obs_dim))

    def describe_observation(self, limit: int = 12) -> str:
        names = self.spec.observation.dim_names()
        return ", ".join(names[:limit]) + (f", ... ({len(names) - limit} more)" if len(names) > limit else "")

    def __repr__(self) -> str:
        what = f"obs {self.obs_dim}" if self.frame_shape is None else "frame " + "x".join(map(str, self.frame_shape))
        return f"VQVAERuntime({self.version}, {what} -> {self.groups} x {self.n_codes} codes)"


__all__ = ["VQVAENumpy", "VQVAERuntime", "VQVAENumpyError", "Normaliser", "check_vqvae_ref", "check_vqvae_tensors",
           "frame_of", "MAX_WIDTH"]


RUNTIME = VQVAERuntime  # what BrainService serves for this component
