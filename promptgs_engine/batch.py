"""Global batches of views: what one optimisation step trains on when it takes more than
one view, how those views are split across ranks, and what the batch size does to the
learning rates, Adam and the schedule (docs/distributed.md).

The step itself is the trainer's (`train.Trainer`); this module holds the rules it
follows and the arithmetic of the statistics it merges.

**Batch.** A step trains on a global batch of ``B`` views (``--batch-size``; by default
one per rank). The 3DGS and AbsGS baselines draw them from the seeded walk over training
views that a single process uses; PromptGS takes entries of its view schedule (2:3:2:3
random multiview, single, related multiview, single) until the batch holds at least
``B`` views, so a multiview entry counts as its views and is never cut in two. Every rank
computes the same batch from the shared seed and takes a contiguous block of it: with
``n`` views and ``W`` ranks, the first ``n mod W`` ranks take ``⌈n / W⌉`` views, the others
``⌊n / W⌋``.

**Gradients.** Each view is rendered and back-propagated on its own, with its loss
divided by the batch's view count: the step's gradient is the mean over its views. A rank
sums its views' gradients in batch order, and one flat all-reduce sums them over ranks.
One process with ``--batch-size B`` does the same with no all-reduce, adding the views in
batch order. The two agree bit for bit whenever the sums associate alike: two ranks whose
second holds one view, so ``(g0 + … + g(n-2)) + g(n-1)`` either way (``a + b`` is
``b + a`` in floating point); that covers two ranks of one view each, and PromptGS steps
of three views on two ranks. Otherwise (two ranks of two views, three ranks) the
all-reduce associates the sum differently and the runs agree to float rounding.

**Densification statistics.** The per-view additions to the strategy's statistics
(view-space gradient sums and counts, PromptGS's score, error and view count) are kept
apart and summed over ranks in the same all-reduce as the gradients, then added to the
state, so every rank refines from the same statistics (the largest screen radii, where a
strategy keeps them, reduce by maximum). The error field's back-projected points are
gathered and added view by view in batch order.

**Batch rules** (Grendel-GS, Zhao et al., "On Scaling Up 3D Gaussian Splatting
Training", 2024, and its ``lr_scale_mode="sqrt"`` in ``scene/gaussian_model.py``): every
learning rate times √B, Adam's ε divided by √B, its β's raised to the power B; and the
run is counted in views, as Grendel-GS counts iterations in images: ``--iterations I``
takes ⌈I / B⌉ steps, and every step count of the schedule (densification start, stop and
interval, opacity reset, SH degree increase) is divided by B. gsplat's ``simple_trainer``
uses the same √B learning rate and ε, with β's ``1 − B(1 − β)`` (the first-order
expansion of β^B) and a manual ``--steps_scaler``.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import torch

from .strategies import DefaultSchedule

# Statistics the strategies accumulate per Gaussian from every view: summed over views
# (and ranks), or kept as the maximum.
SUM_STATISTICS = ("grad2d", "count", "score", "error", "views")
MAX_STATISTICS = ("radii",)

ADAM_BETAS = (0.9, 0.999)
ADAM_EPS = 1e-15


def adam_settings(lr: float, batch_size: int) -> dict[str, Any]:
    """Learning rate, ε and β's of Adam for a batch of ``batch_size`` views (module
    docstring). A batch of one leaves 3DGS's settings exactly as they are."""
    b = int(batch_size)
    root = math.sqrt(b)
    return {"lr": lr * root, "eps": ADAM_EPS / root, "betas": (ADAM_BETAS[0] ** b, ADAM_BETAS[1] ** b)}


def steps_for(iterations: int, batch_size: int) -> int:
    """Optimisation steps of a run of ``iterations`` views at ``batch_size`` views a step."""
    return -(-int(iterations) // int(batch_size))


def scale_schedule(schedule: DefaultSchedule, batch_size: int) -> DefaultSchedule:
    """Every step count of ``schedule`` divided by the batch size (at least 1)."""
    if batch_size == 1:
        return schedule
    return dataclasses.replace(
        schedule, **{f.name: max(1, round(getattr(schedule, f.name) / batch_size)) for f in dataclasses.fields(schedule)}
    )


def rank_share(n_views: int, rank: int, world_size: int) -> list[int]:
    """Indices of the batch's views that ``rank`` trains on: a contiguous block, the
    first ``n_views mod world_size`` ranks one view more than the rest."""
    base, extra = divmod(n_views, world_size)
    start = rank * base + min(rank, extra)
    return list(range(start, start + base + (1 if rank < extra else 0)))


def sum_statistics_keys(state: dict[str, Any]) -> list[str]:
    """The summed statistics (`SUM_STATISTICS`) that a strategy's ``state`` keeps."""
    return [k for k in SUM_STATISTICS if k in state]


def max_statistics_keys(strategy: Any) -> list[str]:
    """The maximised statistics a strategy keeps: the screen radii, where it grows by them."""
    return list(MAX_STATISTICS) if getattr(strategy, "refine_scale2d_stop_iter", 0) > 0 else []


def fresh_statistics(state: dict[str, Any], keys: list[str], n: int, device: torch.device) -> dict[str, Any]:
    """A copy of a strategy ``state`` whose per-view accumulators ``keys`` are zero for
    ``n`` Gaussians: a step's views add to it, and it is summed over ranks before it
    joins the state (`merge_statistics`)."""
    delta = dict(state)
    for key in keys:
        delta[key] = torch.zeros(n, device=device)
    return delta


def merge_statistics(
    state: dict[str, Any], summed: dict[str, torch.Tensor], maximised: dict[str, torch.Tensor]
) -> None:
    """Add a step's statistics to ``state``: the ``summed`` ones (already summed over
    ranks) are added, the ``maximised`` ones (already maximised over ranks) kept as the
    larger."""
    for key, value in summed.items():
        state[key] = value.clone() if state.get(key) is None else state[key].add_(value)
    for key, value in maximised.items():
        state[key] = value if state.get(key) is None else torch.maximum(state[key], value)
