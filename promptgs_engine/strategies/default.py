"""The 3DGS and AbsGS baselines, through gsplat's pure-torch ``DefaultStrategy``.

gsplat 1.5.3 decides the opacity reset with ``step % self.reset_every == 0 & step > 0``.
``&`` binds tighter than the comparisons, so this reads as the chain
``step % reset_every == 0 > 0``, which is never true: opacity is never reset.
`ResettingDefaultStrategy` performs the reset the 3DGS paper describes. The reset
(``gsplat.strategy.ops.reset_opa``) clamps opacities to a ceiling, so applying it again
is harmless should a later gsplat fix the expression.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch
from gsplat.strategy import DefaultStrategy
from gsplat.strategy.ops import reset_opa

STRATEGY_NAMES = ("3dgs", "absgs", "promptgs")

# Step counts of the 3DGS paper's schedule for a 30k-step run.
_REFERENCE_ITERATIONS = 30_000


@dataclass
class DefaultSchedule:
    """Densification schedule scaled to the run length (3DGS values at 30k steps)."""

    refine_start_iter: int
    refine_stop_iter: int
    refine_every: int
    reset_every: int
    sh_degree_interval: int

    @classmethod
    def for_iterations(cls, iterations: int) -> "DefaultSchedule":
        s = min(1.0, iterations / _REFERENCE_ITERATIONS)
        return cls(
            refine_start_iter=max(1, round(500 * s)),
            refine_stop_iter=max(2, round(15_000 * s)),
            refine_every=max(10, round(100 * s)),
            reset_every=max(100, round(3000 * s)),
            sh_degree_interval=max(50, round(1000 * s)),
        )


@dataclass
class ResettingDefaultStrategy(DefaultStrategy):
    """gsplat's DefaultStrategy with the periodic opacity reset actually applied."""

    def step_post_backward(
        self,
        params: torch.nn.ParameterDict,
        optimizers: dict[str, torch.optim.Optimizer],
        state: dict[str, Any],
        step: int,
        info: dict[str, Any],
        packed: bool = False,
    ) -> None:
        super().step_post_backward(params, optimizers, state, step, info, packed=packed)
        if 0 < step < self.refine_stop_iter and step % self.reset_every == 0:
            reset_opa(params=params, optimizers=optimizers, state=state, value=self.prune_opa * 2.0)


def make_default_strategy(name: str, schedule: DefaultSchedule, verbose: bool = False) -> ResettingDefaultStrategy:
    """`3dgs`: view-space gradient threshold 2e-4; `absgs`: absolute gradients, 8e-4."""
    if name not in ("3dgs", "absgs"):
        raise ValueError(f"unknown default strategy {name!r}")
    absgrad = name == "absgs"
    return ResettingDefaultStrategy(
        grow_grad2d=0.0008 if absgrad else 0.0002,
        absgrad=absgrad,
        refine_start_iter=schedule.refine_start_iter,
        refine_stop_iter=schedule.refine_stop_iter,
        refine_every=schedule.refine_every,
        reset_every=schedule.reset_every,
        verbose=verbose,
    )
