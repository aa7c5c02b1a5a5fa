"""Adam's step for the trainer's six one-parameter optimisers, without `Optimizer.step`'s
per-call Python work.

`torch.optim.Adam(fused=True).step()` spends about 0.1 ms of Python (hooks, grouping by
device and dtype, argument checks) around a kernel that takes a few microseconds on a
small model; with one optimiser per parameter that is most of Adam's cost at 200×150
(`benchmarks/train_profile.py` shows it). `fused_adam_step` calls the same fused kernel on the
same state (``exp_avg``, ``exp_avg_sq``, ``step``), so results are bit-identical to
``opt.step()`` and checkpoints, gsplat's state surgery and the learning-rate schedulers are
unchanged. Optimisers it does not cover (not fused, AMSGrad, weight decay, several
parameters a group) take the ordinary ``step()``.
"""

from __future__ import annotations

import torch


def _direct(opt: torch.optim.Optimizer) -> bool:
    if not isinstance(opt, torch.optim.Adam) or len(opt.param_groups) != 1:
        return False
    g = opt.param_groups[0]
    return (
        len(g["params"]) == 1 and bool(g.get("fused")) and not g["amsgrad"] and not g["maximize"]
        and g["weight_decay"] == 0 and not g.get("decoupled_weight_decay", False) and not g["capturable"]
        and not g["differentiable"] and not isinstance(g["lr"], torch.Tensor)
    )


@torch.no_grad()
def fused_adam_step(optimizers: dict[str, torch.optim.Optimizer]) -> None:
    """One Adam step of every optimiser, then its gradients set to None (``zero_grad``)."""
    for opt in optimizers.values():
        if not _direct(opt):
            opt.step()
            opt.zero_grad(set_to_none=True)
            continue
        group = opt.param_groups[0]
        p = group["params"][0]
        if p.grad is None:
            continue
        state = opt.state[p]
        if not state:  # as Adam._init_group lays it out
            state["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
            state["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            state["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
        beta1, beta2 = group["betas"]
        state["step"].add_(1)
        torch._fused_adam_(
            [p], [p.grad], [state["exp_avg"]], [state["exp_avg_sq"]], [], [state["step"]],
            amsgrad=False, lr=group["lr"], beta1=beta1, beta2=beta2, weight_decay=0.0, eps=group["eps"],
            maximize=False, grad_scale=None, found_inf=None,
        )
        p.grad = None
        opt._opt_called = True  # what the LR schedulers check for a step before theirs
