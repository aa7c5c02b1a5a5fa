"""Global batches of views: what one optimisation step trains on when it takes more than
one view, how those views are split across ranks, and what the batch size does to the
learning rates, Adam and the schedule (docs/distributed.md).

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
from typing import TYPE_CHECKING, Any

import torch

from .errors import TrainingError
from .metrics import loss_and_mse, mse_to_psnr
from .strategies import DefaultSchedule
from .strategies.default import STATISTICS_MERGED

if TYPE_CHECKING:  # pragma: no cover
    from .focus import TrainView
    from .train import StepResult, Trainer

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


class BatchedSteps:
    """The training step of a run with several views a step, or several ranks."""

    def __init__(self, trainer: "Trainer"):
        self.trainer = trainer
        self.entry = 0  # next entry of PromptGS's view schedule

    # -- the batch --------------------------------------------------------------------

    def plan(self, step: int) -> list["TrainView"] | list[int]:
        """The step's views: TrainViews (PromptGS), or training-camera indices (the
        baselines, whose images only the rank that trains on them loads)."""
        t = self.trainer
        if t.focus is None:
            return [t.next_camera_index() for _ in range(t.batch_size)]
        views: list[TrainView] = []
        while len(views) < t.batch_size:
            views += t.focus.plan(step, entry=self.entry)
            self.entry += 1
        return views

    def _view(self, planned) -> "TrainView":
        if not isinstance(planned, int):
            return planned
        from .focus import TrainView

        camera = self.trainer.scene.train_cameras[planned].downscaled(self.trainer.cfg.downscale)
        return TrainView(camera, camera.load_image(device=self.trainer.device), planned)

    def _fresh_statistics(self) -> dict[str, Any]:
        """A copy of the strategy state whose per-view accumulators are zero: the views of
        this step add to it, and it is summed over ranks before joining the state."""
        t = self.trainer
        n = t.n_gaussians
        delta = dict(t.strategy_state)
        for key in self.sum_keys() + self.max_keys():
            delta[key] = torch.zeros(n, device=t.device)
        return delta

    def sum_keys(self) -> list[str]:
        return [k for k in SUM_STATISTICS if k in self.trainer.strategy_state]

    def max_keys(self) -> list[str]:
        return list(MAX_STATISTICS) if getattr(self.trainer.strategy, "refine_scale2d_stop_iter", 0) > 0 else []

    # -- one step ---------------------------------------------------------------------

    def train_step(self) -> "StepResult":
        from .train import StepResult

        t = self.trainer
        step = t.step
        planned = self.plan(step)
        n = len(planned)
        mine = rank_share(n, t.dist.rank, t.dist.world_size)
        collect = step < t.strategy.refine_stop_iter  # gsplat's strategies stop collecting there
        delta = self._fresh_statistics() if collect else None
        with_depth = t.focus is not None and t.focus.feeds_field(step)
        field_points: list[tuple[int, torch.Tensor, torch.Tensor]] = []
        totals = torch.zeros(2)  # loss and squared error, summed over this rank's views
        names = []
        for i in mine:
            view = self._view(planned[i])
            names.append(view.camera.name)
            loss, mse = self._train_view(step, view, n, with_depth, delta, field_points, i)
            totals += torch.tensor([loss, mse])
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in t.params.values()]
        stats = [delta[k] for k in self.sum_keys()] if collect else []
        reduced = t.dist.all_reduce_sum(grads + stats + [totals.to(t.device)])
        if t.dist.distributed:
            for p, g in zip(t.params.values(), reduced[: len(grads)]):
                p.grad = g
        loss_value, mse_value = (float(v) / n for v in reduced[-1].cpu())
        if not math.isfinite(loss_value):
            cameras = ", ".join(names) or "on other ranks"
            raise TrainingError(f"step {step}: the loss is {loss_value} (a batch with cameras {cameras})")
        info: dict[str, Any] = {STATISTICS_MERGED: True}
        if collect:
            self._merge_statistics(delta, reduced[len(grads) : len(grads) + len(stats)])
        if t.focus is not None and with_depth:
            self._add_field_points(step, field_points)
        t.update(step, info)
        if step % t.schedule.refine_every == 0:
            t.dist.check_agreement(step, t.params)
        return StepResult(loss=loss_value, psnr=mse_to_psnr(mse_value))

    def _train_view(self, step, view, n, with_depth, delta, field_points, index) -> tuple[float, float]:
        """Render one view, back-propagate its share of the loss, add its statistics to
        ``delta`` and its error-field points to ``field_points``; (loss, mse)."""
        t = self.trainer
        out, alpha, info = t.render_cameras(
            [view.camera], sh_degree=t.active_sh_degree(step), screen_filter=view.screen_filter, absgrad=t.absgrad,
            render_mode="RGB+ED" if with_depth else "RGB",
        )
        img = out[..., :3]
        gt = view.gt[None].to(t.device)
        loss, l1_map, dssim_map = t.image_loss(img, gt)
        t.strategy.step_pre_backward(t.params, t.optimizers, t.strategy_state, step, info)
        (loss / n).backward()
        # The strategies undo the loss's 1/n on view-space gradients by n_cameras.
        info["n_cameras"] = n
        if t.focus is not None:
            sink: list = []
            t.focus.field_sink = sink
            try:
                t.focus.observe(
                    step, [view], img.detach(), l1_map.detach(), dssim_map.detach(),
                    out[..., 3].detach() if with_depth else None, alpha[..., 0].detach(), info,
                )
            finally:
                t.focus.field_sink = None
            field_points += [(index, pts, vals) for pts, vals in sink]
        if delta is not None:
            t.strategy._update_state(t.params, delta, info, packed=False)
        return loss_and_mse(loss, img, gt)

    def _merge_statistics(self, delta: dict[str, Any], summed: list[torch.Tensor]) -> None:
        t = self.trainer
        state = t.strategy_state
        for key, value in zip(self.sum_keys(), summed):
            state[key] = value.clone() if state.get(key) is None else state[key].add_(value)
        for key in self.max_keys():
            value = t.dist.all_reduce_max(delta[key])
            state[key] = value if state.get(key) is None else torch.maximum(state[key], value)

    def _add_field_points(self, step: int, mine: list[tuple[int, torch.Tensor, torch.Tensor]]) -> None:
        t = self.trainer
        gathered = t.dist.all_gather_object(mine, what="the error-field gather")
        everyone = sorted((item for part in gathered for item in part), key=lambda item: item[0])
        for _, pts, vals in everyone:
            t.focus.field.add_points(pts, vals, step)

    # -- checkpoints ------------------------------------------------------------------

    def state_dict(self) -> dict:
        return {"entry": self.entry}

    def load_state_dict(self, state: dict) -> None:
        self.entry = int(state["entry"])

