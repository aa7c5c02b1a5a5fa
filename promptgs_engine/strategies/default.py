"""The 3DGS and AbsGS baselines, through gsplat's pure-torch ``DefaultStrategy``.

gsplat 1.5.3 decides the opacity reset with ``step % self.reset_every == 0 & step > 0``.
``&`` binds tighter than the comparisons, so this reads as the chain
``step % reset_every == 0 > 0``, which is never true: opacity is never reset.
`ResettingDefaultStrategy` performs the reset the 3DGS paper describes. The reset
(``gsplat.strategy.ops.reset_opa``) clamps opacities to a ceiling, so applying it again
is harmless should a later gsplat fix the expression.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from gsplat.strategy import DefaultStrategy
from gsplat.strategy.ops import duplicate, remove, reset_opa, split

from ..threads import one_thread

STRATEGY_NAMES = ("3dgs", "absgs", "promptgs")
# Flag in the info of a batched step whose statistics are in the state already (batch.py).
STATISTICS_MERGED = "statistics_merged"
# Entries of a step's info that its statistics make once and share (`step_visible`,
# `step_grad2d_norms`).
STEP_VISIBLE = "step_visible"
STEP_GRAD2D_NORMS = "step_grad2d_norms"

# Strategy state of the far background shell (sky.py), set by the trainer: BACKGROUND is
# 1.0 for the shell's Gaussians (carried through growth and pruning like every per-Gaussian
# state), BACKGROUND_RADIUS the shell's radius.
BACKGROUND = "background"
BACKGROUND_RADIUS = "background_radius"

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
        """Start, stop, reset and SH steps scale with the run; the refinement interval
        does not go below ``iterations / 20`` (capped at 100), so a short run gets a few
        growth rounds on settled gradients rather than dozens on noisy ones (scaling it
        down to 10 steps as gsplat's ``steps_scaler`` would multiplies the Gaussian count
        tenfold on a 600-step run)."""
        s = min(1.0, iterations / _REFERENCE_ITERATIONS)
        return cls(
            refine_start_iter=max(1, round(500 * s)),
            refine_stop_iter=max(2, round(15_000 * s)),
            refine_every=max(10, round(100 * s), min(100, iterations // 20)),
            reset_every=max(100, round(3000 * s)),
            sh_degree_interval=max(50, round(1000 * s)),
        )

    def densification_step(self, fraction: float) -> int:
        """The step ``fraction`` (0 to 1) of the way through the densification window,
        rounded down."""
        return self.refine_start_iter + int(fraction * (self.refine_stop_iter - self.refine_start_iter))

    def stretched(self, factor: float) -> "DefaultSchedule":
        """The schedule over a run ``factor`` (≥ 1) times as many steps long: start and
        stop times ``factor`` (rounded), intervals times ``factor`` rounded up, so the run
        has as many growth rounds, opacity resets and SH increases, and no more."""
        if factor < 1:
            raise ValueError(f"a schedule is stretched by a factor of at least 1, not {factor}")
        return DefaultSchedule(
            refine_start_iter=round(self.refine_start_iter * factor),
            refine_stop_iter=round(self.refine_stop_iter * factor),
            refine_every=math.ceil(self.refine_every * factor),
            reset_every=math.ceil(self.reset_every * factor),
            sh_degree_interval=math.ceil(self.sh_degree_interval * factor),
        )


@dataclass
class ResettingDefaultStrategy(DefaultStrategy):
    """gsplat's DefaultStrategy with the periodic opacity reset actually applied, and an
    optional Gaussian budget: when more Gaussians qualify for growth than the budget has
    room for, the ones with the highest `growth_priority` grow.

    With ``auto_budget`` the budget is found during the run. Just before each opacity
    reset the ``loss_probe`` (a fixed set of training views rendered without gradients)
    is read, and the growth of the cycle since the previous reset is judged by its
    elasticity: relative loss reduction per relative Gaussian increase (0.1: 10% more
    Gaussians for 1% lower loss). Below ``auto_budget_elasticity`` growth stops at the
    current count; pruned Gaussians may be replaced up to it. Whole reset cycles are
    compared because both ends are then equally far from a reset, which raises the loss
    for most of a cycle in short runs; a run with fewer than two resets in its
    densification window (under about 600 steps) is never capped.
    """

    budget: int | None = None
    auto_budget: bool = False
    # The ledger (``state["ledger"]``, in train.json as "growth"): how many Gaussians each
    # refinement grew and pruned. PromptGS keeps a finer one of its own.
    keeps_default_ledger: ClassVar[bool] = True
    auto_budget_elasticity: float = 0.1
    loss_probe: Any = None  # callable() -> float, needed by auto_budget

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
            if self.auto_budget:
                self._judge_reset_cycle(params, state, step)
            reset_opa(params=params, optimizers=optimizers, state=state, value=self.prune_opa * 2.0)

    @one_thread()  # small element-wise work: faster without waking a thread (threads.py)
    def _update_state(self, params, state, info, packed: bool = False) -> None:
        if info.get(STATISTICS_MERGED):  # a batched step added its views' statistics (batch.py)
            return
        self.add_statistics(params, state, info, packed=packed)

    def add_statistics(self, params, state, info, packed: bool = False, only: torch.Tensor | None = None) -> None:
        """Add a step's growth statistics (``grad2d``, ``count``) to the Gaussians in
        ``only`` (bool [N]; None: every one): `accumulate_grad2d` for unpacked renders
        without the 2D-scale statistics, else gsplat's own, with the statistics of the
        Gaussians outside ``only`` put back as they were."""
        if not packed and self.refine_scale2d_stop_iter == 0:
            accumulate_grad2d(state, info, self.key_for_gradient, self.absgrad, params["means"].shape[0], only=only)
            return
        saved = None
        if only is not None and state.get("grad2d") is not None:
            saved = state["grad2d"].clone(), state["count"].clone()
        super()._update_state(params, state, info, packed=packed)
        if saved is not None:
            for key, before in zip(("grad2d", "count"), saved):  # no masked read: no wait on a GPU
                state[key].copy_(torch.where(only, state[key], before))

    # -- growth -----------------------------------------------------------------------

    def growth_candidates(self, params, state, grads: torch.Tensor, step: int) -> torch.Tensor:
        """Gaussians that qualify for growth: mean view-space gradient above threshold."""
        return grads > self.grow_grad2d

    def growth_priority(self, params, state, grads: torch.Tensor) -> torch.Tensor:
        """Order in which candidates grow when the budget is short (higher first)."""
        return grads

    # -- budget -----------------------------------------------------------------------

    def effective_budget(self, state: dict[str, Any]) -> int | None:
        """The cap on the Gaussian count now: the fixed budget, the automatic one once it
        has stopped growth, the smaller of both, or None."""
        frozen = (state.get("auto_budget") or {}).get("frozen_at")
        caps = [b for b in (self.budget, frozen) if b is not None]
        return min(caps) if caps else None

    def _judge_reset_cycle(self, params, state, step: int) -> None:
        """Judge the growth of the reset cycle that ends now (just before the reset)."""
        ab = state.setdefault("auto_budget", {"frozen_at": None, "last_reset": None, "history": []})
        if ab["frozen_at"] is not None or self.loss_probe is None:
            return
        loss = float(self.loss_probe())
        n = int(params["means"].shape[0])
        prev = ab["last_reset"]
        if prev is not None and n > prev["n"]:
            gain = (prev["loss"] - loss) / max(prev["loss"], 1e-12)
            elasticity = gain / ((n - prev["n"]) / max(prev["n"], 1))
            ab["history"].append({"step": step, "n": n, "loss": loss, "elasticity": elasticity})
            if elasticity < self.auto_budget_elasticity:
                ab["frozen_at"] = n
        ab["last_reset"] = {"step": step, "loss": loss, "n": n}

    def prune_mask(self, params, state, step: int) -> torch.Tensor:
        """bool [N]: gsplat's pruning rule (faint Gaussians; after the first reset, those
        too big in the world or, while ``refine_scale2d_stop_iter`` lasts, on screen), with
        the far background measured by `too_big`."""
        is_prune = torch.sigmoid(params["opacities"].flatten()) < self.prune_opa
        if step > self.reset_every:
            is_too_big = too_big(params, state, self.prune_scale3d)
            if step < self.refine_scale2d_stop_iter:
                is_too_big |= state["radii"] > self.prune_scale2d
            is_prune = is_prune | is_too_big
        return is_prune

    @torch.no_grad()
    def _prune_gs(self, params, optimizers, state, step) -> int:
        is_prune = self.prune_mask(params, state, step)
        n_prune = int(is_prune.sum())
        if n_prune > 0:
            remove(params=params, optimizers=optimizers, state=state, mask=is_prune)
        if self.keeps_default_ledger:
            state.setdefault("ledger", new_default_ledger())["pruned"] += n_prune
        return n_prune

    def _grow_gs(self, params, optimizers, state, step) -> tuple[int, int]:
        grads = state["grad2d"] / state["count"].clamp_min(1)
        grow = self.growth_candidates(params, state, grads, step)
        budget = self.effective_budget(state)
        if budget is not None:
            room = max(budget - params["means"].shape[0], 0)
            if int(grow.sum()) > room:
                priority = self.growth_priority(params, state, grads).masked_fill(~grow, float("-inf"))
                keep = torch.zeros_like(grow)
                if room > 0:
                    keep[priority.topk(room).indices] = True
                grow = grow & keep
        if self.keeps_default_ledger:
            ledger = state.setdefault("ledger", new_default_ledger())
            ledger["grown"] += int(grow.sum())
            ledger["refinements"].append({"step": int(step), "n": int(params["means"].shape[0]), "grown": int(grow.sum())})
        return grow_selected(params, optimizers, state, grow, self.grow_scale3d, self.revised_opacity)


def too_big(params, state: dict[str, Any], prune_scale3d: float) -> torch.Tensor:
    """bool [N]: Gaussians too big in the world to keep, 3DGS's rule: largest scale over
    ``prune_scale3d`` × the scene scale.

    The far background shell (`sky.py`, ``state["background"]``) lies at twice the scene's
    reach, and its Gaussians start as wide as its point spacing, which can be over that
    limit from the first step: 3DGS's rule would remove every one not yet split when
    pruning by size begins, and the novel views' sky would show the black render
    background through the holes. They are held to the same limit as an angle instead,
    ``prune_scale3d`` × the shell's radius."""
    size = torch.exp(params["scales"]).max(dim=-1).values
    big = size > prune_scale3d * state["scene_scale"]
    background = state.get(BACKGROUND)
    if background is not None and background.shape[0] == size.shape[0]:
        big = torch.where(background > 0, size > prune_scale3d * float(state[BACKGROUND_RADIUS]), big)
    return big


def pixel_gradient_scale(info: dict[str, Any], grads: torch.Tensor) -> torch.Tensor:
    """[2]: what a ``means2d`` gradient is multiplied by before its norm is taken, as
    gsplat's statistics do (half the image size, times the cameras of the step)."""
    c = info["n_cameras"]
    return torch.tensor([info["width"] / 2.0 * c, info["height"] / 2.0 * c], dtype=grads.dtype, device=grads.device)


def step_visible(info: dict[str, Any]) -> torch.Tensor:
    """[C, N] bool: the Gaussians each view of the step rendered (both radii > 0). Made once
    a step and kept in ``info``, which every statistic of the step reads it from."""
    visible = info.get(STEP_VISIBLE)
    if visible is None:
        visible = info[STEP_VISIBLE] = (info["radii"] > 0).all(dim=-1)
    return visible


def step_grad2d_norms(info: dict[str, Any], key: str, absgrad: bool) -> torch.Tensor:
    """[C, N]: the norms of the step's view-space gradients of ``info[key]`` (``absgrad``: its
    absolute ones) times `pixel_gradient_scale`, made once a step and kept in ``info``."""
    name = f"{STEP_GRAD2D_NORMS}:{key}:{int(absgrad)}"
    norms = info.get(name)
    if norms is None:
        grads = info[key].absgrad if absgrad else info[key].grad  # [C, N, 2]
        norms = info[name] = (grads * pixel_gradient_scale(info, grads)).norm(dim=-1)
    return norms


def accumulate_grad2d(
    state: dict[str, Any], info: dict[str, Any], key: str, absgrad: bool, n: int, only: torch.Tensor | None = None
) -> None:
    """Add a step's view-space gradient norms and visibility counts to ``state["grad2d"]``
    and ``state["count"]``, as gsplat's ``DefaultStrategy._update_state`` does for unpacked
    renders without the 2D-scale statistics, with the same sums in the same order (bitwise
    equal), but masked adds over all Gaussians in place of gathers, nonzero and index_add_:
    half the torch calls, none of them sized by a count of visible Gaussians. ``only`` (bool
    [N]): the Gaussians that take this step's statistics; the others keep theirs."""
    norms = step_grad2d_norms(info, key, absgrad)  # [C, N]
    visible = step_visible(info)  # [C, N]
    if only is not None:
        visible = visible & only
    for key_ in ("grad2d", "count"):
        if state[key_] is None:
            state[key_] = torch.zeros(n, device=norms.device)
    for cam in range(visible.shape[0]):
        state["grad2d"].add_(torch.where(visible[cam], norms[cam], 0.0))
        state["count"].add_(visible[cam])


def new_default_ledger() -> dict[str, Any]:
    return {"grown": 0, "pruned": 0, "refinements": []}


def grow_selected(params, optimizers, state, grow: torch.Tensor, grow_scale3d: float, revised_opacity: bool = False) -> tuple[int, int]:
    """Grow the selected Gaussians as 3DGS does: clone the small ones, split the large.

    Each grown Gaussian adds exactly one to the count (a clone adds a copy; a split
    replaces one by two).
    """
    is_small = torch.exp(params["scales"]).max(dim=-1).values <= grow_scale3d * state["scene_scale"]
    is_dupli = grow & is_small
    is_split = grow & ~is_small
    n_dupli, n_split = int(is_dupli.sum()), int(is_split.sum())
    if n_dupli > 0:
        duplicate(params=params, optimizers=optimizers, state=state, mask=is_dupli)
    if n_split > 0:
        is_split = torch.cat([is_split, torch.zeros(n_dupli, dtype=torch.bool, device=is_split.device)])
        split(params=params, optimizers=optimizers, state=state, mask=is_split, revised_opacity=revised_opacity)
    return n_dupli, n_split


def make_default_strategy(
    name: str, schedule: DefaultSchedule, budget: int | None = None, verbose: bool = False, auto_budget: bool = False
) -> ResettingDefaultStrategy:
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
        budget=budget,
        auto_budget=auto_budget,
        verbose=verbose,
    )
