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
(``max_weight``): then only as many go as carry 5%, and a lean model keeps more. On the
real test scenes the 40% least important carry a few percent of the weight at most.

A prompted object can carry little weight in total (a drone covers one pixel in a few
views) and would fall under any global cut. So with prompts (PromptGS), a Gaussian inside
a prompt box is kept whenever it carries any blending weight (over ``protect_pixels``,
0) in some training view: it draws part of what the prompt marks. A drone of two pixels
is often drawn by several faint Gaussians of a tenth of a pixel each, so any higher floor
lets the cut take most of them and the object with them. The boxes hold about 1% of the
Gaussians, so keeping them all costs little.

The trainer compacts once, at 60% of the run (`compaction_step`): a tenth of the run after
densification stops, so that the Gaussians of the last refinement and the opacities
clamped by the last reset have settled, and the remaining 40%, in which 3DGS only
fine-tunes, fine-tune the compacted model (LightGaussian prunes and then fine-tunes the
same way); right where densification stops, the same cut costs more than twice as much
PSNR. A PromptGS run compacts no earlier than its first full-size whole view (70% of the
run under the progressive schedule, on scenes wide enough for it): cut while the views
still train at half size, the model has less full-size fine-tuning left than 3DGS's.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from typing import Any, Callable, Sequence

import torch
from gsplat.strategy.ops import remove

from .prompts import PromptBox, contains_any
from .render import render

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


def compaction_step(total_steps: int, refine_stop_iter: int, full_size_step: int = 0, at: float = COMPACT_AT) -> int:
    """The step at which a run of ``total_steps`` compacts: ``at`` of the run
    (`COMPACT_AT`), never before densification stops (``refine_stop_iter``) nor, in a
    PromptGS run, before its whole views reach full size (``full_size_step``,
    `focus.PromptFocus.full_size_step`). Counted in steps (a step of a batched or
    distributed run trains several views)."""
    return min(max(refine_stop_iter, full_size_step, int(at * total_steps)), total_steps - 1)


def compact_model(
    params: torch.nn.ParameterDict,
    optimizers: dict[str, torch.optim.Optimizer],
    state: dict[str, Any],
    cameras: Sequence[Any],
    prompts: Sequence[PromptBox],
    backend: str,
    screen_filter: float,
    rasterize_mode: str,
    options: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Compact a run's Gaussians now: importance over its training ``cameras`` (at the
    training resolution), rendered as the run renders (``backend``, ``screen_filter``,
    ``rasterize_mode``); the ``prompts`` of a PromptGS run protect their objects.
    ``options`` (a job's ``extra["compaction"]``) may set ``fraction``, ``max_weight`` and
    ``protect_pixels``, for experiments. Returns the summary of `compact`."""
    options = options or {}

    def render_fn(cams, colors):
        return render(
            params["means"].detach(), params["quats"].detach(), torch.exp(params["scales"].detach()),
            torch.sigmoid(params["opacities"].detach()), colors,
            torch.stack([c.world_to_camera for c in cams]).to(colors.device), torch.stack([c.K for c in cams]).to(colors.device),
            cams[0].width, cams[0].height, sh_degree=None, backend=backend,
            eps2d=screen_filter, rasterize_mode=rasterize_mode,
        )

    importance = blending_weights(render_fn, params, cameras)
    return compact(
        params, optimizers, state, importance, prompts,
        fraction=float(options.get("fraction", REMOVED_FRACTION)),
        max_weight=float(options.get("max_weight", MAX_REMOVED_WEIGHT)),
        protect_pixels=float(options.get("protect_pixels", PROTECT_PIXELS)),
    )
