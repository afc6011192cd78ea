"""Adam, the optimiser of every fit, training stage and refinement, without ``torch.optim``.

``torch.optim``'s first ``step()`` imports ``torch._dynamo`` (its compile-time hooks), about 2 s on two
cores, paid by every ``delta`` process that optimises anything, one process per workflow job. This is
the same algorithm through the same fused kernel (``torch.optim.Adam(fused=True)`` without weight decay,
AMSGrad or maximisation: its results are matched bit for bit in the tests; the unfused ``foreach`` update
differs from it in the last bits), and the same ``state_dict`` layout, so a checkpoint written by either
resumes in the other.

The fused kernel reads a parameter, its gradient and both moments once and writes them once, where the
``foreach`` update makes about ten passes: on a dense colour grid of 17.6 M values, 11 ms a step against
64 ms on two cores.

Parameter groups are dicts as ``torch.optim``'s: ``params`` and ``lr``, any other key (a ``name``) kept;
a group's ``lr`` may be changed between steps. A parameter without a gradient is skipped, as there.
"""

from __future__ import annotations

from typing import Iterable, Union

import torch

ParamsOrGroups = Union[Iterable[torch.Tensor], Iterable[dict]]
#: The rest of a ``torch.optim.Adam`` group's settings, as this update has them (its state loads there).
TORCH_GROUP = {"weight_decay": 0.0, "amsgrad": False, "maximize": False, "foreach": None, "capturable": False,
               "differentiable": False, "fused": True, "decoupled_weight_decay": False}  # fmt: skip


class Adam:
    """Adam (Kingma & Ba) with bias correction: ``torch.optim.Adam(params, lr, betas, eps)``'s update."""

    def __init__(self, params: ParamsOrGroups, lr: float = 1e-3, betas: tuple[float, float] = (0.9, 0.999),
                 eps: float = 1e-8):  # fmt: skip
        items = list(params)
        if not items:
            raise ValueError("Adam: no parameters to optimise")
        groups = items if isinstance(items[0], dict) else [{"params": items}]
        self.defaults = {"lr": lr, "betas": tuple(betas), "eps": eps}
        self.param_groups: list[dict] = []
        for g in groups:
            group = {**self.defaults, **g, "params": list(g["params"])}
            if any(not p.is_leaf for p in group["params"]):
                raise ValueError("Adam: can only optimise leaf tensors")
            self.param_groups.append(group)
        self.state: dict[torch.Tensor, dict] = {}

    def zero_grad(self, set_to_none: bool = True) -> None:
        for group in self.param_groups:
            for p in group["params"]:
                if p.grad is None:
                    continue
                if set_to_none:
                    p.grad = None
                else:
                    p.grad.detach_().zero_()

    @torch.no_grad()
    def step(self) -> None:
        """One update of every parameter that has a gradient: a group's tensors of one device and dtype in one
        call of ``torch._fused_adam_`` (the kernel of ``torch.optim.Adam(fused=True)``)."""
        for group in self.param_groups:
            beta1, beta2 = group["betas"]
            params = [p for p in group["params"] if p.grad is not None]
            batches: dict[tuple, list[torch.Tensor]] = {}
            for p in params:
                batches.setdefault((p.device, p.dtype), []).append(p)
            for batch in batches.values():
                states = [self.state.get(p) or self._new_state(p) for p in batch]
                steps = [s["step"] for s in states]
                torch._foreach_add_(steps, 1)
                torch._fused_adam_(batch, [p.grad for p in batch], [s["exp_avg"] for s in states],
                                   [s["exp_avg_sq"] for s in states], [], steps, lr=group["lr"], beta1=beta1,
                                   beta2=beta2, weight_decay=0.0, eps=group["eps"], amsgrad=False,
                                   maximize=False)  # fmt: skip

    def _new_state(self, p: torch.Tensor) -> dict:
        state = self.state[p] = {
            "step": torch.tensor(0.0, device=p.device),  # on the parameter's device, as the fused kernel reads it
            "exp_avg": torch.zeros_like(p, memory_format=torch.preserve_format),
            "exp_avg_sq": torch.zeros_like(p, memory_format=torch.preserve_format),
        }
        return state

    def state_dict(self) -> dict:
        """``torch.optim``'s layout: parameters numbered in group order, state keyed by those numbers."""
        index: dict[int, int] = {}
        groups = []
        for group in self.param_groups:
            ids = [index.setdefault(id(p), len(index)) for p in group["params"]]
            groups.append({**TORCH_GROUP, **{k: v for k, v in group.items() if k != "params"}, "params": ids})
        state = {index[id(p)]: dict(s) for p, s in self.state.items()}
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, state_dict: dict) -> None:
        """Takes a state of this optimiser or of ``torch.optim.Adam`` over the same groups of parameters."""
        saved = state_dict["param_groups"]
        if len(saved) != len(self.param_groups) or any(
            len(s["params"]) != len(g["params"]) for s, g in zip(saved, self.param_groups)
        ):
            raise ValueError("Adam: the saved state has other groups of parameters than this optimiser")
        for s in saved:
            other = {k: s[k] for k in TORCH_GROUP if k in s and s[k] and k not in ("foreach", "fused")}
            if other:
                raise ValueError(f"Adam: the saved state was stepped with {other}, which this update does not do")
        params = {}
        for s, g in zip(saved, self.param_groups):
            params.update(zip(s["params"], g["params"]))
            g.update({k: v for k, v in s.items() if k in ("lr", "betas", "eps")})
            g["betas"] = tuple(g["betas"])
        self.state = {}
        for key, s in state_dict["state"].items():
            p = params[int(key)]
            self.state[p] = {
                "step": torch.as_tensor(s["step"], dtype=torch.float32).to(p.device).clone(),
                "exp_avg": s["exp_avg"].to(device=p.device, dtype=p.dtype).clone(),
                "exp_avg_sq": s["exp_avg_sq"].to(device=p.device, dtype=p.dtype).clone(),
            }
