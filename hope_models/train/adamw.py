"""AdamW over torch's functional Adam: torch.optim.AdamW's arithmetic and state_dict without
torch.optim.Optimizer.

    opt = adamw([{"params": decay, "weight_decay": 0.1}, {"params": no_decay, "weight_decay": 0.0}],
                lr=3e-4, betas=(0.9, 0.95), eps=1e-8)
    opt.zero_grad(set_to_none=True); loss.backward(); opt.step()
    state = opt.state_dict()          # the layout torch.optim.AdamW.state_dict() has
    opt.load_state_dict(state)        # also one torch.optim.AdamW wrote (older checkpoints)

Why: torch.optim.Optimizer imports torch's compiler (torch._dynamo, sympy) when its first
parameter group is added, which costs a training job ~1.5 s of CPU and ~75 MB of RSS on this
machine, more on a Pi, for a compiler no job uses. step() calls the function torch.optim.AdamW
calls for CPU tensors (torch.optim.adam.adam, one tensor at a time, decoupled weight decay), so
the weights are bit for bit torch's (tests/test_adamw.py). A torch whose functional Adam has no
decoupled weight decay gets torch.optim.AdamW itself.
"""
from __future__ import annotations

import inspect
from typing import Any, Iterable

import torch
from torch.optim.adam import adam

# What torch.optim.AdamW keeps in each parameter group besides these four and "params".
_GROUP_FLAGS: dict[str, Any] = {"amsgrad": False, "foreach": None, "maximize": False, "capturable": False,
                                "differentiable": False, "fused": None, "decoupled_weight_decay": True}
_HYPER = ("lr", "betas", "eps", "weight_decay")


def adamw(groups: Iterable[dict[str, Any]], *, lr: float, betas: tuple[float, float], eps: float) -> Any:
    """This module's AdamW, or torch.optim.AdamW on a torch without the functional form it calls."""
    groups = list(groups)
    if "decoupled_weight_decay" in inspect.signature(adam).parameters:
        return AdamW(groups, lr=lr, betas=betas, eps=eps)
    return torch.optim.AdamW(groups, lr=lr, betas=betas, eps=eps)


class AdamW:
    def __init__(self, groups: Iterable[dict[str, Any]], *, lr: float, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8, weight_decay: float = 1e-2):
        self.param_groups: list[dict[str, Any]] = []
        for g in groups:
            params = list(g["params"])
            if not params:
                raise ValueError("AdamW: a parameter group without parameters")
            self.param_groups.append({"params": params, "lr": g.get("lr", lr), "betas": tuple(g.get("betas", betas)),
                                      "eps": g.get("eps", eps), "weight_decay": g.get("weight_decay", weight_decay),
                                      **_GROUP_FLAGS})
        self.state: dict[torch.Tensor, dict[str, torch.Tensor]] = {}

    def zero_grad(self, set_to_none: bool = True) -> None:
        for g in self.param_groups:
            for p in g["params"]:
                if p.grad is None:
                    continue
                if set_to_none:
                    p.grad = None
                else:
                    p.grad.detach_().zero_()

    @torch.no_grad()
    def step(self) -> None:
        for g in self.param_groups:
            params = [p for p in g["params"] if p.grad is not None]
            if not params:
                continue
            for p in params:
                if p.grad.is_sparse:
                    raise RuntimeError("AdamW does not take sparse gradients")
                if p not in self.state:  # as torch's optimizer starts a parameter's state
                    self.state[p] = {"step": torch.tensor(0.0, dtype=torch.float32),
                                     "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
                                     "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format)}
            states = [self.state[p] for p in params]
            beta1, beta2 = g["betas"]
            adam(params, [p.grad for p in params], [s["exp_avg"] for s in states], [s["exp_avg_sq"] for s in states],
                 [], [s["step"] for s in states], foreach=False, capturable=False, differentiable=False, fused=None,
                 grad_scale=None, found_inf=None, has_complex=any(torch.is_complex(p) for p in params),
                 decoupled_weight_decay=True, amsgrad=False, beta1=beta1, beta2=beta2, lr=g["lr"],
                 weight_decay=g["weight_decay"], eps=g["eps"], maximize=False)

    # -- torch.optim.Optimizer's state_dict layout: parameters numbered in group order ---------------

    def state_dict(self) -> dict[str, Any]:
        number: dict[torch.Tensor, int] = {}
        groups = []
        for g in self.param_groups:
            for p in g["params"]:
                number.setdefault(p, len(number))
            groups.append({**{k: v for k, v in g.items() if k != "params"}, "params": [number[p] for p in g["params"]]})
        return {"state": {number[p]: dict(st) for p, st in self.state.items()}, "param_groups": groups}

    def load_state_dict(self, state_dict: dict[str, Any]) -> None:
        groups = state_dict["param_groups"]
        if len(groups) != len(self.param_groups):
            raise ValueError(f"optimizer state: {len(groups)} parameter group(s), the model has {len(self.param_groups)}")
        param_of: dict[int, torch.Tensor] = {}
        for saved, mine in zip(groups, self.param_groups, strict=True):
            if len(saved["params"]) != len(mine["params"]):
                raise ValueError(f"optimizer state: a group of {len(saved['params'])} parameter(s), the model's "
                                 f"has {len(mine['params'])}")
            param_of.update(zip((int(n) for n in saved["params"]), mine["params"], strict=True))
        state: dict[torch.Tensor, dict[str, torch.Tensor]] = {}
        for n, st in state_dict["state"].items():
            p = param_of.get(int(n))
            if p is None:
                raise ValueError(f"optimizer state: parameter {n} is in no group")
            # as torch's optimizer loads it: the step a float32 scalar, the moments in the parameter's dtype
            state[p] = {k: v.to(dtype=torch.float32) if k == "step" else v.to(dtype=p.dtype, device=p.device)
                        for k, v in st.items()}
        for saved, mine in zip(groups, self.param_groups, strict=True):
            mine.update({k: tuple(saved[k]) if k == "betas" else saved[k] for k in _HYPER if k in saved})
        self.state = state


__all__ = ["AdamW", "adamw"]
