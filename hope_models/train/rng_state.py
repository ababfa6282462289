"""The global RNG state of torch, numpy and python, as a checkpoint holds it: tensors for the
safetensors file, plain numbers for training_state.json. A resumed job restores it so its next
random draw is the one an uninterrupted job would have made."""
from __future__ import annotations

import random
from typing import Any


def capture() -> tuple[dict[str, Any], dict[str, Any]]:
    """(tensors, json) of the current global RNG state."""
    import numpy as np  # lazy: loads numpy
    import torch  # lazy: loads torch

    np_name, np_keys, np_pos, np_has_gauss, np_gauss = np.random.get_state()
    tensors = {"rng.torch": torch.get_rng_state(),
               "rng.numpy_keys": torch.from_numpy(np.ascontiguousarray(np_keys).view(np.int32).copy())}
    py_version, py_internal, py_gauss = random.getstate()
    state = {"numpy": {"name": np_name, "pos": int(np_pos), "has_gauss": int(np_has_gauss),
                       "cached_gaussian": float(np_gauss)},
             "python": {"version": py_version, "internal": list(py_internal), "gauss_next": py_gauss}}
    return tensors, state


def restore(tensors: dict[str, Any], state: dict[str, Any]) -> None:
    """Set the global RNG state from capture()'s output (read back from a checkpoint, so any
    wrong shape raises; the caller names the checkpoint)."""
    import numpy as np  # lazy: loads numpy
    import torch  # lazy: loads torch

    torch.set_rng_state(tensors["rng.torch"])
    keys = tensors["rng.numpy_keys"].numpy().view(np.uint32)
    n = state["numpy"]
    np.random.set_state((n["name"], keys, n["pos"], n["has_gauss"], n["cached_gaussian"]))
    p = state["python"]
    random.setstate((p["version"], tuple(p["internal"]), p["gauss_next"]))
