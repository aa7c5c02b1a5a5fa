"""The training loop: 3DGS optimisation with a pluggable densification strategy.

`Trainer` owns the Gaussians, their optimisers, the strategy and (PromptGS) the prompt
bookkeeping of one run, and steps them: one view or one multiview batch a step, or a
global batch of views over several ranks (batch.py). It writes checkpoints and snapshots
into the run folder (run_folder.py) atomically, so a crash or a cancel never leaves a
half-written checkpoint and a failed run keeps the last good one; `run.run_training`
is the whole job around it.
"""

from __future__ import annotations

import functools
import logging
import math
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from .adam import fused_adam_step
from .batch import (
    adam_settings, fresh_statistics, max_statistics_keys, merge_statistics, rank_share, scale_schedule, steps_for,
    sum_statistics_keys,
)
from .compaction import COMPACT_AT, compact_model, compaction_step
from .config import TrainConfig
from .data import Camera, Scene, load_colmap_scene
from .data.images import preload_images
from .determinism import settle_mkl
from .distributed import RANK_PARAMS_ENV, Dist
from .errors import PromptGSError, TrainingError
from .events import EventWriter, write_snapshot
from .focus import LiveModel, PromptFocus, load_prompt_setting, run_length
from .formats import load_gaussians, save_exports
from .gaussians import PARAM_KEYS, init_from_points, save_ply
from .losses import photometric_maps
from .metrics import loss_and_mse, mse_to_psnr
from .propose import TrainingProposer, proposal_steps
from .render import render, resolve_backend
from .run_folder import CHECKPOINT, FINAL_PLY, atomic_torch_save
from .sky import sky_points
from .strategies import DefaultSchedule, make_default_strategy
from .strategies.default import BACKGROUND, BACKGROUND_RADIUS, STATISTICS_MERGED
from .strategies.promptgs import LAST_ROUND_JUDGED_AT, PromptGSStrategy
from .threads import one_thread
from .views import TrainView

log = logging.getLogger("promptgs.train")


def make_optimizers(params: torch.nn.ParameterDict, cfg: TrainConfig, extent: float, batch_size: int = 1) -> dict:
    """One Adam per parameter, as gsplat's strategies expect (one param group each), with
    the batch rules of `batch.adam_settings` (a batch of one: 3DGS's settings)."""
    lrs = {
        "means": cfg.means_lr * extent,
        "scales": cfg.scales_lr,
        "quats": cfg.quats_lr,
        "opacities": cfg.opacities_lr,
        "sh0": cfg.sh0_lr,
        "shN": cfg.shN_lr,
    }
    # The fused implementation is about 3x faster on the CPU (9 ms vs 28 ms for 100k
    # Gaussians, benchmarks/rasterizer.py) and keeps the same state layout.
    optimizers = {}
    for k in PARAM_KEYS:
        adam = adam_settings(lrs[k], batch_size)
        optimizers[k] = torch.optim.Adam(
            [{"params": [params[k]], "lr": adam["lr"], "name": k}], eps=adam["eps"], betas=adam["betas"], fused=True
        )
    return optimizers


def first_non_finite(params: torch.nn.ParameterDict | dict[str, torch.Tensor]) -> str | None:
    """Name of the first parameter holding a NaN or an inf, or None.

    A NaN or inf anywhere makes a parameter's sum non-finite: one sum per parameter and one
    read of all of them (no mask as large as a parameter; 0.07 ms for six parameters of 9k
    Gaussians against 0.16 ms for six reads). A sum that overflows from finite values is
    confirmed elementwise."""
    values = [v.detach() for v in params.values()]
    sums = torch.stack([v.sum() for v in values])
    if bool(torch.isfinite(sums).all()):
        return None
    for key, value, total in zip(params.keys(), values, sums):
        if not bool(torch.isfinite(total)) and not bool(torch.isfinite(value).all()):
            return key
    return None


@dataclass
class StepResult:
    loss: float
    psnr: float | None  # None when the step was asked not to measure it


class Trainer:
    """Owns the Gaussians, the optimisers and the strategy for one run."""

    def __init__(
        self,
        cfg: TrainConfig,
        scene: Scene | None = None,
        events: EventWriter | None = None,
        quiet: bool = False,
        dist: Dist | None = None,
    ):
        cfg.validate()
        settle_mkl()  # before any torch math: same bits in every process (determinism.py)
        self.cfg = cfg
        # Several ranks (distributed.py), or several views a step (batch.py).
        self.dist = dist or Dist()
        self.batch_size = int(cfg.batch_size or self.dist.world_size)
        self.run_entries = run_length(cfg)  # cfg.iterations, plus PromptGS's related steps
        self.total_steps = steps_for(self.run_entries, self.batch_size)
        self.out = Path(cfg.out)
        self.events = events or EventWriter()
        self.quiet = quiet or self.events.enabled
        self.backend = resolve_backend(cfg.backend)
        self.device = torch.device("cuda" if self.backend == "cuda" else "cpu")
        self.scene = scene if scene is not None else load_colmap_scene(cfg.dataset, images=cfg.images, test_every=cfg.test_every)
        if not self.scene.train_cameras:
            raise PromptGSError(f"{cfg.dataset}: no training images")
        self.preload_images()
        torch.manual_seed(cfg.seed)
        self.rng = np.random.default_rng(cfg.seed)
        # 3DGS's schedule for cfg.iterations, stretched over the related steps PromptGS adds:
        # as many growth rounds and opacity resets as the 3DGS run of the same iterations.
        schedule = DefaultSchedule.for_iterations(cfg.iterations).stretched(self.run_entries / cfg.iterations)
        self.schedule = scale_schedule(schedule, self.batch_size)
        self.screen_filter = cfg.effective_screen_filter
        points, colors = self.scene.points.float(), self.scene.point_colors.float()
        self.n_sky_points = 0
        sky_radius = 0.0
        if cfg.sky and points.shape[0] and not cfg.init:
            sky, sky_colors, sky_radius = sky_points(self.scene.train_cameras, points)
            points, colors = torch.cat([points, sky]), torch.cat([colors, sky_colors])
            self.n_sky_points = sky.shape[0]
            log.info("%d SfM points and %d far background (sky) points", self.scene.points.shape[0], self.n_sky_points)
        self.params = (
            load_gaussians(cfg.init, sh_degree=cfg.sh_degree) if cfg.init
            else init_from_points(points, colors, sh_degree=cfg.sh_degree, init_opacity=cfg.init_opacity)
        ).to(self.device)
        self.n_initial = self.n_gaussians  # what the run starts from (train.json)
        self.optimizers = make_optimizers(self.params, cfg, self.scene.extent, self.batch_size)
        gamma = 0.01 ** (1.0 / self.total_steps)
        self.schedulers = [torch.optim.lr_scheduler.ExponentialLR(self.optimizers["means"], gamma=gamma)]
        self.strategy = self._make_strategy()
        self.strategy.loss_probe = self.probe_loss
        self._probe_views: list[tuple[Camera, torch.Tensor]] | None = None
        self.strategy.check_sanity(self.params, self.optimizers)
        self.strategy_state = self.strategy.initialize_state(scene_scale=self.scene.extent)
        if self.n_sky_points:
            # The shell's Gaussians, for the strategy's size limit (strategies.default.too_big).
            background = torch.zeros(self.n_gaussians, device=self.device)
            background[-self.n_sky_points :] = 1.0
            self.strategy_state[BACKGROUND] = background
            self.strategy_state[BACKGROUND_RADIUS] = sky_radius
        self.step = 0
        self.train_seconds = 0.0
        self._order: list[int] = []
        self.focus = self._make_focus() if cfg.strategy == "promptgs" else None
        if self.focus is not None:
            self.strategy.attention_fn = lambda pts: self.focus.field.attention(pts.cpu(), self.focus.prompts)
        # Several views a step, or several ranks: `_train_batch`.
        self.batched = self.dist.distributed or self.batch_size > 1
        self.entry = 0  # the next entry of PromptGS's view schedule a batched step takes

    # -- set-up -----------------------------------------------------------------------

    def _make_strategy(self):
        if self.cfg.strategy in ("3dgs", "absgs"):
            return make_default_strategy(
                self.cfg.strategy, self.schedule, budget=self.cfg.budget_cap, auto_budget=self.cfg.budget == "auto"
            )
        sched = self.schedule
        return PromptGSStrategy(
            refine_start_iter=sched.refine_start_iter,
            refine_stop_iter=sched.refine_stop_iter,
            refine_every=sched.refine_every,
            reset_every=sched.reset_every,
            budget=self.cfg.budget_cap,
            auto_budget=self.cfg.budget == "auto",
            protect_steps=max(sched.reset_every, 2 * sched.refine_every),
            last_round_judgement_step=max(int(LAST_ROUND_JUDGED_AT * self.total_steps), sched.refine_stop_iter),
            **self.cfg.extra.get("promptgs", {}),
        )

    def _make_focus(self) -> PromptFocus:
        cfg = self.cfg
        prompts = load_prompt_setting(cfg, self.scene)
        proposer = None
        if cfg.propose_prompts:
            sched = self.schedule
            proposer = TrainingProposer(
                [c.downscaled(cfg.downscale) for c in self.scene.train_cameras], self.scene.points,
                proposal_steps(sched.refine_start_iter, sched.refine_stop_iter, sched.reset_every),
                run_dir=self.out, dataset=str(cfg.dataset), backend=self.backend, screen_filter=self.screen_filter,
                rasterize_mode=cfg.rasterize_mode, given=prompts, writes=self.dist.is_writer,
            )
        return PromptFocus(
            cfg, self.scene, self.schedule, self.total_steps, self.strategy, self.device, prompts, proposer=proposer
        )

    def preload_images(self) -> bool:
        """Decode the training images at the training size before the first step, as
        OpenSplat does, when the image cache holds them all (otherwise they load as needed):
        the steps of the first pass over the views then do not wait for the decoder."""
        cams = [c.downscaled(self.cfg.downscale) for c in self.scene.train_cameras]
        items = [(c.image_path, c.downscale, c.width * c.height * 3) for c in cams]
        return preload_images(items, threads=torch.get_num_threads())

    @property
    def absgrad(self) -> bool:
        return bool(getattr(self.strategy, "absgrad", False))

    def active_sh_degree(self, step: int) -> int:
        return min(step // self.schedule.sh_degree_interval, self.cfg.sh_degree)

    def next_camera_index(self) -> int:
        """Walk a fresh random permutation of the training views, like 3DGS."""
        if not self._order:
            self._order = list(self.rng.permutation(len(self.scene.train_cameras)))
        return int(self._order.pop())

    PROBE_VIEWS = 4
    PROBE_WIDTH = 200

    @torch.no_grad()
    def probe_loss(self) -> float:
        """Mean L1 of a fixed set of training views (evenly spaced, at most
        `PROBE_WIDTH` pixels wide), rendered without gradients: a loss that does not
        depend on which views or crops the last steps trained on (the automatic budget)."""
        if self._probe_views is None:
            cams = self.scene.train_cameras
            picks = sorted({round(i * (len(cams) - 1) / max(self.PROBE_VIEWS - 1, 1)) for i in range(self.PROBE_VIEWS)})
            self._probe_views = []
            for i in picks:
                cam = cams[i].downscaled(self.cfg.downscale)
                cam = cam.downscaled(max(1, math.ceil(cam.width / self.PROBE_WIDTH)))
                self._probe_views.append((cam, cam.load_image(device=self.device)))
        losses = []
        for cam, gt in self._probe_views:
            img, _, _ = self.render_camera(cam, sh_degree=self.active_sh_degree(self.step))
            losses.append(float((img[..., :3].clamp(0, 1) - gt).abs().mean()))
        return sum(losses) / len(losses)

    # -- one step ---------------------------------------------------------------------

    def render_cameras(
        self, cameras: list[Camera], sh_degree: int | None = None, screen_filter: float | None = None, **kwargs
    ):
        """Render cameras of one size in one call; returns (images [C,H,W,D], alphas, info).
        ``screen_filter`` (px²) defaults to the run's."""
        p = self.params
        return render(
            p["means"],
            p["quats"],
            torch.exp(p["scales"]),
            torch.sigmoid(p["opacities"]),
            p["sh0"],
            torch.stack([c.world_to_camera for c in cameras]).to(self.device),
            torch.stack([c.K for c in cameras]).to(self.device),
            cameras[0].width,
            cameras[0].height,
            sh_degree=self.cfg.sh_degree if sh_degree is None else sh_degree,
            backend=self.backend,
            eps2d=self.screen_filter if screen_filter is None else screen_filter,
            rasterize_mode=self.cfg.rasterize_mode,
            sh_rest=p["shN"],
            **kwargs,
        )

    def render_camera(self, camera: Camera, sh_degree: int | None = None, **kwargs):
        """Render one camera at its own resolution; returns (image [H,W,C], alpha, info)."""
        img, alpha, info = self.render_cameras([camera], sh_degree, **kwargs)
        return img[0], alpha[0], info

    def plan_step(self, step: int):
        """The views this step trains on (one size): PromptGS's plan, or 3DGS's next view."""
        if self.focus is not None:
            return self.focus.plan(step)
        index = self.next_camera_index()
        camera = self.scene.train_cameras[index].downscaled(self.cfg.downscale)
        return [TrainView(camera, camera.load_image(device=self.device), index)]

    def image_loss(self, img: torch.Tensor, gt: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """(loss, L1 map, D-SSIM map) of renders [C, H, W, 3] against ground truth: the loss
        is (1 − λ)·L1 + λ·D-SSIM from per-pixel maps, which PromptGS reuses for its scores."""
        return photometric_maps(img, gt, self.cfg.ssim_lambda)

    def reports_progress(self, step: int) -> bool:
        """Whether the run loop reports its progress (loss, PSNR) after step number ``step``
        (counted from 1)."""
        return step % self.cfg.progress_every == 0 or step == self.total_steps

    def train_step(self, psnr: bool = True) -> StepResult:
        """One training step. ``psnr``: also measure the render's PSNR against its image, a
        pass over both images that changes nothing else (the run loop asks for it on the
        steps it reports; a step of several views or ranks always measures it)."""
        if self.batched:
            return self._train_batch()
        step = self.step
        views = self.plan_step(step)
        cameras = [v.camera for v in views]
        gt = (views[0].gt[None] if len(views) == 1 else torch.stack([v.gt for v in views])).to(self.device)
        # PromptGS's error field needs the rendered depth, on the steps that feed it.
        with_depth = self.focus is not None and self.focus.feeds_field(step)
        out, alpha, info = self.render_cameras(
            cameras, sh_degree=self.active_sh_degree(step), screen_filter=views[0].screen_filter, absgrad=self.absgrad,
            render_mode="RGB+ED" if with_depth else "RGB",
        )
        img = out if out.shape[-1] == 3 else out[..., :3]  # a slice's backward would copy the gradient
        loss, l1_map, dssim_map = self.image_loss(img, gt)
        self.strategy.step_pre_backward(self.params, self.optimizers, self.strategy_state, step, info)
        loss.backward()
        if psnr:
            loss_value, mse_value = loss_and_mse(loss, img, gt)
        else:
            loss_value, mse_value = float(loss.detach()), None
        if not math.isfinite(loss_value):
            raise TrainingError(f"step {step}: the loss is {loss_value} (camera {cameras[0].name})")
        if self.focus is not None:
            self.focus.observe(
                step, views, img.detach(), l1_map.detach(), dssim_map.detach(),
                out[..., 3].detach() if with_depth else None, alpha[..., 0].detach(), info,
            )
        self.update(step, info)
        return StepResult(loss=loss_value, psnr=None if mse_value is None else mse_to_psnr(mse_value))

    # -- a step of several views, or of several ranks (batch.py) ---------------------

    def _plan_batch(self, step: int) -> list[TrainView] | list[int]:
        """The step's global batch: TrainViews (PromptGS: schedule entries until the batch
        holds ``batch_size`` views), or training-camera indices (the baselines, whose
        images only the rank that trains on them loads)."""
        if self.focus is None:
            return [self.next_camera_index() for _ in range(self.batch_size)]
        views: list[TrainView] = []
        while len(views) < self.batch_size:
            views += self.focus.plan(step, entry=self.entry)
            self.entry += 1
        return views

    def _batch_view(self, planned: TrainView | int) -> TrainView:
        if not isinstance(planned, int):
            return planned
        camera = self.scene.train_cameras[planned].downscaled(self.cfg.downscale)
        return TrainView(camera, camera.load_image(device=self.device), planned)

    def _train_batch(self) -> StepResult:
        """One step over a global batch of views: this rank's share rendered and
        back-propagated view by view, then gradients, statistics and losses summed over
        ranks in one all-reduce (batch.py describes the arithmetic)."""
        step = self.step
        planned = self._plan_batch(step)
        n = len(planned)
        mine = rank_share(n, self.dist.rank, self.dist.world_size)
        collect = step < self.strategy.refine_stop_iter  # gsplat's strategies stop collecting there
        delta = None
        if collect:
            keys = sum_statistics_keys(self.strategy_state) + max_statistics_keys(self.strategy)
            delta = fresh_statistics(self.strategy_state, keys, self.n_gaussians, self.device)
        with_depth = self.focus is not None and self.focus.feeds_field(step)
        field_points: list[tuple[int, torch.Tensor, torch.Tensor]] = []
        totals = torch.zeros(2)  # loss and squared error, summed over this rank's views
        names = []
        for i in mine:
            view = self._batch_view(planned[i])
            names.append(view.camera.name)
            loss, mse = self._train_batch_view(step, view, n, with_depth, delta, field_points, i)
            totals += torch.tensor([loss, mse])
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in self.params.values()]
        summed_keys = sum_statistics_keys(self.strategy_state) if collect else []
        stats = [delta[k] for k in summed_keys]
        reduced = self.dist.all_reduce_sum(grads + stats + [totals.to(self.device)])
        if self.dist.distributed:
            for p, g in zip(self.params.values(), reduced[: len(grads)]):
                p.grad = g
        loss_value, mse_value = (float(v) / n for v in reduced[-1].cpu())
        if not math.isfinite(loss_value):
            cameras = ", ".join(names) or "on other ranks"
            raise TrainingError(f"step {step}: the loss is {loss_value} (a batch with cameras {cameras})")
        info: dict[str, Any] = {STATISTICS_MERGED: True}
        if collect:
            summed = dict(zip(summed_keys, reduced[len(grads) : len(grads) + len(stats)]))
            maximised = {k: self.dist.all_reduce_max(delta[k]) for k in max_statistics_keys(self.strategy)}
            merge_statistics(self.strategy_state, summed, maximised)
        if self.focus is not None and with_depth:
            self._add_field_points(step, field_points)
        self.update(step, info)
        if step % self.schedule.refine_every == 0:
            self.dist.check_agreement(step, self.params)
        return StepResult(loss=loss_value, psnr=mse_to_psnr(mse_value))

    def _train_batch_view(
        self,
        step: int,
        view: TrainView,
        n: int,
        with_depth: bool,
        delta: dict[str, Any] | None,
        field_points: list[tuple[int, torch.Tensor, torch.Tensor]],
        index: int,
    ) -> tuple[float, float]:
        """Render one view of a batch of ``n``, back-propagate its share of the loss, add
        its statistics to ``delta`` and its error-field points (as view ``index``) to
        ``field_points``; (loss, mse)."""
        out, alpha, info = self.render_cameras(
            [view.camera], sh_degree=self.active_sh_degree(step), screen_filter=view.screen_filter, absgrad=self.absgrad,
            render_mode="RGB+ED" if with_depth else "RGB",
        )
        img = out[..., :3]
        gt = view.gt[None].to(self.device)
        loss, l1_map, dssim_map = self.image_loss(img, gt)
        self.strategy.step_pre_backward(self.params, self.optimizers, self.strategy_state, step, info)
        (loss / n).backward()
        # The strategies undo the loss's 1/n on view-space gradients by n_cameras.
        info["n_cameras"] = n
        if self.focus is not None:
            sink: list = []
            self.focus.field_sink = sink
            try:
                self.focus.observe(
                    step, [view], img.detach(), l1_map.detach(), dssim_map.detach(),
                    out[..., 3].detach() if with_depth else None, alpha[..., 0].detach(), info,
                )
            finally:
                self.focus.field_sink = None
            field_points += [(index, pts, vals) for pts, vals in sink]
        if delta is not None:
            self.strategy._update_state(self.params, delta, info, packed=False)
        return loss_and_mse(loss, img, gt)

    def _add_field_points(self, step: int, mine: list[tuple[int, torch.Tensor, torch.Tensor]]) -> None:
        """Every rank's error-field points of this step, added view by view in batch order."""
        gathered = self.dist.all_gather_object(mine, what="the error-field gather")
        everyone = sorted((item for part in gathered for item in part), key=lambda item: item[0])
        for _, pts, vals in everyone:
            self.focus.field.add_points(pts, vals, step)

    def update(self, step: int, info: dict) -> None:
        """Apply the step's gradients, then the schedules, the strategy's refinement and
        PromptGS's bookkeeping."""
        fused_adam_step(self.optimizers)
        for sched in self.schedulers:
            sched.step()
        self.strategy.step_post_backward(self.params, self.optimizers, self.strategy_state, step, info, packed=False)
        if self.focus is not None:
            self.focus.after_step(step, self.live_model(step))
        if self.cfg.compact and step == self.compaction_at and self.strategy_state.get("compaction") is None:
            self.compact(step)
        self.check_finite()

    def live_model(self, step: int) -> LiveModel:
        """The Gaussians as PromptGS's bookkeeping may read and grow them after ``step``."""
        return LiveModel(self.params, self.optimizers, self.strategy_state, self.render_camera, self.active_sh_degree(step))

    @functools.cached_property
    def compaction_at(self) -> int:
        """The step a ``--compact`` run compacts at (`compaction.compaction_step`);
        ``extra["compaction"]["at"]`` may move it, for experiments."""
        at = float(self.cfg.extra.get("compaction", {}).get("at", COMPACT_AT))
        full_size = self.focus.full_size_step() if self.focus is not None else 0
        return compaction_step(self.total_steps, self.schedule.refine_stop_iter, full_size, at)

    def compact(self, step: int) -> dict[str, Any]:
        """Compact the Gaussians now (`compaction.compact_model`) over the training views at
        the training size, the prompts protecting their objects; the summary is kept in the
        strategy state (and so in checkpoints and ``train.json``)."""
        cfg = self.cfg
        summary = compact_model(
            self.params, self.optimizers, self.strategy_state,
            [c.downscaled(cfg.downscale) for c in self.scene.train_cameras],
            list(self.focus.prompts) if self.focus is not None else [],
            self.backend, self.screen_filter, cfg.rasterize_mode, cfg.extra.get("compaction", {}),
        )
        summary["step"] = step
        self.strategy_state["compaction"] = summary
        return summary

    def check_finite(self) -> None:
        with one_thread():  # small models: faster than waking a thread for each sum (threads.py)
            key = first_non_finite(self.params)
        if key is not None:
            raise TrainingError(
                f"step {self.step}: NaN/inf in parameter '{key}'; the last good checkpoint is kept in {self.out / CHECKPOINT}"
            )

    # -- files ------------------------------------------------------------------------

    def checkpoint_dict(self) -> dict:
        return {
            "step": self.step,
            "train_seconds": self.train_seconds,
            "params": {k: v.detach().cpu() for k, v in self.params.items()},
            "optimizers": {k: o.state_dict() for k, o in self.optimizers.items()},
            "schedulers": [s.state_dict() for s in self.schedulers],
            "strategy_state": {
                k: (v.cpu() if isinstance(v, torch.Tensor) else v) for k, v in self.strategy_state.items()
            },
            "rng": self.rng.bit_generator.state,
            "order": list(self._order),
            "torch_rng": torch.get_rng_state(),
            "focus": self.focus.state_dict() if self.focus is not None else None,
            "batch": {"entry": self.entry if self.batched else self.step},
        }

    def save_checkpoint(self) -> None:
        if self.dist.is_writer:
            atomic_torch_save(self.checkpoint_dict(), self.out / CHECKPOINT)

    def load_checkpoint(self, path: Path) -> None:
        try:
            ckpt = torch.load(path, map_location="cpu", weights_only=False)
        except Exception as exc:
            raise PromptGSError(f"{path}: cannot read checkpoint ({exc})") from exc
        self.params = torch.nn.ParameterDict(
            {k: torch.nn.Parameter(v.to(self.device)) for k, v in ckpt["params"].items()}
        )
        self.optimizers = make_optimizers(self.params, self.cfg, self.scene.extent, self.batch_size)
        for k, opt in self.optimizers.items():
            opt.load_state_dict(ckpt["optimizers"][k])
        gamma = 0.01 ** (1.0 / self.total_steps)
        self.schedulers = [torch.optim.lr_scheduler.ExponentialLR(self.optimizers["means"], gamma=gamma)]
        for s, state in zip(self.schedulers, ckpt["schedulers"]):
            s.load_state_dict(state)
        self.strategy_state = {
            k: (v.to(self.device) if isinstance(v, torch.Tensor) else v) for k, v in ckpt["strategy_state"].items()
        }
        self.rng.bit_generator.state = ckpt["rng"]
        self._order = list(ckpt["order"])
        torch.set_rng_state(ckpt["torch_rng"])
        self.step = int(ckpt["step"])
        self.train_seconds = float(ckpt["train_seconds"])
        if self.focus is not None and ckpt.get("focus"):
            self.focus.load_state_dict(ckpt["focus"])
        if self.batched:
            # A checkpoint of a run at one view a step has consumed one schedule entry a step.
            self.entry = int((ckpt.get("batch") or {"entry": self.step})["entry"])

    def snapshot(self) -> Path | None:
        if not self.dist.is_writer:
            return None
        folder = self.out / "snapshots"
        folder.mkdir(exist_ok=True)
        path = folder / f"step_{self.step:06d}.npz"
        score = error = field = None
        if self.focus is not None:
            score, error = self.strategy.per_gaussian(self.params, self.strategy_state)
            field = self.focus.field_arrays()
        write_snapshot(path, self.params, score=score, error=error, field=field)
        self.events.emit("snapshot", step=self.step, path=str(path), n_gaussians=self.n_gaussians)
        return path

    @property
    def n_gaussians(self) -> int:
        return int(self.params["means"].shape[0])

    # -- the run ----------------------------------------------------------------------

    def train(self) -> dict:
        """Train to ``cfg.iterations``, then write the PLY and ``metrics.json``."""
        cfg = self.cfg
        self.events.emit(
            "start",
            out=str(self.out),
            iterations=self.total_steps,
            backend=self.backend,
            strategy=cfg.strategy,
            n_train=len(self.scene.train_cameras),
            n_test=len(self.scene.test_cameras),
            n_gaussians=self.n_gaussians,
        )
        bar = tqdm(total=self.total_steps, initial=self.step, desc=f"train {cfg.strategy}", disable=self.quiet, unit="step")
        loss_ema: float | None = None
        while self.step < self.total_steps:
            report = self.reports_progress(self.step + 1)
            t0 = time.perf_counter()
            result = self.train_step(psnr=report)
            self.train_seconds += time.perf_counter() - t0
            self.step += 1
            loss_ema = result.loss if loss_ema is None else 0.9 * loss_ema + 0.1 * result.loss
            bar.update(1)
            if report:
                bar.set_postfix(loss=f"{loss_ema:.4f}", psnr=f"{result.psnr:.2f}", n=self.n_gaussians)
                per_step = self.train_seconds / max(self.step, 1)
                self.events.emit(
                    "progress",
                    step=self.step,
                    iterations=self.total_steps,
                    loss=loss_ema,
                    psnr=result.psnr,
                    n_gaussians=self.n_gaussians,
                    elapsed_s=self.train_seconds,
                    eta_s=per_step * (self.total_steps - self.step),
                )
            if cfg.checkpoint_every and self.step % cfg.checkpoint_every == 0:
                self.save_checkpoint()
            if cfg.snapshot_every and self.step % cfg.snapshot_every == 0:
                self.snapshot()
        bar.close()
        self.dist.check_agreement(self.step, self.params)
        if os.environ.get(RANK_PARAMS_ENV):
            atomic_torch_save(
                {k: v.detach().cpu() for k, v in self.params.items()},
                Path(os.environ[RANK_PARAMS_ENV]) / f"rank{self.dist.rank}.pt",
            )
        self.save_checkpoint()
        if self.dist.is_writer:
            save_ply(self.params, self.out / FINAL_PLY)
            save_exports(self.params, self.out / FINAL_PLY, cfg.export, antialiased=cfg.antialiased)
        if self.events.enabled and not cfg.snapshot_every:
            self.snapshot()
        log.info("trained %d steps in %.1f s, %d Gaussians", self.step, self.train_seconds, self.n_gaussians)
        return self.run_summary()

    def run_summary(self) -> dict:
        return {
            "iterations": self.cfg.iterations,
            "steps": self.step,  # with PromptGS's related steps (focus.run_length)
            "train_seconds": self.train_seconds,
            "n_gaussians": self.n_gaussians,
            "initial_gaussians": self.n_initial,  # the --init file's, or the SfM points (and sky shell)
            "backend": self.backend,
            "strategy": self.cfg.strategy,
            "peak_rss_mb": peak_rss_mb(),
            "peak_gpu_mb": peak_gpu_mb(self.device),
            "budget": self.cfg.budget,
            "auto_budget": self.strategy_state.get("auto_budget"),
            "sky_points": self.n_sky_points,
            "world_size": self.dist.world_size,
            "batch_size": self.batch_size,
            "growth": self.strategy_state.get("ledger"),
            "compaction": self.strategy_state.get("compaction"),
        }


def peak_rss_mb() -> float | None:
    """Peak resident memory of this process so far, in MiB (None where unknown)."""
    try:
        import resource
    except ImportError:  # Windows
        return None
    kib = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return kib / (1024.0 * 1024.0) if sys.platform == "darwin" else kib / 1024.0


def peak_gpu_mb(device: torch.device) -> float | None:
    """Peak GPU memory torch allocated on ``device`` so far, in MiB (None off the GPU).

    What torch's allocator handed out; the CUDA context and the allocator's cache add to
    what nvidia-smi shows for the process.
    """
    if device.type != "cuda":
        return None
    return torch.cuda.max_memory_allocated(device) / (1024.0 * 1024.0)
