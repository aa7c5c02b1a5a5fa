"""Compaction (``--compact``): once growth has ended, remove the Gaussians that contribute
least to the training views, and let the rest of the run fine-tune what is left.

What a Gaussian contributes is its blending weight summed over every pixel of every
training view, ``I_g = Σ_views Σ_pixels α_g(p) · T_g(p)`` (``T`` the transmittance in
front of it): Mini-Splatting's importance score (Fang and Wang, ECCV 2024), and
LightGaussian's global significance (Fan et al., NeurIPS 2024) without its volume
factor. It is measured exactly, not estimated: every Gaussian gets a one-channel colour of
1, and the gradient of the rendered channel's sum with respect to that colour is
``Σ_pixels α·T`` (one forward and backward pass per training view at the training
resolution).

The threshold is a percentile, as LightGaussian prunes by a ratio of its ranking: the 40%
least important Gaussians go (``fraction``), so a compacted model holds 0.6× the
Gaussians it grew, unless those 40% carry more than 5% of all the blending weight
(``max_weight``): then only as many go as carry 5%, and a lean model keeps more. On
tumbler (3DGS, seed 0, 1500 steps) the 40% least important carried under 1% of the
weight; on fern, about 3%.

A prompted object can carry little weight in total (a drone covers one pixel in a few
views) and would fall under any global cut. So with prompts (PromptGS), a Gaussian inside
a prompt box is kept whenever it carries any blending weight (over ``protect_pixels``,
0) in some training view: it draws part of what the prompt marks. A drone of two pixels
is often drawn by several faint Gaussians of a tenth of a pixel each: a floor of a
quarter of a pixel protected 89 of the 589 seen Gaussians in the box of the `sparse`
mountain (600 steps, seed 0), the cut took the rest, and recall fell from 0.56 to 0.15.
The boxes hold few Gaussians (878 of 89.6k there), so keeping them all costs little.

The trainer compacts once, at 60% of the run (`compaction_step`): a tenth of the run after
densification stops, so that the Gaussians of the last refinement and the opacities
clamped by the last reset have settled, and the remaining 40%, in which 3DGS only
fine-tunes, fine-tune the compacted model (LightGaussian prunes and then fine-tunes the
same way). On tumbler, removing 1% of the weight right where densification stops cost
0.18 dB; a tenth of the run later, 0.07 dB. A PromptGS run compacts no earlier than its
first full-size whole view (70% of the run under the progressive schedule, on scenes wide
enough for it): at 60% the 64-sample mountain (one box, 1500 steps) was still training at
half size, and the cut cost 0.18 and 0.12 dB at seeds 0 and 1; at full size, 0.10 and
0.03 dB, and the sparse scene's three seeds moved from −0.05 / −0.01 / −0.09 to
0.00 / +0.03 / −0.04 dB (docs/results/economy/README.md, "Compaction at full size").
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import torch
from gsplat.strategy.ops import remove

from .prompts import PromptBox, contains_any

log = logging.getLogger("promptgs.compaction")

REMOVED_FRACTION = 0.4  # of the Gaussians, the least important
MAX_REMOVED_WEIGHT = 0.05  # the share of all blending weight the removed ones may carry at most
PROTECT_PIXELS = 0.0  # inside prompts: a Gaussian with more blending weight than this in some view is kept
COMPACT_AT = 0.6  # of the run (never before densification stops)


@dataclass
class Importance:
    """Per Gaussian: blending weight summed over all views, and its largest in one view."""

    total: torch.Tensor  # [N]
    peak_view: torch.Tensor  # [N]


def blending_weights(
    render_fn: Callable[..., Any], params: torch.nn.ParameterDict, cameras: Sequence[Any], chunk: int = 1
) -> Importance:
    """``Σ_pixels α·T`` of every Gaussian in each of ``cameras``, summed and maximised over
    the cameras. ``render_fn(cameras, colors=..., sh_degree=None)`` renders feature
    colours [N, 1] (the trainer's `render_cameras` with the run's filter)."""
    n = params["means"].shape[0]
    device = params["means"].device
    total = torch.zeros(n, device=device)
    peak = torch.zeros(n, device=device)
    for start in range(0, len(cameras), chunk):
        ones = torch.ones(n, 1, device=device, requires_grad=True)
        out, _, _ = render_fn(list(cameras[start : start + chunk]), colors=ones)
        out[..., 0].sum().backward()
        weight = ones.grad[:, 0].detach()
        total += weight
        peak = torch.maximum(peak, weight)
    return Importance(total=total, peak_view=peak)


def removal_mask(
    importance: Importance,
    protected: torch.Tensor | None = None,
    fraction: float = REMOVED_FRACTION,
    max_weight: float = MAX_REMOVED_WEIGHT,
) -> torch.Tensor:
    """bool [N]: the ``fraction`` least important of the Gaussians (counted over all of
    them, taken among the unprotected), fewer if they would carry more than
    ``max_weight`` of the total blending weight; never one in ``protected``."""
    total = importance.total
    n = total.shape[0]
    candidates = torch.arange(n, device=total.device)
    if protected is not None:
        candidates = candidates[~protected]
    order = candidates[torch.argsort(total[candidates])]  # least important first
    order = order[: int(round(fraction * n))]
    cumulative = torch.cumsum(total[order].double(), dim=0)
    order = order[cumulative <= max_weight * float(total.sum())]
    mask = torch.zeros(n, dtype=torch.bool, device=total.device)
    mask[order] = True
    return mask


def prompt_protection(means: torch.Tensor, importance: Importance, prompts: Sequence[PromptBox], protect_pixels: float = PROTECT_PIXELS) -> torch.Tensor:
    """bool [N]: inside a prompt box and carrying more than ``protect_pixels`` of blending
    weight in some view (it draws part of what the prompt marks)."""
    if not prompts:
        return torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
    inside = contains_any(list(prompts), means.detach().cpu()).to(means.device)
    return inside & (importance.peak_view > protect_pixels)


@torch.no_grad()
def compact(
    params: torch.nn.ParameterDict,
    optimizers: dict[str, torch.optim.Optimizer],
    state: dict[str, Any],
    importance: Importance,
    prompts: Sequence[PromptBox] = (),
    fraction: float = REMOVED_FRACTION,
    max_weight: float = MAX_REMOVED_WEIGHT,
    protect_pixels: float = PROTECT_PIXELS,
) -> dict[str, Any]:
    """Remove the Gaussians `removal_mask` picks (with optimizer and strategy state), never
    a prompt-protected one. Returns what was done, for ``train.json``."""
    n = params["means"].shape[0]
    protected = prompt_protection(params["means"], importance, prompts, protect_pixels)
    mask = removal_mask(importance, protected, fraction, max_weight)
    n_removed = int(mask.sum())
    if n_removed:
        remove(params=params, optimizers=optimizers, state=state, mask=mask)
    summary = {
        "before": n,
        "removed": n_removed,
        "after": n - n_removed,
        "protected": int(protected.sum()),
        "removed_weight": float(importance.total[mask].sum() / importance.total.sum().clamp_min(1e-12)),
    }
    log.info("compaction: %d of %d Gaussians removed (%.2f%% of the blending weight), %d protected in prompts",
             n_removed, n, 100 * summary["removed_weight"], summary["protected"])
    return summary


def compaction_step(trainer) -> int:
    """The step at which a run compacts: ``COMPACT_AT`` of the run (or
    ``extra["compaction"]["at"]``, for experiments), never before densification stops nor,
    in a PromptGS run, before its whole views reach full size (`PromptFocus.full_size_step`).
    Counted in steps (a step of a batched or distributed run trains several views)."""
    at = float(trainer.cfg.extra.get("compaction", {}).get("at", COMPACT_AT))
    steps = trainer.total_steps
    full_size = trainer.focus.full_size_step() if trainer.focus is not None else 0
    return min(max(trainer.schedule.refine_stop_iter, full_size, int(at * steps)), steps - 1)


def maybe_compact(trainer, step: int) -> dict[str, Any] | None:
    """Called by the trainer after every step of a ``--compact`` run: compacts once, at
    `compaction_step`."""
    if step != compaction_step(trainer) or trainer.strategy_state.get("compaction") is not None:
        return None
    return compact_trainer(trainer)


def compact_trainer(trainer) -> dict[str, Any]:
    """Compact a `train.Trainer`'s Gaussians now: importance over its training views at
    the training resolution, rendered as the run renders (filter, mode, backend); the
    prompts of a PromptGS run protect their objects. The summary is also kept in the
    strategy state (and so in checkpoints and ``train.json``). ``extra["compaction"]``
    may set ``fraction``, ``max_weight`` and ``protect_pixels`` (for experiments)."""
    cfg, params = trainer.cfg, trainer.params
    options = cfg.extra.get("compaction", {})
    cameras = [c.downscaled(cfg.downscale) for c in trainer.scene.train_cameras]
    prompts = list(trainer.focus.prompts) if trainer.focus is not None else []

    def render_fn(cams, colors):
        from .render import render

        return render(
            params["means"].detach(), params["quats"].detach(), torch.exp(params["scales"].detach()),
            torch.sigmoid(params["opacities"].detach()), colors,
            torch.stack([c.world_to_camera for c in cams]).to(colors.device), torch.stack([c.K for c in cams]).to(colors.device),
            cams[0].width, cams[0].height, sh_degree=None, backend=trainer.backend,
            eps2d=trainer.screen_filter, rasterize_mode=cfg.rasterize_mode,
        )

    importance = blending_weights(render_fn, params, cameras)
    summary = compact(
        params, trainer.optimizers, trainer.strategy_state, importance, prompts,
        fraction=float(options.get("fraction", REMOVED_FRACTION)),
        max_weight=float(options.get("max_weight", MAX_REMOVED_WEIGHT)),
        protect_pixels=float(options.get("protect_pixels", PROTECT_PIXELS)),
    )
    summary["step"] = trainer.step
    trainer.strategy_state["compaction"] = summary
    return summary
