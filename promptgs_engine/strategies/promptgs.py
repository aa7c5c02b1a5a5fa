"""The PromptGS densification strategy: Gaussian scoring, prompt-prioritised growth,
protection of young Gaussians in prompts, and attention-guided resampling.

Outside the prompt boxes it behaves as the 3DGS strategy (gsplat's DefaultStrategy, with
the opacity reset applied). Inside them:

* **Score.** Each Gaussian accumulates, over the views that see it since the last
  refinement, ``S_g = Σ_i P^i · F(∇_g + d_g^i + o_g + s_g + r_g)`` (paper Eq. 2), where
  ``P^i = λ1·L1 + λ2·D-SSIM + λ3·L_edge`` is view i's loss (Eq. 3) and the terms are
  normalised so that 1 means "at the densification threshold":
  ``∇_g`` = view-space gradient / grow_grad2d, ``d_g^i`` = 1 / (1 + depth / scene_scale)
  (near Gaussians count more), ``o_g`` = opacity, ``s_g`` = largest scale /
  (grow_scale3d · scene_scale), ``r_g`` = screen radius / (grow_scale2d · image size);
  each term is clamped to [0, 4] and ``F(x) = log(1 + x)`` keeps one huge term from
  dominating (`score_terms`). Growth ranks by the mean per view.
* **Prioritised growth inside the prompts** (`prompt_growth`). At each refinement a quota
  of the prompts' Gaussians grows, and the score distribution sets it: the number whose
  score lies above Tukey's upper fence ``Q3 + 1.5 · IQR`` of the prompts' scores
  (`prompt_quota`), the long tail of "abnormally high" scores that the paper's Fig. 2
  shows densification bringing down. The quota goes to the highest priority, score ×
  ``(1 + attention)`` (the error field fused with the prompt weight), among those whose
  priority clears the same fence: the attention field decides where the quota goes. No
  gradient threshold selects anything inside the prompts.
* **Outside the prompts**, growth is 3DGS's rule (mean view-space gradient over 3DGS's
  threshold), less what the prompts add beyond that rule: the prompts' growth over what
  the rule would have grown inside them, and the resampled Gaussians that have stayed
  (`resampled_that_stayed`). The outside candidates with the smallest gradients give
  way, and what they cannot offset is carried to the next refinement
  (``state["debt"]``): the prompts move Gaussians to where they point rather than add
  them. A ``budget`` caps the total, prompt Gaussians first.
* **Growth statistics as 3DGS measures them.** A whole-view step below full size
  (``info["downscale"] > 1``) trains but adds nothing to the statistics. Outside the
  prompts only the trainer's statistics steps vote (``info["votes_outside"]``: whole
  views at full size with 3DGS's 0.3 px² screen filter,
  `focus.PromptFocus.is_statistics_step`): crops would densify the background of a
  prompt over and over, and under PromptGS's narrow filter a flat surface drawn by
  Gaussians smaller than a pixel shows gaps whose gradients grow it (a 64 px toy scene
  grew 82k Gaussians against 3DGS's 65k that way). Low-resolution gradients grew about
  twice the 3DGS count on the mountain (docs/promptgs.md).
* **Enough votes outside** (``outside_min_votes``, 3). The statistics steps are about
  30% of the steps over the first half of densification (60% over the second,
  `focus.EVERY_SINGLE_VIEW_FROM`), so an outside Gaussian's mean gradient rests on a few
  views (a median of 3–4 per refinement interval on the sparse mountain at 1500 steps,
  before the second half's steps were added) where 3DGS
  averages over every step. A mean of few samples crosses the threshold by chance far
  more often: the sparse mountain grew 100k Gaussians outside its box where 3DGS grew 84k
  in all. Outside, the summed gradient is divided by at least three views: a Gaussian
  seen by one statistics step grows only on three times the threshold (the ledger's
  ``few_votes`` counts the candidates held back); holding back every Gaussian seen by
  fewer than three, tried first, is harsher (docs/promptgs.md).
* **Resampled Gaussians earn their keep** (`idle_resampled`): one that is still under
  ``carve_keep_opacity`` (0.05) a refinement interval after it came, and after the last
  opacity reset, is removed at the next refinement. Carving adds up to a thousand points
  a round where the render is wrong; most land on surfaces that the rest of the model
  fits soon after. Only those that stay cost outside growth, once, when they are judged
  (the ledger's ``resampled_stayed``): charged on arrival, a round that was mostly removed
  a refinement later had held back 3DGS's growth outside early in training, where growth
  compounds. The last round, which no refinement follows, is judged once at
  ``last_round_judgement_step`` (`LAST_ROUND_JUDGED_AT` of the run) by the same bar.
* **Protection.** Other Gaussians born inside a prompt (by growth or resampling) are not
  pruned for ``protect_steps`` steps, so the first opacity prune does not remove an
  object before it has been seen from enough views.
* **Ledger.** ``state["ledger"]`` (``train.json`` "growth") counts what grew inside and
  outside, what resampling added and what was removed, per refinement.
* **Resampling** (`carve_prompt`): inside a prompt box, candidate points on a voxel grid
  are projected into the box's most relevant views; a point is kept where the current
  render is wrong (high error at its pixel) in most of the views that see it — a
  multi-view-consistent vote that recovers objects SfM missed entirely.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, ClassVar, Sequence

import torch
import torch.nn.functional as F
from gsplat.strategy.ops import _update_param_with_optimizer, remove

from ..gaussians import rgb_to_sh
from ..prompts import PromptBox, boxes_contain
from ..threads import one_thread
from .default import STATISTICS_MERGED, ResettingDefaultStrategy, step_grad2d_norms, step_visible

# Above this fraction of the Gaussians inside the prompts, growth there uses the normal
# 3DGS threshold (see growth_candidates).
MAX_FOCUS_FRACTION = 0.5

# Weights of the per-view loss P^i (Eq. 3).
LAMBDA_L1 = 0.8
LAMBDA_DSSIM = 0.2
LAMBDA_EDGE = 0.5


# Tukey's upper fence: scores above Q3 + TUKEY_K · IQR are the long tail that grows.
TUKEY_K = 1.5

# Carving: the least per-pixel error (mean abs over the channels, 0..1) that votes for a
# resampled point; above it, a view's own bar is 3× its median error, so a noisy image
# sets a higher one. CARVE_ERROR_THRESHOLD holds for boxes the run made (proposals, the
# centre box); DRAWN_CARVE_ERROR_THRESHOLD for boxes the user drew around objects. A drone
# of two pixels over terrain of a similar colour differs from it by only a few hundredths,
# so a drawn box, which marks objects, takes the faint ones too. A proposed box already
# holds its object's Gaussian (`focus.PromptFocus.seed_proposals`), and the low bar there
# fills it with the terrain around it; the centre box holds a whole real capture, whose
# texture a short run misses by a few hundredths everywhere, so the low bar would carve
# it all. docs/promptgs.md, "Resampling: faint objects".
CARVE_ERROR_THRESHOLD = 0.08
DRAWN_CARVE_ERROR_THRESHOLD = 0.03

# Resampling's last round comes at a refinement that no refinement follows, so nothing
# would judge it (`PromptGSStrategy.idle_resampled`) and its faint Gaussians, most under
# carve_keep_opacity, would stay to the end. It is judged once, at this fraction of the
# run's steps, by the same bar. Not one refinement interval after it came, as the other
# rounds are: the objects' Gaussians are still faint then and brighten later, and that
# judgement removed them.
LAST_ROUND_JUDGED_AT = 0.8


def prompt_quota(scores: torch.Tensor) -> tuple[int, float]:
    """How many Gaussians of the prompts grow at one refinement, from the distribution of
    their scores (mean score per view since the last refinement): those above Tukey's
    upper fence, ``Q3 + 1.5 · IQR``. The scores are long-tailed (the paper's Fig. 2); the
    tail beyond the fence is the "abnormally high" part that densification should bring
    down, and as it shrinks so does the quota. Returns ``(quota, fence)``."""
    if scores.numel() == 0:
        return 0, float("inf")
    q1, q3 = torch.quantile(scores.double(), torch.tensor([0.25, 0.75], dtype=torch.float64, device=scores.device)).tolist()
    fence = q3 + TUKEY_K * (q3 - q1)
    return int((scores > fence).sum()), float(fence)


def score_terms(
    params, info: dict[str, Any], scene_scale: float, grow_grad2d: float, grow_scale3d: float, grow_scale2d: float, absgrad: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The per-view part of the score, ``F(∇_g + d_g^i + o_g + s_g + r_g)`` of Eq. 2, for
    every (view, Gaussian) pair the step rendered: ``(view index, Gaussian index, value)``.
    Each term is normalised so that 1 means "at the densification threshold" and clamped
    to [0, 4]; ``F = log1p``. Needs the step's ``means2d`` gradient."""
    radii = info["radii"]  # [C, N, 2]
    n = radii.shape[1]
    visible = step_visible(info)  # [C, N]
    # Pairs as flat indices camera · N + Gaussian (the order of ``torch.where(visible)``):
    # one-index gathers are several times faster than two-index ones on the CPU.
    pairs = visible.reshape(-1).nonzero().squeeze(1)
    cam_ids, gs_ids = pairs // n, pairs % n
    if pairs.numel() == 0:
        return cam_ids, gs_ids, torch.zeros(0, device=radii.device)
    w, h = info["width"], info["height"]
    g = (step_grad2d_norms(info, "means2d", absgrad).reshape(-1)[pairs] / grow_grad2d).clamp(0, 4)
    depth = info["depths"].reshape(-1)[pairs]
    d = 1.0 / (1.0 + depth.clamp_min(0) / scene_scale)
    o = torch.sigmoid(params["opacities"][gs_ids])
    scales = torch.exp(params["scales"][gs_ids])
    s = (torch.maximum(torch.maximum(scales[:, 0], scales[:, 1]), scales[:, 2]) / (grow_scale3d * scene_scale)).clamp(0, 4)
    pair_radii = radii.reshape(-1, 2)[pairs]
    r = (torch.maximum(pair_radii[:, 0], pair_radii[:, 1]) / (grow_scale2d * max(w, h))).clamp(0, 4)
    return cam_ids, gs_ids, torch.log1p(g + d + o + s + r)


def new_ledger() -> dict[str, Any]:
    """Where a run's Gaussians come from and go (see `PromptGSStrategy`): totals, and one
    entry per refinement."""
    return {"grown_inside": 0, "grown_outside": 0, "resampled": 0, "resampled_removed": 0, "pruned_inside": 0,
            "pruned_outside": 0, "refinements": []}


@dataclass
class PromptGSStrategy(ResettingDefaultStrategy):
    prompts: list = field(default_factory=list)  # list[PromptBox]
    outside_offset: bool = True  # outside growth gives way to the prompts' extra growth
    outside_min_votes: int = 3  # outside, the mean gradient is taken over at least this many views
    protect_steps: int = 500
    carve_error_threshold: float = CARVE_ERROR_THRESHOLD  # least per-pixel error that votes for resampling
    carve_drawn_error_threshold: float = DRAWN_CARVE_ERROR_THRESHOLD  # the same in a box the user drew
    carve_max_candidates: int = 2_000_000  # grid points tried per box; beyond it the grid coarsens
    carve_keep_opacity: float = 0.05  # a resampled Gaussian still fainter after a refinement interval is removed
    last_round_judgement_step: int | None = None  # judge resampled Gaussians no refinement judged (None: never)
    attention_fn: Any = None  # callable(points [N,3]) -> attention [N] in [0, 2], or None
    keeps_default_ledger: ClassVar[bool] = False  # its own ledger: new_ledger()

    def initialize_state(self, scene_scale: float = 1.0) -> dict[str, Any]:
        state = super().initialize_state(scene_scale)
        # score / error: sums over the views that saw each Gaussian; views: how many.
        # (gsplat's own `count` is zeroed at every refinement, these are not.)
        # carved: 1 for Gaussians that resampling added (and their grown copies).
        # charged: 1 for resampled Gaussians already offset against outside growth.
        state.update({"score": None, "error": None, "views": None, "born": None, "carved": None, "charged": None})
        # Gaussians resampled into the prompts since the last refinement.
        state["resampled"] = 0
        # Prompt growth 3DGS's rule would not make, not yet offset by outside growth.
        state["debt"] = 0
        state["ledger"] = new_ledger()
        return state

    def record_resampled(self, state: dict[str, Any], n: int) -> None:
        """Count Gaussians added to the prompts by resampling (outside growth gives way)."""
        state["resampled"] = state.get("resampled", 0) + int(n)
        state.setdefault("ledger", new_ledger())["resampled"] += int(n)

    def set_prompts(self, prompts: Sequence[PromptBox]) -> None:
        self.prompts = list(prompts)

    def inside_prompts(self, means: torch.Tensor) -> torch.Tensor:
        if not self.prompts:
            return torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
        return boxes_contain(self.prompts, means.detach()).any(dim=0)

    def inside_prompts_seen(self, means: torch.Tensor, visible: torch.Tensor) -> torch.Tensor:
        """`inside_prompts` for the Gaussians a step rendered (``visible`` [C, N] in some
        view, `step_visible`); the others are False on the CPU, where only the rendered
        ones are tested (a crop sees about a quarter of them). On a GPU every Gaussian is
        tested: a gather by a count of visible ones would make the host wait."""
        if means.device.type != "cpu":
            return self.inside_prompts(means) & visible.any(dim=0)
        inside = torch.zeros(means.shape[0], dtype=torch.bool, device=means.device)
        if self.prompts:
            ids = visible.any(dim=0).nonzero().squeeze(1)
            inside[ids] = boxes_contain(self.prompts, means.detach()[ids]).any(dim=0)
        return inside

    # -- statistics -------------------------------------------------------------------

    @staticmethod
    def low_resolution(info: dict) -> bool:
        """A step rendered below full size (progressive schedule): it trains but takes no
        statistics."""
        return float(info.get("downscale", 1.0)) > 1.0

    def takes_statistics(self, step: int, info: dict) -> bool:
        """Whether `step_post_backward` will read this step's statistics, ``view_loss``
        among them: gsplat's rule (before ``refine_stop_iter``) and ours (not at low
        resolution). The trainer computes the per-view losses only then."""
        return step < self.refine_stop_iter and not self.low_resolution(info)

    def _ensure_state(self, params, state) -> None:
        n = params["means"].shape[0]
        device = params["means"].device
        for key in ("score", "error", "views"):
            if state[key] is None:
                state[key] = torch.zeros(n, device=device)
        for key in ("born", "carved", "charged"):
            if state.get(key) is None:
                state[key] = torch.zeros(n, device=device)

    @one_thread()  # small element-wise work: faster without waking a thread (threads.py)
    def _update_state(self, params, state, info, packed: bool = False) -> None:
        if info.get(STATISTICS_MERGED):  # a batched step added its views' statistics (batch.py)
            return
        if self.low_resolution(info):
            # A low-resolution step trains but does not vote for growth.
            for key in ("grad2d", "count"):
                if state.get(key) is None:
                    state[key] = torch.zeros(params["means"].shape[0], device=params["means"].device)
            self._ensure_state(params, state)
            return
        # Outside the prompts, only the trainer's statistics steps (``votes_outside``:
        # whole views at full size with 3DGS's screen filter) count towards growth. A crop
        # step renders the region around a prompt at full resolution, over and over, and
        # would densify the terrain behind a drone group far beyond what 3DGS gives it;
        # under the narrow filter, flat surfaces show gaps whose gradients grow them.
        votes_outside = info.get("votes_outside", not info.get("crop_step", False))
        if votes_outside or state.get("grad2d") is None:
            super()._update_state(params, state, info, packed=packed)
        else:  # packed radii are per visible pair, not [C, N, 2]: test every Gaussian then
            means = params["means"]
            inside = self.inside_prompts(means) if packed else self.inside_prompts_seen(means, step_visible(info))
            self.add_statistics(params, state, info, packed=packed, only=inside)
        self._ensure_state(params, state)
        if "view_loss" not in info:
            return
        with torch.no_grad():
            cam_ids, gs_ids, value = score_terms(
                params, info, state["scene_scale"], self.grow_grad2d, self.grow_scale3d, self.grow_scale2d, self.absgrad
            )
            if gs_ids.numel() == 0:
                return
            view_loss = info["view_loss"].to(value.device)[cam_ids]
            state["score"].index_add_(0, gs_ids, view_loss * value)
            state["views"].index_add_(0, gs_ids, torch.ones_like(value))
            if "error_map" in info:
                # Per-Gaussian error: the per-pixel loss under its projected centre.
                emap = info["error_map"]  # [C, H, W]
                w, h = info["width"], info["height"]
                means2d = info["means2d"].detach()  # [C, N, 2]
                xy = means2d.reshape(-1, 2)[cam_ids * means2d.shape[1] + gs_ids]  # flat gathers, as in score_terms
                px = xy[:, 0].long().clamp(0, w - 1)
                py = xy[:, 1].long().clamp(0, h - 1)
                state["error"].index_add_(0, gs_ids, emap.reshape(-1)[(cam_ids * h + py) * w + px])

    # -- growth -----------------------------------------------------------------------

    def growth_candidates(self, params, state, grads, step) -> torch.Tensor:
        """3DGS's rule outside the prompts; inside them, the score quota (`prompt_quota`)
        placed by priority (score × (1 + attention)). Outside growth then gives way to
        what the prompts add beyond 3DGS's rule."""
        self._ensure_state(params, state)
        inside = self.inside_prompts(params["means"])
        rule = grads > self.grow_grad2d  # 3DGS's candidates, everywhere
        ledger = state.setdefault("ledger", new_ledger())
        focused = bool(inside.any()) and float(inside.float().mean()) <= MAX_FOCUS_FRACTION
        if not focused:
            # No prompt, or prompts holding most of the scene: they focus nothing, and a
            # quota there would only grow the whole scene beyond 3DGS.
            chosen_in = rule & inside
            fence = None
        else:
            chosen_in, fence = self.prompt_growth(params, state, inside)
        # Outside, the mean gradient is taken over at least outside_min_votes views: a mean
        # of a handful crosses the threshold by chance far more often than 3DGS's mean over
        # every step, while a gradient large enough still grows on fewer.
        grads_out = state["grad2d"] / state["count"].clamp_min(max(self.outside_min_votes, 1))
        outside = (grads_out > self.grow_grad2d) & ~inside
        few_votes = rule & ~inside & ~outside
        n_out = int(outside.sum())
        # What the prompts add beyond 3DGS's rule: inside growth over what the rule
        # would have grown there, the Gaussians resampled since the last refinement, and
        # what earlier refinements could not offset.
        n_rule_in = int((rule & inside).sum())
        resampled = int(state.get("resampled", 0))
        state["resampled"] = 0
        stayed = self.resampled_that_stayed(params, state, step)
        state["charged"][stayed] = 1.0
        n_stayed = int(stayed.sum())
        extra = max(int(chosen_in.sum()) - n_rule_in, 0) + n_stayed + int(state.get("debt", 0))
        keep_out = max(n_out - extra, 0) if self.outside_offset else n_out
        state["debt"] = max(extra - n_out, 0) if self.outside_offset else 0
        kept = outside
        if keep_out < n_out:
            # 3DGS's own criterion decides which outside candidates grow: the largest
            # view-space gradients. (The prompt score favours near, large, opaque
            # Gaussians, which outside the prompts are the floaters in front of cameras.)
            kept = torch.zeros_like(outside)
            if keep_out > 0:
                kept[grads.masked_fill(~outside, float("-inf")).topk(keep_out).indices] = True
        ledger["refinements"].append({
            "step": int(step), "n": int(params["means"].shape[0]), "inside": int(inside.sum()),
            "rule_inside": n_rule_in, "grown_inside": int(chosen_in.sum()), "score_fence": fence,
            "rule_outside": n_out, "few_votes": int(few_votes.sum()), "grown_outside": int(kept.sum()),
            "resampled": resampled, "resampled_stayed": n_stayed, "debt": int(state["debt"]),
        })
        ledger["grown_inside"] += int(chosen_in.sum())
        ledger["grown_outside"] += int(kept.sum())
        return chosen_in | kept

    def prompt_growth(self, params, state, inside: torch.Tensor) -> tuple[torch.Tensor, float | None]:
        """Which Gaussians inside the prompts grow: a quota set by the score distribution
        (`prompt_quota`), given to the highest priority, score × (1 + attention), among
        those whose priority clears the same fence. Returns the mask and the fence."""
        chosen = torch.zeros_like(inside)
        seen = inside & (state["views"] > 0)
        if not bool(seen.any()):
            return chosen, None
        score = state["score"] / state["views"].clamp_min(1)
        quota, fence = prompt_quota(score[seen])
        if quota == 0:
            return chosen, fence
        priority = self.growth_priority(params, state, None, prompt_rank=True)
        eligible = seen & (priority > fence)
        take = min(quota, int(eligible.sum()))
        if take > 0:
            chosen[priority.masked_fill(~eligible, float("-inf")).topk(take).indices] = True
        return chosen, fence

    def per_gaussian(self, params, state) -> tuple[torch.Tensor | None, torch.Tensor | None]:
        """Mean score and mean pixel error per view that saw each Gaussian (since the
        last refinement; the statistics restart at every refinement, as 3DGS's do)."""
        if state.get("views") is None or state["views"].shape[0] != params["means"].shape[0]:
            return None, None
        views = state["views"].clamp_min(1)
        return state["score"] / views, state["error"] / views

    def growth_priority(self, params, state, grads, prompt_rank: bool = False) -> torch.Tensor:
        """Mean score per view times ``1 + attention`` (the error field fused with the
        prompt weight) inside the prompts. For the budget (``prompt_rank`` False), prompt
        Gaussians rank above all others."""
        priority = state["score"] / state["views"].clamp_min(1)
        inside = self.inside_prompts(params["means"])
        if self.attention_fn is not None and bool(inside.any()):
            att = self.attention_fn(params["means"][inside].detach()).to(priority.device)
            priority[inside] = priority[inside] * (1.0 + att)
        if prompt_rank:
            return priority
        return priority + inside.float() * (priority.abs().max() + 1.0)

    def _grow_gs(self, params, optimizers, state, step) -> tuple[int, int]:
        n_before = params["means"].shape[0]
        n_dupli, n_split = super()._grow_gs(params, optimizers, state, step)
        n_new = n_dupli + 2 * n_split
        if n_new:
            state["born"][-n_new:] = float(step)
        # The score restarts at every refinement, as gsplat's gradient statistics do: a
        # Gaussian that grew is judged again on what it does next.
        for key in ("score", "error", "views"):
            state[key].zero_()
        assert params["means"].shape[0] == n_before + n_dupli + n_split
        return n_dupli, n_split

    # -- pruning ----------------------------------------------------------------------

    def step_post_backward(self, params, optimizers, state, step, info, packed: bool = False) -> None:
        super().step_post_backward(params, optimizers, state, step, info, packed=packed)
        at = self.last_round_judgement_step
        if at is not None and step >= at and not state.get("last_round_judged"):
            self.judge_last_round(params, optimizers, state, step)

    @torch.no_grad()
    def judge_last_round(self, params, optimizers, state, step: int) -> int:
        """Remove the resampled Gaussians that no refinement judged (not charged) and that
        `idle_resampled` finds idle; once a run. Returns how many."""
        state["last_round_judged"] = True
        self._ensure_state(params, state)
        idle = self.idle_resampled(params, state, step) & (state["charged"] == 0)
        n = int(idle.sum())
        ledger = state.setdefault("ledger", new_ledger())
        ledger["resampled_removed"] += n
        ledger["last_round"] = {"step": int(step), "removed": n}
        if n:
            remove(params=params, optimizers=optimizers, state=state, mask=idle)
        return n

    @torch.no_grad()
    def _prune_gs(self, params, optimizers, state, step) -> int:
        self._ensure_state(params, state)
        is_prune = self.prune_mask(params, state, step)
        young = (step - state["born"]) < self.protect_steps
        inside = self.inside_prompts(params["means"])
        protected = young & inside
        is_prune = is_prune & ~protected
        idle = self.idle_resampled(params, state, step)
        is_prune = is_prune | idle
        n_prune = int(is_prune.sum())
        ledger = state.setdefault("ledger", new_ledger())
        ledger["resampled_removed"] += int(idle.sum())
        n_in = int((is_prune & inside).sum())
        ledger["pruned_inside"] += n_in
        ledger["pruned_outside"] += n_prune - n_in
        if n_prune > 0:
            remove(params=params, optimizers=optimizers, state=state, mask=is_prune)
        return n_prune

    def resampled_that_stayed(self, params, state, step: int) -> torch.Tensor:
        """bool [N]: resampled Gaussians (and their grown copies) that have earned their
        keep and are not yet offset against outside growth: judged when `idle_resampled`
        judges (`_resampled_to_judge`), and at or over ``carve_keep_opacity``. Only these
        cost outside growth: most of what resampling adds fades and is removed, and
        charging it on arrival held back 3DGS's growth outside the prompts early in
        training, when it compounds."""
        kept = torch.sigmoid(params["opacities"].flatten()) >= self.carve_keep_opacity
        return self._resampled_to_judge(params, state, step) & (state["charged"] == 0) & kept

    def idle_resampled(self, params, state, step: int) -> torch.Tensor:
        """bool [N]: resampled Gaussians that have not earned their keep: a refinement
        interval after they were added (and after the last opacity reset, which clamps
        every opacity), still under ``carve_keep_opacity``. Carving adds up to a thousand
        points per round where the render is wrong, most of them on surfaces the rest of
        the model fits soon after; those fade, and would otherwise stay to the end."""
        faint = torch.sigmoid(params["opacities"].flatten()) < self.carve_keep_opacity
        return self._resampled_to_judge(params, state, step) & faint

    def _resampled_to_judge(self, params, state, step: int) -> torch.Tensor:
        """bool [N]: resampled Gaussians (and their grown copies) at least a refinement
        interval old; none in the refinement interval after an opacity reset, whose
        clamp says nothing of what they earned (resets stop with refinement)."""
        last_reset = step - step % self.reset_every
        if step - last_reset < self.refine_every and last_reset < self.refine_stop_iter:
            return torch.zeros(params["means"].shape[0], dtype=torch.bool, device=params["means"].device)
        return (state["carved"] > 0) & ((step - state["born"]) >= self.refine_every)


# -- resampling ---------------------------------------------------------------------------


# Cells of this many grid steps share the resampling cap fairly (see spread_selection).
SPREAD_CELL_VOXELS = 4


def spread_selection(points: torch.Tensor, score: torch.Tensor, cell: float, k: int) -> torch.Tensor:
    """Indices of ``k`` of ``points`` [N, 3], spread over space: the best-scoring point of
    every ``cell``-sized cube first, then the second best of every cube, and so on (by
    score within each such round).

    Resampling candidates come in two shapes: small isolated clusters (a drone a few
    pixels wide) and wide sheets (a surface the render has not fitted yet). Taking the
    top ``k`` by score alone lets a sheet fill the cap, so a drone that looks a little
    less wrong than the sheet is never resampled; taking one point per cube first gives
    every cluster a share.
    """
    n = points.shape[0]
    if k >= n:
        return torch.arange(n)
    cells = torch.floor((points - points.min(dim=0).values) / cell).long()  # [N, 3], each >= 0
    extent = cells.max(dim=0).values + 1
    if float(extent.double().prod()) < 2.0**62:
        # One integer per cube, ordered as the rows (x, then y, then z): the same cube ids
        # as ``torch.unique(cells, dim=0)``, which sorts rows and is ~50x slower on the CPU.
        packed = (cells[:, 0] * extent[1] + cells[:, 1]) * extent[2] + cells[:, 2]
        _, cell_id = torch.unique(packed, return_inverse=True)
    else:
        _, cell_id = torch.unique(cells, dim=0, return_inverse=True)
    order = torch.argsort(score, descending=True, stable=True)  # best first
    # Rank of each point within its cube (0 = the cube's best).
    by_cell = order[torch.argsort(cell_id[order], stable=True)]
    sorted_ids = cell_id[by_cell]
    first = torch.ones(n, dtype=torch.bool)
    first[1:] = sorted_ids[1:] != sorted_ids[:-1]
    group_start = torch.cummax(torch.where(first, torch.arange(n), torch.zeros(n, dtype=torch.long)), dim=0).values
    rank = torch.empty(n, dtype=torch.long)
    rank[by_cell] = torch.arange(n) - group_start
    # Round (rank) first, score second: rank is whole, score breaks ties within a round.
    key = rank.double() * (float(score.max() - score.min()) + 1.0) - score.double()
    return torch.argsort(key)[:k]


def view_votes(
    points: torch.Tensor, camera: Any, err: torch.Tensor, threshold: float, worst: torch.Tensor, seen: torch.Tensor,
    hits: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Resampling's vote in one view: projects ``points`` [N, 3] into ``camera`` (its
    ``world_to_camera`` and ``K``; see `project_points_torch`), adds 1 to ``seen`` [N] for
    each point the view sees (in front, inside the image) and to ``hits`` for each whose
    pixel of ``err`` [H, W] is over ``threshold``; returns the hits' indices, ascending, and
    ``worst`` [H, W] at their pixels. In one C++ pass (csrc/carve.cpp) where the extension
    has it, else `view_votes_torch`; the same numbers either way."""
    try:
        from .. import _C
    except ImportError:  # the extension is not built: the torch expression still works
        _C = None
    w2c, k = camera.world_to_camera.float(), camera.K.float()
    if _C is None or not hasattr(_C, "carve_votes"):
        return view_votes_torch(points, w2c, k, err, threshold, worst, seen, hits)
    c = [t.contiguous() for t in (points, w2c, k, err, worst)]
    index, pixel = _C.carve_votes(c[0], c[1], c[2], c[3], float(threshold), c[4], seen, hits)
    return index, pixel


def project_points_torch(
    points: torch.Tensor, world_to_camera: torch.Tensor, K: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Pinhole projection of ``points`` [N, 3] as resampling's vote makes it: ``(u, v, z)``,
    term by term (each camera coordinate ``((r0 x + r1 y) + r2 z) + t``, then
    ``x / max(z, 1e-6) * f + c``), so that the C++ pass can round every step the same way.
    `Camera.project`'s numbers up to rounding; the same bits where torch's matrix product
    sums the three terms in order without a fused multiply-add (x86 CPUs tested)."""
    x, y, zw = points.unbind(-1)
    m = world_to_camera
    cam = [x * m[r, 0] + y * m[r, 1] + zw * m[r, 2] + m[r, 3] for r in range(3)]
    zd = cam[2].clamp_min(1e-6)
    return cam[0] / zd * K[0, 0] + K[0, 2], cam[1] / zd * K[1, 1] + K[1, 2], cam[2]


def view_votes_torch(
    points: torch.Tensor, world_to_camera: torch.Tensor, K: torch.Tensor, err: torch.Tensor, threshold: float,
    worst: torch.Tensor, seen: torch.Tensor, hits: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """`view_votes` as torch expressions (the reference of the C++ pass)."""
    u, v, z = project_points_torch(points, world_to_camera, K)
    h, w = err.shape
    # 0 <= u < w holds exactly when 0 <= floor(u) < w, NaN and infinities outside.
    inside = (z > 1e-3) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    seen += inside
    idx = torch.where(inside)[0]
    pixel = torch.floor(v[idx]).long() * w + torch.floor(u[idx]).long()
    hit = err.reshape(-1)[pixel] > threshold
    hit_idx = idx[hit]
    hits[hit_idx] += 1
    return hit_idx, worst.reshape(-1)[pixel[hit]]


@dataclass
class CarvedPoints:
    means: torch.Tensor  # [M, 3]
    colors: torch.Tensor  # [M, 3] in [0, 1]
    voxel: float  # grid spacing used


def carve_prompt(
    box: PromptBox,
    views: Sequence[tuple[Any, torch.Tensor, torch.Tensor]],
    max_points: int = 2000,
    min_views: int = 3,
    min_vote: float = 0.6,
    error_threshold: float = CARVE_ERROR_THRESHOLD,
    max_candidates: int = 250_000,
    generator: torch.Generator | None = None,
    opacity: float | None = None,
) -> CarvedPoints:
    """Points inside ``box`` where the render is wrong consistently across views.

    ``views`` holds ``(camera, render, ground_truth)`` with images ``[H, W, 3]`` for a
    camera of the same size (a crop camera works). Candidates on a grid whose spacing
    projects to about one pixel are kept when, among the views that see them, at least
    ``min_views`` see them and a fraction ``min_vote`` has a per-pixel error above
    ``max(error_threshold, 3 × median error)`` there (3×3 max-dilated, to forgive
    sub-pixel misalignment). The colour is the mean ground truth over those views; with
    ``opacity``, the mean colour that a Gaussian of that opacity drawn over the render
    needs to reproduce the ground truth there.
    """
    empty = CarvedPoints(torch.zeros(0, 3), torch.zeros(0, 3), 0.0)
    if not views:
        return empty
    # Grid spacing: one pixel at the median distance of the views, at the median focal.
    center = torch.tensor(box.center, dtype=torch.float32)
    depths, focals = [], []
    for cam, _, _ in views:
        p = cam.world_to_camera[:3, :3] @ center + cam.world_to_camera[:3, 3]
        depths.append(float(p[2]))
        focals.append(float(cam.K[0, 0]))
    depth = max(float(torch.tensor(depths).median()), 1e-3)
    voxel = depth / max(float(torch.tensor(focals).median()), 1e-6)
    size = torch.tensor(box.size, dtype=torch.float32)
    while float(torch.prod(torch.ceil(size / voxel))) > max_candidates:
        voxel *= 1.25
    counts = [max(int(math.ceil(float(s) / voxel)), 1) for s in size]
    axes = [(torch.arange(c, dtype=torch.float32) + 0.5) / c - 0.5 for c in counts]
    grid = torch.stack(torch.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3) * size
    rot = torch.tensor(box.rotation_matrix(), dtype=torch.float32)
    points = grid @ rot.T + center  # [P, 3]

    seen = torch.zeros(points.shape[0])
    hits = torch.zeros(points.shape[0])
    # Per view, the points that hit and the pixel each hit reads its colour at: colours
    # are summed only for the points kept, at the end, in view order.
    view_hits: list[tuple[torch.Tensor, torch.Tensor]] = []
    for cam, rendered, gt in views:
        err = (rendered - gt).abs().mean(dim=-1)  # [H, W]
        thr = max(error_threshold, 3.0 * float(err.median()))
        # 3×3 max: a point hits if any neighbour pixel is wrong; its colour is read at
        # that worst pixel (the object's, not the background next to it).
        err, worst = F.max_pool2d(err[None, None], 3, stride=1, padding=1, return_indices=True)
        err, worst = err[0, 0], worst[0, 0]
        view_hits.append(view_votes(points, cam, err, thr, worst, seen, hits))
    keep = (seen >= min_views) & (hits >= min_vote * seen)
    idx = torch.where(keep)[0]
    if idx.numel() == 0:
        return CarvedPoints(torch.zeros(0, 3), torch.zeros(0, 3), voxel)
    if idx.numel() > max_points:
        vote = hits[idx] / seen[idx] + 1e-3 * torch.rand(idx.numel(), generator=generator)
        idx = idx[spread_selection(grid[idx], vote, voxel * SPREAD_CELL_VOXELS, max_points)]
    slot = torch.full((points.shape[0],), -1, dtype=torch.long)
    slot[idx] = torch.arange(idx.numel())
    color_sum = torch.zeros(idx.numel(), 3)
    for (_, rendered, gt), (hit_idx, pix) in zip(views, view_hits):
        at = slot[hit_idx]
        mine = at >= 0
        pix = pix[mine]
        color = gt.reshape(-1, 3)[pix]
        if opacity is not None:
            # What a Gaussian of this opacity must carry, drawn over the current render,
            # to give the truth there (an object narrower than a pixel shows in it
            # mixed with what lies behind).
            color = (color - (1.0 - opacity) * rendered.reshape(-1, 3)[pix]) / opacity
        color_sum[at[mine]] += color.clamp(0, 1)
    colors = color_sum / hits[idx, None].clamp_min(1)
    return CarvedPoints(points[idx], colors.clamp(0, 1), voxel)


@torch.no_grad()
def append_gaussians(
    params: torch.nn.ParameterDict,
    optimizers: dict[str, torch.optim.Optimizer],
    state: dict[str, Any],
    means: torch.Tensor,
    colors: torch.Tensor,
    scale: float,
    opacity: float,
    step: int,
    carved: bool = True,
) -> int:
    """Add isotropic Gaussians (fresh optimizer state) and extend the strategy state.
    ``carved``: they are resampled ones, which `PromptGSStrategy.idle_resampled` removes
    while they stay faint (False: only the prune judges them, as any Gaussian; young
    ones inside a prompt are spared for ``protect_steps`` either way)."""
    m = means.shape[0]
    if m == 0:
        return 0
    device = params["means"].device
    k_rest = params["shN"].shape[1]
    new = {
        "means": means.to(device),
        "scales": torch.full((m, 3), math.log(scale), device=device),
        "quats": torch.tensor([1.0, 0.0, 0.0, 0.0], device=device).repeat(m, 1),
        "opacities": torch.full((m,), math.log(opacity / (1 - opacity)), device=device),
        "sh0": rgb_to_sh(colors.to(device)).reshape(m, 1, 3),
        "shN": torch.zeros(m, k_rest, 3, device=device),
    }

    def param_fn(name: str, p: torch.Tensor) -> torch.Tensor:
        return torch.nn.Parameter(torch.cat([p, new[name].to(p.dtype)]), requires_grad=p.requires_grad)

    def optimizer_fn(key: str, v: torch.Tensor) -> torch.Tensor:
        return torch.cat([v, torch.zeros((m, *v.shape[1:]), device=v.device, dtype=v.dtype)])

    _update_param_with_optimizer(param_fn, optimizer_fn, params, optimizers)
    for key, value in state.items():
        if isinstance(value, torch.Tensor):
            fill = float(step) if key == "born" else float(carved) if key == "carved" else 0.0
            state[key] = torch.cat([value, torch.full((m, *value.shape[1:]), fill, device=value.device, dtype=value.dtype)])
    return m
