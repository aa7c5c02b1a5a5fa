"""Focused training for PromptGS: which views each step trains on, at which resolution,
and the prompt-side bookkeeping around the PromptGS strategy.

`PromptFocus` is what the trainer consults when ``--strategy promptgs``:

* **Views.** `views.ViewSchedule` gives the paper's 2:3:2:3 cycle of random multiview,
  single, related multiview and single steps. Related steps train on the prompt's most
  relevant views (`views.related_views`, ranked by the geometric terms only: the
  image-similarity term is left off), rendered as *crops* around the box's
  projection at full training resolution: a tiny object gets the whole step's loss,
  at full detail, for the cost of a few thousand pixels. A related step holds two
  views, and one for the centre prompt (`CENTRE_PROMPT_VIEWS_PER_STEP`), whose crops
  take every view that sees it in turn rather than its most relevant; a run whose only
  prompt is the centre box has one related step a cycle, not two (`CENTRE_PROMPT_RATIO`).
  These steps come on top of ``--iterations``, which counts whole-view steps (`run_length`).
* **Progressive resolution.** Full-image steps run at 8×, 4×, 2× the training
  downscale before the full resolution (paper: 7k steps each at 30k; here the same
  fractions of the run; a level under 64 px across uses the coarsest that fits). While
  densification runs, some single-view steps render at full size: the strategy's
  growth statistics come from them (`is_statistics_step`). Full-size renders use the
  run's screen filter (0.1 px² for PromptGS, `config.PROMPTGS_SCREEN_FILTER`);
  low-resolution steps keep 3DGS's 0.3 px², since a filter narrower than a pixel aliases
  there.
* **Error field.** Each step's per-pixel loss is back-projected with the rendered
  expected depth into `errorfield.ErrorField`; its attention weights prompt growth,
  its peaks become prompts with ``--auto-prompts``, and it is written to snapshots.
* **Resampling.** During densification, every ``resample_every`` steps, each prompt is
  carved (`strategies.promptgs.carve_prompt`) from its related views and the consistent
  high-error points become new small Gaussians.
"""

from __future__ import annotations

import bisect
import dataclasses
import logging
import os
import sys
from dataclasses import dataclass
from typing import Any, Callable

import torch

from .config import BASELINE_SCREEN_FILTER, TrainConfig
from .data import Camera, Scene
from .data.images import BoundedCache
from .errorfield import ErrorField
from .errors import PromptError
from .losses import edge_losses_to, sobel_magnitude
from .prompts import (
    PromptBox, check_visible, load_prompts, placement_warnings, project_box, prompts_from_json, scene_center_prompt,
)
from .propose import TrainingProposer
from .strategies import DefaultSchedule
from .strategies.promptgs import LAMBDA_DSSIM, LAMBDA_EDGE, LAMBDA_L1, PromptGSStrategy, append_gaussians, carve_prompt
from .threads import one_thread
from .views import (
    DEFAULT_RATIO, RELATED_MULTIVIEW, SINGLE, TrainView, ViewSchedule, entries_with_related_steps, related_views,
    top_k_views, views_cap_from_memory,
)

log = logging.getLogger("promptgs.focus")

PROGRESSIVE_LEVELS = (8, 4, 2)
PROGRESSIVE_FRACTION = 7 / 30  # of the run, per level (paper: 7000 of 30000 steps)
# A level that would leave fewer pixels across is replaced by the coarsest that does not.
# Much coarser levels fit a small view so loosely that the full-size statistics steps
# then find gradients everywhere, and PromptGS grows more Gaussians outside the prompts
# than 3DGS.
MIN_PROGRESSIVE_WIDTH = 100
RESAMPLED_OPACITY = 0.5  # of the Gaussians resampling adds
SEED_SCALE_PX = 0.7  # width of the Gaussian seeded at a proposed point, in pixels at its depth (as resampling's)
MIN_RELATED_VIEWS = 3  # as many as resampling's multi-view vote needs
RELATED_VIEWS = 8  # views per prompt whose crops its related steps train (`PromptFocus.set_prompts`)
# Views in a related step of the centre prompt (`--center-prompt`); other prompts take the
# schedule's cap (2). The centre box marks no object, only where the cameras look, and its
# crops hold the densest part of a real capture (a third of the frame), so two of them
# cost more than a whole view (a view's cost there is mostly per Gaussian) and gain
# nothing over one. A box around tiny objects keeps two: with one crop a step, fewer of
# its objects are recovered (docs/promptgs.md, "Views in a related step").
CENTRE_PROMPT_VIEWS_PER_STEP = 1
# Those crops also take every training view that sees the centre box in turn, not only
# the RELATED_VIEWS (8) most relevant (`PromptFocus.set_prompts`): the box marks where all
# the cameras look, not an object that some views see best, and training its crops from
# a few views only loses PSNR in the others (docs/promptgs.md, "Views in a related step").
# The view schedule of a run whose only prompt is the centre box: one related step in a
# cycle of nine, where other runs have two in ten (`views.DEFAULT_RATIO`); the whole-view
# steps are the same (8 per cycle), so 1500 iterations take 1688 steps, not 1875. The box
# marks no object, and its crops train the densest part of the frame again: the second
# related step costs time and does not raise PSNR.
CENTRE_PROMPT_RATIO = (2, 3, 1, 3)
# While densification runs, every FULL_SIZE_EVERY-th single-view step renders the whole
# view at full size with 3DGS's screen filter: the growth statistics outside the prompts
# come from those alone, so that PromptGS grows there as 3DGS would.
FULL_SIZE_EVERY = 2
# From this fraction of the densification window on, every single-view step does. Late in
# a long run most Gaussians sit just under 3DGS's threshold, and a mean gradient over a
# third of 3DGS's views crosses it by chance more often, so PromptGS would end over 3DGS's
# count. Voting with every single-view step from the start of densification (or from a
# quarter of the window) meets the count but costs the prompts' objects.
EVERY_SINGLE_VIEW_FROM = 0.5
# Screen filter (px²) of the low-resolution steps: 3DGS's. Below full size the run's
# narrower filter (0.1) lets the terrain alias.
LOW_RES_SCREEN_FILTER = BASELINE_SCREEN_FILTER
# Screen filter of the statistics steps (`PromptFocus.is_statistics_step`): 3DGS's. Under
# the narrow filter a flat surface drawn by Gaussians smaller than a pixel shows gaps,
# their gradients rise, and growth fills them with more Gaussians than 3DGS grows.
STATISTICS_SCREEN_FILTER = BASELINE_SCREEN_FILTER


@dataclass
class LiveModel:
    """The model as the prompt bookkeeping sees it after a step: the Gaussians, their
    optimisers and the strategy's state (resampling and proposal seeds add Gaussians to
    all three, in place), the run's render of one camera (`train.Trainer.render_camera`)
    and the SH degree the run trains at this step."""

    params: torch.nn.ParameterDict
    optimizers: dict[str, torch.optim.Optimizer]
    state: dict[str, Any]
    render_camera: Callable[[Camera], tuple[torch.Tensor, torch.Tensor, dict]]
    sh_degree: int


# Bytes of ground-truth edge maps kept between steps (`ReferenceEdges`).
REFERENCE_EDGE_BYTES = 256 << 20


class ReferenceEdges(BoundedCache):
    """Sobel magnitudes (`losses.sobel_magnitude`) of the views' ground truth, kept between
    steps: the per-view loss compares a render's edges with its reference's, and the
    reference of a view (or of a crop of it) does not change. Least recently used first
    out, bounded in bytes."""

    def __init__(self, max_bytes: int = REFERENCE_EDGE_BYTES) -> None:
        super().__init__(max_bytes)

    def of(self, view: TrainView) -> torch.Tensor:
        """[H, W, 3] edge magnitudes of ``view.gt``, computed on first use."""
        key = (view.source, view.camera.width, view.camera.height, view.window, str(view.gt.device))
        edges = self._held(key)
        if edges is None:
            edges = sobel_magnitude(view.gt[None])[0]
            self._hold(key, edges)
        return edges


def crop_camera(camera: Camera, x0: int, y0: int, width: int, height: int) -> Camera:
    """The sub-window [x0, x0+width) × [y0, y0+height) of ``camera`` as its own camera."""
    K = camera.K.clone()
    K[0, 2] -= x0
    K[1, 2] -= y0
    return dataclasses.replace(camera, width=width, height=height, K=K)


def load_prompt_setting(cfg, scene=None) -> list[PromptBox]:
    """The prompt boxes a config asks for: a file or inline object, and/or the centre box
    (defined in ``scene``'s own frame: `prompts.scene_center_prompt`), which comes last."""
    boxes: list[PromptBox] = []
    if cfg.prompts is not None:
        if isinstance(cfg.prompts, (dict, list)):
            boxes += prompts_from_json(cfg.prompts, source="job file prompts")
        else:
            boxes += load_prompts(cfg.prompts)
    if cfg.center_prompt:
        if scene is None:
            raise PromptError("the centre prompt needs the scene (its cameras and points)")
        box = scene_center_prompt(scene.train_cameras, scene.points)
        log.info("centre prompt at %s, edge %.4g", [round(v, 4) for v in box.center], box.size[0])
        boxes.append(box)
    return boxes


def run_length(cfg) -> int:
    """Entries of the run's view schedule (steps, or views with several views a step).

    ``--iterations`` counts the steps that train whole views. A PromptGS run with prompts
    (a file, the centre box, or boxes found during the run) adds its related steps, which
    train crops around the prompts, on top: 1500 iterations take 1875 steps at 2:3:2:3
    (1688 at `CENTRE_PROMPT_RATIO`, the centre box alone), so the scene outside the
    prompts gets as many optimisation steps as under 3DGS (taken out of the iterations
    instead, they leave the rest of the scene fewer steps and lower its PSNR). The trainer
    stretches 3DGS's schedule for ``cfg.iterations`` over the whole run (as many growth
    rounds and opacity resets as the 3DGS run); the learning-rate decay and the
    progressive levels span it too. Other runs: ``cfg.iterations``."""
    focused = cfg.strategy == "promptgs" and (
        cfg.prompts is not None or cfg.center_prompt or bool(cfg.auto_prompts) or cfg.propose_prompts
    )
    return entries_with_related_steps(cfg.iterations, view_ratio(cfg)) if focused else int(cfg.iterations)


def view_ratio(cfg) -> tuple[int, int, int, int]:
    """The view schedule's cycle for a PromptGS run: `CENTRE_PROMPT_RATIO` when the centre
    box is the run's only prompt (no prompt file, no automatic or proposed prompts, which
    may arrive during the run), else the paper's 2:3:2:3."""
    centre_only = cfg.center_prompt and cfg.prompts is None and not cfg.auto_prompts and not cfg.propose_prompts
    return CENTRE_PROMPT_RATIO if centre_only else DEFAULT_RATIO


def warn(line: str) -> None:
    """A warning for the user: in the run's log, and on stderr (stdout may carry events)."""
    log.warning(line)
    print(f"promptgs: warning: {line}", file=sys.stderr)


def available_memory_bytes() -> int:
    try:
        return int(os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE"))
    except (ValueError, OSError, AttributeError):
        return 4 << 30


class PromptFocus:
    """The prompt side of a PromptGS run (module docstring): it plans each step's views,
    observes each step's losses, and after a step resamples in the prompts and adds the
    prompts that the error field or the proposer find.

    It is given what it reads: the run's settings (``cfg``), the ``scene``, the stretched
    3DGS ``schedule`` and the run's ``total_steps``, the PromptGS ``strategy`` it keeps
    informed of the prompts, the ``device`` ground truth goes to, the starting ``prompts``
    (`load_prompt_setting`) and, with ``--propose-prompts``, the ``proposer``. The
    Gaussians it may grow come with each call that grows them (`LiveModel`)."""

    def __init__(
        self,
        cfg: TrainConfig,
        scene: Scene,
        schedule: DefaultSchedule,
        total_steps: int,
        strategy: PromptGSStrategy,
        device: torch.device,
        prompts: list[PromptBox],
        proposer: TrainingProposer | None = None,
        max_views: int = 2,
        related_k: int = RELATED_VIEWS,
        field_every: int = 10,
    ):
        self.growth_schedule = schedule
        self.total_steps = total_steps
        self.strategy = strategy
        self.device = device
        self.cameras = scene.train_cameras
        self.points = scene.points
        self.base_downscale = cfg.downscale
        self.full_cameras = [c.downscaled(self.base_downscale) for c in self.cameras]
        self.prompts: list[PromptBox] = []
        self.related: list[list[int]] = []
        self.related_k = related_k
        self.field_every = field_every  # the field moves slowly; back-projecting every step costs ~10% of a step
        self.field = ErrorField.from_extent(scene.extent, resolution=128)
        self.reference_edges = ReferenceEdges()
        self.auto_prompts = int(cfg.auto_prompts or 0)
        self.auto_prompt_step = None
        if self.auto_prompts:
            self.auto_prompt_step = schedule.densification_step(0.25)
        self.proposer = proposer
        self.resample_every = max(2 * schedule.refine_every, 20)
        self.progressive = cfg.progressive if cfg.progressive is not None else True
        cam0 = self.full_cameras[0]
        bytes_per_view = cam0.width * cam0.height * 4 * 64  # image, alpha, depth and their gradients
        cap = views_cap_from_memory(bytes_per_view, available_memory_bytes(), max_views=max_views)
        self.schedule = ViewSchedule(len(self.cameras), max_views_per_step=max(cap, 1), seed=cfg.seed, ratio=view_ratio(cfg))
        self.generator = torch.Generator().manual_seed(cfg.seed)
        # The centre box (`load_prompt_setting` puts it last): its related steps take
        # CENTRE_PROMPT_VIEWS_PER_STEP views.
        self.centre_prompt = prompts[-1] if cfg.center_prompt and prompts else None
        # The boxes the user drew (not the centre box; proposals come later): resampling
        # votes for fainter errors in them (`carve_error_threshold`).
        self.drawn_prompts = [p for p in prompts if p != self.centre_prompt]
        # When a list, observe() leaves error-field points here instead of adding them
        # (a batched step adds every rank's points in batch order).
        self.field_sink: list | None = None
        self.set_prompts(prompts)

    # -- prompts ----------------------------------------------------------------------

    def set_prompts(self, prompts: list[PromptBox]) -> None:
        if prompts:
            check_visible(prompts, self.full_cameras, source="prompts")
            for line in placement_warnings(prompts, self.full_cameras, self.points, [c.name for c in self.full_cameras]):
                warn(line)
        self.prompts = list(prompts)
        self.related = related_views(self.prompts, self.full_cameras, self.related_k) if self.prompts else []
        # Focused multiview steps need a few views that agree; a prompt seen by fewer
        # than MIN_RELATED_VIEWS training cameras gets none (its related steps become
        # random multiview steps): cropping the same one or two views over and over fits
        # them at the others' expense.
        for i, views in enumerate(self.related):
            if len(views) < MIN_RELATED_VIEWS:
                warn(f"prompt {i} is seen by {len(views)} training cameras (fewer than {MIN_RELATED_VIEWS}): no focused views for it")
        # The centre box's crops rotate over every training view that sees it (see
        # CENTRE_PROMPT_VIEWS_PER_STEP); resampling still votes in its related_k best views.
        regions = [
            top_k_views(p, self.full_cameras, len(self.full_cameras)) if p == self.centre_prompt else v
            for p, v in zip(self.prompts, self.related)
        ]
        self.schedule.set_regions(
            [v if len(v) >= MIN_RELATED_VIEWS else [] for v in regions],
            views_per_step=[CENTRE_PROMPT_VIEWS_PER_STEP if p == self.centre_prompt else None for p in self.prompts],
        )
        self.strategy.set_prompts(self.prompts)
        log.info("%d prompts; related views %s", len(self.prompts), self.related)

    # -- views ------------------------------------------------------------------------

    def downscale_at(self, step: int) -> int:
        """Extra downscale of full-image steps under the progressive schedule: 8×, 4×, 2×
        for 7/30 of the run each, then full size, as in the paper. A level that would
        leave fewer than MIN_PROGRESSIVE_WIDTH pixels across uses the coarsest one that
        does not, so the low-resolution phase keeps its 70% of the run (a 480 px view:
        4×, 4×, 2×; a 320 or 252 px view: 2× three times; under 200 px, none). Skipping such levels instead started
        full-size steps at 47% of the run, and the one-box mountain run took 1.70× the
        3DGS time against 1.27×."""
        if not self.progressive:
            return 1
        width = self.full_cameras[0].width
        coarsest = max([1] + [f for f in PROGRESSIVE_LEVELS if width // f >= MIN_PROGRESSIVE_WIDTH])
        levels = [min(f, coarsest) for f in PROGRESSIVE_LEVELS]
        stage = int(step / (PROGRESSIVE_FRACTION * self.total_steps))
        return levels[stage] if stage < len(levels) else 1

    def full_size_step(self) -> int:
        """The first step whose whole-view renders are at full size (`downscale_at` is 1
        from there on; 0 without the progressive schedule). `downscale_at` never rises with
        the step, so a binary search finds it (`compaction_step` asks after every step)."""
        return bisect.bisect_left(range(self.total_steps), True, key=lambda s: self.downscale_at(s) == 1)

    def every_single_view_step(self) -> int:
        """The first step from which every single-view step of the densification window is
        a statistics step (`EVERY_SINGLE_VIEW_FROM` of the window; before it, every
        FULL_SIZE_EVERY-th one)."""
        return self.growth_schedule.densification_step(EVERY_SINGLE_VIEW_FROM)

    def is_statistics_step(self, step: int, kind: str, entry: int | None = None) -> bool:
        """Whether a single-view step is a statistics step: while densification runs, every
        FULL_SIZE_EVERY-th one (schedule ``entry``, the step itself at one entry a step),
        and every one from `every_single_view_step` on. It renders the whole view at full
        size (although the progressive schedule may be below it) with 3DGS's screen
        filter, and the PromptGS strategy takes the growth statistics of the Gaussians
        outside the prompts from these steps alone: outside the prompts they grow where
        3DGS's would, measured as 3DGS measures (about 30% of the steps in the first half
        of the window, 60% in the second)."""
        sched = self.growth_schedule
        if step >= sched.refine_stop_iter or kind != SINGLE:
            return False
        entry = step if entry is None else entry
        return step >= self.every_single_view_step() or entry % FULL_SIZE_EVERY == 0

    def _crop_views(self, region: int, views: list[int]) -> list[TrainView]:
        box = self.prompts[region]
        boxes = []
        for v in views:
            bbox = project_box(box, self.full_cameras[v]).pixel_bbox()
            if bbox is not None:
                boxes.append((v, bbox))
        if not boxes:
            return []
        margin = 8
        w = max(b[2] - b[0] for _, b in boxes) + 2 * margin
        h = max(b[3] - b[1] for _, b in boxes) + 2 * margin
        out = []
        for v, (x0, y0, x1, y1) in boxes:
            cam = self.full_cameras[v]
            cw, ch = max(min(w, cam.width), 16), max(min(h, cam.height), 16)
            cx0 = min(max((x0 + x1) // 2 - cw // 2, 0), cam.width - cw)
            cy0 = min(max((y0 + y1) // 2 - ch // 2, 0), cam.height - ch)
            gt = cam.load_image(window=(cx0, cy0, cw, ch), device=self.device)
            out.append(TrainView(crop_camera(cam, cx0, cy0, cw, ch), gt, v, crop=True, window=(cx0, cy0, cw, ch)))
        # A batch renders at one size: keep the views whose crop matches the first.
        size = (out[0].camera.width, out[0].camera.height)
        return [t for t in out if (t.camera.width, t.camera.height) == size]

    def plan(self, step: int, entry: int | None = None) -> list[TrainView]:
        """The views of schedule ``entry`` (default: ``step``, one entry a step) at
        training step ``step``; a batch of several views a step takes several entries
        (batch.py)."""
        entry = step if entry is None else entry
        batch = self.schedule.batch(entry)
        if batch.kind == RELATED_MULTIVIEW and batch.region is not None and self.prompts:
            views = self._crop_views(batch.region, batch.views)
            if views:
                return views
        statistics = self.is_statistics_step(step, batch.kind, entry)
        factor = 1 if statistics else self.downscale_at(step)
        screen_filter = STATISTICS_SCREEN_FILTER if statistics else LOW_RES_SCREEN_FILTER if factor > 1 else None
        out = []
        for v in batch.views:
            cam = self.full_cameras[v].downscaled(factor)
            out.append(TrainView(cam, cam.load_image(device=self.device), v, screen_filter=screen_filter, statistics=statistics))
        size = (out[0].camera.width, out[0].camera.height)
        return [t for t in out if (t.camera.width, t.camera.height) == size]

    # -- after each step --------------------------------------------------------------

    def feeds_field(self, step: int) -> bool:
        """Whether this step's losses go into the error field (it then needs the depth)."""
        return step % self.field_every == 0

    @torch.no_grad()
    @one_thread()  # small element-wise work: faster without waking a thread (threads.py)
    def observe(
        self,
        step: int,
        views: list[TrainView],
        rendered: torch.Tensor,
        l1_map: torch.Tensor,
        dssim_map: torch.Tensor,
        depth: torch.Tensor | None,
        alpha: torch.Tensor,
        info: dict,
    ) -> None:
        """Per-pixel errors for the strategy, and per-view losses on the steps whose
        statistics it takes (`PromptGSStrategy.takes_statistics`); every ``field_every``
        steps, feed the error field. ``l1_map`` and ``dssim_map`` are [C, H, W] (the maps
        the training loss was computed from, detached); ``depth`` [C, H, W] is needed on
        the steps that `feeds_field`, and may be None on the others."""
        info["error_map"] = l1_map
        info["crop_step"] = any(v.crop for v in views)
        # Only statistics steps vote for growth outside the prompts (see is_statistics_step).
        info["votes_outside"] = all(v.statistics for v in views)
        # Below full resolution (progressive schedule); a crop is at full resolution.
        info["downscale"] = 1.0 if info["crop_step"] else self.full_cameras[views[0].source].width / views[0].camera.width
        if self.strategy.takes_statistics(step, info):  # the per-view losses weigh the scores
            ref_edges = torch.stack([self.reference_edges.of(v) for v in views]).to(rendered.device)
            info["view_loss"] = (
                LAMBDA_L1 * l1_map.mean(dim=(1, 2)) + LAMBDA_DSSIM * dssim_map.mean(dim=(1, 2))
                + LAMBDA_EDGE * edge_losses_to(rendered, ref_edges)
            )
        if not self.feeds_field(step):
            return
        loss_map = 0.8 * l1_map + 0.2 * dssim_map
        for i, v in enumerate(views):
            if self.field_sink is not None:  # a batched step adds every rank's points in order
                self.field_sink.append(self.field.view_points(loss_map[i], depth[i], alpha[i], v.camera, top_q=0.1))
            else:
                self.field.accumulate(loss_map[i], depth[i], alpha[i], v.camera, step=step, top_q=0.1)

    def after_step(self, step: int, model: LiveModel) -> None:
        """After step ``step``: add the error field's prompts (``--auto-prompts``) or the
        proposer's (``--propose-prompts``) at their steps, and resample in the prompts at
        the resampling steps, growing ``model``."""
        if self.auto_prompt_step is not None and step == self.auto_prompt_step:
            proposals = self.field.peaks(self.auto_prompts)
            visible = []
            for box in proposals:
                try:
                    check_visible([box], self.full_cameras)
                    visible.append(box)
                except PromptError:
                    continue
            log.info("step %d: %d automatic prompts from the error field", step, len(visible))
            self.set_prompts(self.prompts + visible)
        if self.proposer is not None and self.proposer.is_step(step):
            self.set_prompts(self.prompts + self.proposer.run(step, self.prompts, model.params, model.sh_degree))
            self.seed_proposals(step, model, self.proposer.trained)
        if self.prompts and self.is_resample_step(step):
            self.resample(step, model)

    def is_resample_step(self, step: int) -> bool:
        """Resampling steps, counted from the last opacity reset: the first one refinement
        interval after it, then every ``resample_every`` steps. Right after a reset every
        opacity is clamped low, the render is mostly empty and every pixel looks wrong, so
        carving then would scatter Gaussians through the whole box."""
        sched = self.growth_schedule
        if not sched.refine_start_iter < step < sched.refine_stop_iter:
            return False
        since_reset = step % sched.reset_every
        return since_reset >= sched.refine_every and (since_reset - sched.refine_every) % self.resample_every == 0

    def carve_error_threshold(self, box: PromptBox) -> float:
        """The least per-pixel error that votes for resampling in ``box``: lower in a box
        the user drew around objects than in one the run made (a proposal, the centre box);
        `strategies.promptgs.CARVE_ERROR_THRESHOLD` says why."""
        if box in self.drawn_prompts:
            return self.strategy.carve_drawn_error_threshold
        return self.strategy.carve_error_threshold

    @torch.no_grad()
    def resample(self, step: int, model: LiveModel) -> int:
        """Carve each prompt from its related views' crops (`strategies.promptgs.carve_prompt`)
        and add the consistent high-error points to ``model`` as small Gaussians, within
        the strategy's budget; the number added."""
        added = 0
        for region, box in enumerate(self.prompts):
            views = self._crop_views(region, self.related[region])
            if len(views) < 3:
                continue
            triples = []
            for view in views:
                img, _, _ = model.render_camera(view.camera)
                triples.append((view.camera, img.clamp(0, 1).cpu(), view.gt.cpu()))  # carving runs on the CPU
            budget = self.strategy.effective_budget(model.state)
            room = None if budget is None else max(budget - int(model.params["means"].shape[0]), 0)
            max_points = 1000 if room is None else min(1000, room)
            if max_points <= 0:
                break
            carved = carve_prompt(
                box, triples, max_points=max_points, error_threshold=self.carve_error_threshold(box),
                max_candidates=self.strategy.carve_max_candidates, generator=self.generator, opacity=RESAMPLED_OPACITY,
            )
            if carved.means.shape[0]:
                jitter = (torch.rand(carved.means.shape, generator=self.generator) - 0.5) * carved.voxel * 0.5
                added += append_gaussians(
                    model.params, model.optimizers, model.state, carved.means + jitter, carved.colors,
                    scale=carved.voxel * 0.7, opacity=RESAMPLED_OPACITY, step=step,
                )
        if added:
            self.strategy.record_resampled(model.state, added)
            log.info("step %d: resampled %d Gaussians in prompts", step, added)
        return added

    @torch.no_grad()
    def seed_proposals(self, step: int, model: LiveModel, proposals) -> int:
        """One small Gaussian at each proposal's triangulated point (``proposals.Proposal``),
        of its candidates' median image colour, ``SEED_SCALE_PX`` pixels wide at its
        depth, opacity `RESAMPLED_OPACITY`: the point that SfM did not triangulate. The
        ledger counts it with the resampled Gaussians, but it is judged as one grown in a
        prompt (protected from pruning for ``protect_steps``), not as a resampled one:
        several views agreed on it. Judged as resampled, a seed could be removed as idle
        (`strategies.promptgs.PromptGSStrategy.idle_resampled`) before the related steps
        had fitted it, and objects whose proposals lay right on them were lost."""
        added = 0
        for p in proposals:
            added += append_gaussians(
                model.params, model.optimizers, model.state, torch.tensor([p.point], dtype=torch.float32),
                torch.tensor([p.colour], dtype=torch.float32), scale=SEED_SCALE_PX * p.pixel,
                opacity=RESAMPLED_OPACITY, step=step, carved=False,
            )
        if added:
            self.strategy.record_resampled(model.state, added)
            log.info("step %d: seeded %d Gaussians at proposed points", step, added)
        return added

    # -- outputs ----------------------------------------------------------------------

    def field_arrays(self) -> dict[str, Any]:
        arrays = self.field.to_arrays(self.prompts) if len(self.field) else {}
        if self.proposer is not None:
            arrays.update(self.proposer.arrays())
        return arrays

    def state_dict(self) -> dict:
        return {"prompts": [p.to_dict() for p in self.prompts], "field": self.field.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.field.load_state_dict(state["field"])
        self.set_prompts(prompts_from_json({"prompts": state["prompts"]}, source="checkpoint"))
