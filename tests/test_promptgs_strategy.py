import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from promptgs_engine.bench.toy_scene import look_at
from promptgs_engine.config import TrainConfig
from promptgs_engine.data import Camera
from promptgs_engine.focus import crop_camera
from promptgs_engine.gaussians import init_from_points
from promptgs_engine.prompts import PromptBox
from promptgs_engine.render import render
from promptgs_engine.strategies.promptgs import (
    DRAWN_CARVE_ERROR_THRESHOLD, PromptGSStrategy, append_gaussians, carve_prompt, project_points_torch, score_terms,
    spread_selection, view_votes, view_votes_torch,
)
from promptgs_engine.train import make_optimizers


def _params(points, opacity=0.5):
    n = points.shape[0]
    p = init_from_points(points, torch.full((n, 3), 0.5), sh_degree=1, init_opacity=opacity)
    with torch.no_grad():
        p["scales"].fill_(math.log(0.001))  # small: growth clones them in place
    return p, make_optimizers(p, TrainConfig(dataset="d", out="o"), extent=1.0)


def _strategy(prompts, **kw):
    s = PromptGSStrategy(refine_start_iter=0, refine_stop_iter=10_000, refine_every=100, reset_every=10_000, prompts=prompts, **kw)
    return s, s.initialize_state(scene_scale=1.0)


def _info(n, grads, view_loss=1.0, w=100, h=100):
    means2d = torch.full((1, n, 2), 50.0, requires_grad=True)
    means2d.grad = grads.reshape(1, n, 2)
    return {
        "means2d": means2d,
        "radii": torch.full((1, n, 2), 3, dtype=torch.int32),
        "depths": torch.full((1, n), 2.0),
        "width": w,
        "height": h,
        "n_cameras": 1,
        "gaussian_ids": None,
        "view_loss": torch.tensor([view_loss]),
        "error_map": torch.ones(1, h, w),
    }


UNIT_BOX = PromptBox(center=(0.0, 0.0, 0.0), size=(1.0, 1.0, 1.0))


def _set_stats(s, state, params, score, grads, votes=4):
    """Statistics as after a refinement interval: ``votes`` statistics steps saw each
    Gaussian (enough to grow outside the prompts), with the given mean score per view and
    mean view-space gradient (in units of the 3DGS threshold)."""
    s._ensure_state(params, state)
    n = params["means"].shape[0]
    state["views"] = torch.ones(n)
    state["score"] = torch.as_tensor(score, dtype=torch.float32).clone()
    state["error"] = torch.zeros(n)
    votes = torch.as_tensor(votes, dtype=torch.float32).expand(n).clone()
    state["count"] = votes
    state["grad2d"] = torch.as_tensor(grads, dtype=torch.float32) * s.grow_grad2d * votes


FILLER = 30  # Gaussians far outside the box, idle: the prompt holds a small part of the scene


def _box_and_outside(n_inside, n_outside=1):
    """``n_inside`` points in the unit box, ``n_outside`` outside it, then FILLER more outside."""
    inside = torch.stack([torch.linspace(-0.4, 0.4, n_inside), torch.zeros(n_inside), torch.zeros(n_inside)], dim=1)
    outside = torch.stack([torch.linspace(3.0, 5.0, n_outside), torch.zeros(n_outside), torch.zeros(n_outside)], dim=1)
    filler = torch.stack([torch.full((FILLER,), -6.0), torch.linspace(-3.0, 3.0, FILLER), torch.zeros(FILLER)], dim=1)
    return torch.cat([inside, outside, filler])


def test_prompt_growth_is_the_score_tail_placed_by_attention():
    # Twenty Gaussians in the box, none with a gradient over 3DGS's threshold: the two in
    # the long tail of the score distribution grow (Tukey's fence), the rest do not; the
    # one outside, at half the threshold, does not either.
    pts = _box_and_outside(20)
    params, opts = _params(pts)
    s, state = _strategy([UNIT_BOX])
    n = 21 + FILLER
    score = torch.cat([1.0 + 0.01 * torch.arange(18.0), torch.tensor([3.0, 2.9]), torch.ones(1 + FILLER)])
    _set_stats(s, state, params, score, torch.full((n,), 0.5))
    grow = s.growth_candidates(params, state, state["grad2d"] / state["count"], step=100)
    assert grow.nonzero().flatten().tolist() == [18, 19]
    # The attention field decides where the quota goes: a Gaussian of ordinary score at a
    # high-error place outranks the weaker of the two tail ones.
    s.attention_fn = lambda p: torch.where(p[:, 0] < -0.39, 2.0, 0.0)  # only Gaussian 0 (in the box)
    _set_stats(s, state, params, score, torch.full((n,), 0.5))
    grow = s.growth_candidates(params, state, state["grad2d"] / state["count"], step=100)
    assert grow.nonzero().flatten().tolist() == [0, 18]
    # Through _grow_gs: two clones, born now, and the statistics restart.
    _set_stats(s, state, params, score, torch.full((n,), 0.5))
    assert s._grow_gs(params, opts, state, step=100) == (2, 0)
    assert params["means"].shape[0] == n + 2 and bool((state["born"][-2:] == 100).all())
    assert float(state["score"].abs().sum()) == 0.0
    ledger = state["ledger"]["refinements"][-1]
    assert ledger["grown_inside"] == 2 and ledger["rule_inside"] == 0 and ledger["grown_outside"] == 0


def test_inside_the_prompts_the_score_decides_growth_not_a_gradient_threshold():
    # Twenty Gaussians in the box. Five have three times 3DGS's gradient threshold but an
    # ordinary score; two are the score's tail with a gradient under even a quarter of
    # the threshold (the lowered threshold prompts used to have). Only the tail grows:
    # neither 3DGS's rule nor a lowered threshold selects anything inside the prompts.
    pts = _box_and_outside(20)
    params, _ = _params(pts)
    s, state = _strategy([UNIT_BOX])
    n = 21 + FILLER
    score = torch.cat([1.0 + 0.01 * torch.arange(20.0), torch.ones(1 + FILLER)])
    score[[10, 11]] = torch.tensor([3.0, 2.9])
    grads = torch.cat([torch.full((5,), 3.0), torch.full((15,), 0.2), torch.zeros(1 + FILLER)])
    _set_stats(s, state, params, score, grads)
    grow = s.growth_candidates(params, state, state["grad2d"] / state["count"], step=100)
    assert grow.nonzero().flatten().tolist() == [10, 11]
    entry = state["ledger"]["refinements"][-1]
    assert entry["rule_inside"] == 5 and entry["grown_inside"] == 2
    # The quota follows the score distribution: a flat one has no tail, and nothing grows.
    _set_stats(s, state, params, torch.ones(n), grads)
    assert int(s.growth_candidates(params, state, state["grad2d"] / state["count"], step=200).sum()) == 0


def test_a_prompt_holding_most_of_the_scene_does_not_lower_the_threshold():
    # Three of four Gaussians inside the box: it focuses nothing, so the 3DGS threshold
    # holds everywhere and gradients at half of it grow nothing.
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [3.0, 0.0, 0.0]])
    params, opts = _params(pts)
    s, state = _strategy([UNIT_BOX])
    g = 0.5 * s.grow_grad2d / (100 / 2.0)
    s._update_state(params, state, _info(4, torch.tensor([[g, 0.0]] * 4)))
    assert s._grow_gs(params, opts, state, step=100) == (0, 0)


def test_outside_the_prompts_the_largest_gradients_grow_not_the_highest_scores():
    # Two outside candidates: one near the camera with a huge score (near, opaque, big on
    # screen) and a gradient just over the threshold, one far with a gradient twice as
    # large. One Gaussian is owed from an earlier refinement, so one outside candidate
    # gives way: the larger gradient grows.
    pts = torch.tensor([[3.0, 0.0, 0.0], [5.0, 0.0, 0.0]])
    params, opts = _params(pts)
    s, state = _strategy([UNIT_BOX])
    unit = s.grow_grad2d / (100 / 2.0)
    info = _info(2, torch.tensor([[1.2 * unit, 0.0], [2.4 * unit, 0.0]]))
    info["depths"] = torch.tensor([[0.1, 50.0]])
    info["radii"] = torch.tensor([[[40, 40], [1, 1]]], dtype=torch.int32)
    for _ in range(s.outside_min_votes):  # enough statistics steps to vote outside
        s._update_state(params, state, info)
    state["debt"] = 1
    score, _ = s.per_gaussian(params, state)
    assert score[0] > score[1]
    assert s._grow_gs(params, opts, state, step=100) == (1, 0)
    assert torch.equal(params["means"][-1].detach(), pts[1])
    assert state["debt"] == 0


def _prompt_and_outside_candidates(n_outside=3, **kw):
    # Inside: twenty Gaussians under 3DGS's threshold, two of them in the score's tail
    # (they grow where 3DGS would grow none). Outside: candidates above the threshold,
    # by rising gradient.
    pts = _box_and_outside(20, n_outside)
    params, opts = _params(pts)
    s, state = _strategy([UNIT_BOX], **kw)
    score = torch.cat([1.0 + 0.01 * torch.arange(18.0), torch.tensor([3.0, 2.9]), torch.ones(n_outside + FILLER)])
    grads = torch.cat([torch.full((20,), 0.5), 1.5 + torch.arange(float(n_outside)), torch.zeros(FILLER)])
    _set_stats(s, state, params, score, grads)
    return s, state, params, opts, pts


def test_outside_growth_gives_way_to_the_prompts_extra_growth():
    # 3DGS would grow the 3 outside candidates. The prompt adds 2, so the 2 weakest
    # outside candidates give way: the count grows as 3DGS's would.
    s, state, params, opts, pts = _prompt_and_outside_candidates()
    assert sum(s._grow_gs(params, opts, state, step=100)) == 3
    grown = params["means"][23 + FILLER :].detach()
    assert sorted(round(float(x), 3) for x in grown[:, 0]) == [0.358, 0.4, 5.0]
    # Without the offset, all grow: 5.
    s, state, params, opts, _ = _prompt_and_outside_candidates(outside_offset=False)
    assert sum(s._grow_gs(params, opts, state, step=100)) == 5


def test_resampling_s_last_round_is_judged_once_late_in_the_run():
    # Refinements stop at step 300; the last round, resampled at 250, was never judged.
    # At the judgement step, its Gaussians still under carve_keep_opacity go; one that
    # brightened stays, and so do Gaussians already judged (charged) and ones never
    # resampled, however faint. Before that step nothing goes, and it happens once. Step
    # 400 lies within a refinement interval of a multiple of reset_every (350), but resets
    # stop with refinement, so no reset happened there to excuse the faint.
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0], [0.2, 0.0, 0.0], [0.3, 0.0, 0.0], [3.0, 0.0, 0.0]])
    params, opts = _params(pts)
    s = PromptGSStrategy(refine_start_iter=0, refine_stop_iter=300, refine_every=100, reset_every=350,
                         prompts=[UNIT_BOX], last_round_judgement_step=400)
    state = s.initialize_state(scene_scale=1.0)
    s._ensure_state(params, state)
    with torch.no_grad():
        params["opacities"].copy_(torch.logit(torch.tensor([0.01, 0.01, 0.5, 0.01, 0.01])))
    state["carved"] = torch.tensor([1.0, 1.0, 1.0, 1.0, 0.0])
    state["charged"] = torch.tensor([0.0, 0.0, 0.0, 1.0, 0.0])
    state["born"] = torch.tensor([250.0, 250.0, 250.0, 150.0, 0.0])
    info = _info(5, torch.zeros(5, 2))
    s.step_post_backward(params, opts, state, step=399, info=info)
    assert params["means"].shape[0] == 5
    s.step_post_backward(params, opts, state, step=400, info=info)
    kept = params["means"][:, 0].detach().tolist()
    assert [round(x, 3) for x in kept] == [0.2, 0.3, 3.0]
    assert state["ledger"]["last_round"] == {"step": 400, "removed": 2}
    assert state["born"].shape[0] == 3 and state["carved"].tolist() == [1.0, 1.0, 0.0]
    with torch.no_grad():
        params["opacities"].fill_(float(torch.logit(torch.tensor(0.01))))
    s.step_post_backward(params, opts, state, step=500, info=info)
    assert params["means"].shape[0] == 3  # once a run


def test_outside_a_gradient_seen_by_too_few_statistics_steps_needs_to_be_larger():
    # Outside the prompt the summed gradient is divided by at least three views. Four
    # outside Gaussians over 3DGS's threshold, seen by 1, 2, 3 and 1 statistics steps with
    # mean gradients 2.0, 1.2, 1.5 and 4.0 (in threshold units): over three views that is
    # 0.67, 0.8, 1.5 and 1.33, so the last two grow and the ledger counts two held back.
    pts = _box_and_outside(2, 4)
    params, opts = _params(pts)
    s, state = _strategy([UNIT_BOX], outside_min_votes=3)
    votes = torch.cat([torch.full((2,), 1.0), torch.tensor([1.0, 2.0, 3.0, 1.0]), torch.full((FILLER,), 9.0)])
    grads = torch.cat([torch.zeros(2), torch.tensor([2.0, 1.2, 1.5, 4.0]), torch.zeros(FILLER)])
    _set_stats(s, state, params, torch.ones(6 + FILLER), grads, votes=votes)
    grow = s.growth_candidates(params, state, state["grad2d"] / state["count"], step=100)
    assert grow.nonzero().flatten().tolist() == [4, 5]
    assert state["ledger"]["refinements"][-1]["few_votes"] == 2
    s, state = _strategy([UNIT_BOX], outside_min_votes=1)  # 3DGS's rule: every one grows
    _set_stats(s, state, params, torch.ones(6 + FILLER), grads, votes=votes)
    assert s.growth_candidates(params, state, state["grad2d"] / state["count"], step=100).nonzero().flatten().tolist() == [2, 3, 4, 5]


def test_what_outside_growth_cannot_offset_is_carried_to_the_next_refinement():
    # One outside candidate against two extra prompt Gaussians: it gives way, and the one
    # left over is owed at the next refinement, where one of two outside candidates gives way.
    s, state, params, opts, _ = _prompt_and_outside_candidates(n_outside=1)
    assert sum(s._grow_gs(params, opts, state, step=100)) == 2
    assert state["debt"] == 1
    n = params["means"].shape[0]
    grads = torch.zeros(n)
    grads[21:23] = 2.0  # two outside candidates (in the filler), and nothing in the box's tail now
    _set_stats(s, state, params, torch.ones(n), grads)
    keep = s.growth_candidates(params, state, state["grad2d"] / state["count"], step=200)
    assert int(keep.sum()) == 1 and state["debt"] == 0


def test_resampled_gaussians_cost_outside_growth_once_they_have_stayed():
    # Three Gaussians resampled into the box at step 100, two that became opaque and one
    # still faint; three outside candidates. At the refinement one interval later, the two
    # that stayed are offset (the two weakest outside candidates give way) and the faint
    # one costs nothing; at the next refinement the two are not charged again.
    pts = _box_and_outside(3, 3)
    params, opts = _params(pts)
    with torch.no_grad():
        params["opacities"][2] = math.log(0.02 / 0.98)
    s, state = _strategy([UNIT_BOX])
    s._ensure_state(params, state)
    state["carved"][:3] = 1.0
    state["born"][:3] = 100.0
    s.record_resampled(state, 3)
    grads = torch.cat([torch.zeros(3), torch.tensor([1.5, 2.0, 2.5]), torch.zeros(FILLER)])
    _set_stats(s, state, params, torch.ones(6 + FILLER), grads)
    early = s.growth_candidates(params, state, state["grad2d"] / state["count"], step=150)
    assert early.nonzero().flatten().tolist() == [3, 4, 5]  # not a refinement interval old yet
    _set_stats(s, state, params, torch.ones(6 + FILLER), grads)
    grow = s.growth_candidates(params, state, state["grad2d"] / state["count"], step=200)
    assert grow.nonzero().flatten().tolist() == [5]
    assert state["ledger"]["refinements"][-1]["resampled_stayed"] == 2 and state["debt"] == 0
    _set_stats(s, state, params, torch.ones(6 + FILLER), grads)
    again = s.growth_candidates(params, state, state["grad2d"] / state["count"], step=300)
    assert again.nonzero().flatten().tolist() == [3, 4, 5]


def test_resampled_gaussians_that_stay_faint_are_removed():
    pts = _box_and_outside(4)
    params, opts = _params(pts, opacity=0.02)  # all faint, under carve_keep_opacity
    s, state = _strategy([UNIT_BOX], protect_steps=10_000)
    s._ensure_state(params, state)
    state["carved"][:2] = 1.0  # the first two were resampled, at step 100
    state["born"][:] = 100.0
    # Right after an opacity reset nothing is judged; one refinement interval later the
    # faint resampled ones go, though young Gaussians in prompts are otherwise protected.
    s.reset_every = 1000
    assert int(s.idle_resampled(params, state, step=1050).sum()) == 0
    assert s._prune_gs(params, opts, state, step=1200) == 2
    assert params["means"].shape[0] == 3 + FILLER
    assert state["ledger"]["resampled_removed"] == 2


def test_low_resolution_steps_add_nothing_to_the_growth_statistics():
    pts = torch.tensor([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    params, _ = _params(pts)
    grads = torch.tensor([[2e-6, 0.0], [0.0, 4e-6]])  # under the score's clamp
    s, full = _strategy([UNIT_BOX])
    s._update_state(params, full, _info(2, grads))
    s, mixed = _strategy([UNIT_BOX])
    low = _info(2, grads)
    low["downscale"] = 4.0
    s._update_state(params, mixed, low)  # first: the state still starts empty
    assert torch.equal(mixed["count"], torch.zeros(2)) and torch.equal(mixed["score"], torch.zeros(2))
    s._update_state(params, mixed, _info(2, grads))
    s._update_state(params, mixed, low)
    # Only the full-size step counts, inside the prompt and out.
    for key in ("grad2d", "count", "score", "views"):
        assert torch.allclose(mixed[key], full[key]), key
    # The step's own gradients (used by the optimizer) are untouched.
    assert torch.equal(low["means2d"].grad, grads.reshape(1, 2, 2))


@pytest.mark.parametrize("scale2d_steps", [0, 10_000])  # our accumulation, or gsplat's with 2D scales
def test_crop_steps_add_growth_statistics_inside_the_prompts_only(scale2d_steps):
    """A crop step (``votes_outside`` False) adds its view-space gradients and counts to the
    Gaussians it saw inside a prompt; those outside keep the statistics of the whole-view
    steps, and one the crop did not see gets nothing."""
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.2, 0.1, 0.0], [3.0, 0.0, 0.0], [-0.3, 0.0, 0.0]])
    params, _ = _params(pts)
    grads = torch.tensor([[2e-6, 0.0], [0.0, 3e-6], [4e-6, 0.0], [1e-6, 1e-6]])
    s, state = _strategy([UNIT_BOX], refine_scale2d_stop_iter=scale2d_steps)
    s._update_state(params, state, _info(4, grads))  # a whole view: every Gaussian votes
    whole_grad2d, whole_count = state["grad2d"].clone(), state["count"].clone()
    crop = _info(4, grads * 2)
    crop["votes_outside"] = False
    crop["radii"][0, 1] = 0  # the crop does not see Gaussian 1
    s._update_state(params, state, crop)
    assert torch.equal(state["count"], whole_count + torch.tensor([1.0, 0.0, 0.0, 1.0]))
    assert state["grad2d"][0] > whole_grad2d[0] and state["grad2d"][3] > whole_grad2d[3]
    assert torch.equal(state["grad2d"][1:3], whole_grad2d[1:3])


def test_spread_selection_gives_an_isolated_cluster_a_share_of_the_cap():
    # A sheet of 400 candidates scoring 1.0 and a 3-point cluster scoring 0.8 elsewhere:
    # the top 20 by score would all lie on the sheet.
    xs = torch.arange(20, dtype=torch.float32) * 0.1
    sheet = torch.stack(torch.meshgrid(xs, xs, indexing="ij"), -1).reshape(-1, 2)
    sheet = torch.cat([sheet, torch.zeros(400, 1)], dim=1)
    cluster = torch.tensor([[5.0, 5.0, 5.0], [5.05, 5.0, 5.0], [5.0, 5.05, 5.0]])
    points = torch.cat([sheet, cluster])
    score = torch.cat([torch.ones(400), torch.full((3,), 0.8)])
    chosen = spread_selection(points, score, cell=0.5, k=20)
    assert chosen.numel() == 20 and chosen.unique().numel() == 20
    assert bool((chosen >= 400).any())  # the cluster is represented
    # One point per 0.5 m cell first: the sheet's 16 cells and the cluster's one cell
    # make 17 picks, then the second round starts.
    cells = torch.floor((points[chosen] - points.min(dim=0).values) / 0.5).long()
    assert torch.unique(cells, dim=0).shape[0] == 17
    # Within a round the better score comes first; asking for everything returns everything.
    assert int(spread_selection(points, score, cell=0.5, k=1)[0]) < 400
    assert spread_selection(points, score, cell=0.5, k=1000).numel() == 403


def test_score_ranks_a_large_gradient_in_a_high_loss_view_above_an_idle_gaussian():
    pts = torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.0, 0.0]])
    params, _ = _params(pts)
    s, state = _strategy([UNIT_BOX])
    g = 2 * s.grow_grad2d / 50.0
    s._update_state(params, state, _info(2, torch.tensor([[g, 0.0], [0.0, 0.0]]), view_loss=0.5))
    score, error = s.per_gaussian(params, state)
    assert score[0] > score[1] > 0
    # The same gradients in a view with twice the loss give twice the score increment.
    s2, state2 = _strategy([UNIT_BOX])
    s2._update_state(params, state2, _info(2, torch.tensor([[g, 0.0], [0.0, 0.0]]), view_loss=1.0))
    assert torch.allclose(state2["score"], 2 * state["score"])
    assert torch.allclose(error, torch.ones(2))


def test_score_terms_pair_each_view_with_the_gaussians_it_sees():
    """Two views seeing different Gaussians: every (view, Gaussian) pair with both radii
    positive, in view-major order, each with the terms of its own view and Gaussian."""
    n = 5
    params, _ = _params(torch.zeros(n, 3))
    with torch.no_grad():
        params["scales"].copy_(torch.log(torch.tensor([[0.02, 0.05, 0.01]] * n)))
    radii = torch.tensor([[[3, 3], [0, 0], [4, 2], [2, 0], [1, 1]], [[0, 0], [5, 6], [0, 0], [2, 2], [3, 3]]], dtype=torch.int32)
    means2d = torch.zeros(2, n, 2, requires_grad=True)
    means2d.grad = torch.arange(2 * n * 2, dtype=torch.float32).reshape(2, n, 2) * 1e-5
    depths = torch.arange(2 * n, dtype=torch.float32).reshape(2, n) + 1.0
    info = {"means2d": means2d, "radii": radii, "depths": depths, "width": 100, "height": 80, "n_cameras": 2}
    cam_ids, gs_ids, value = score_terms(params, info, 2.0, 2e-4, 0.01, 0.05, False)
    assert cam_ids.tolist() == [0, 0, 0, 1, 1, 1]
    assert gs_ids.tolist() == [0, 2, 4, 1, 3, 4]
    for c, g, v in zip(cam_ids.tolist(), gs_ids.tolist(), value.tolist()):
        grad = float((means2d.grad[c, g] * torch.tensor([100 / 2 * 2, 80 / 2 * 2])).norm()) / 2e-4
        terms = (
            min(grad, 4.0) + 1.0 / (1.0 + float(depths[c, g]) / 2.0) + float(torch.sigmoid(params["opacities"][g].detach()))
            + min(0.05 / (0.01 * 2.0), 4.0) + min(float(radii[c, g].max()) / (0.05 * 100), 4.0)
        )
        assert v == pytest.approx(math.log1p(terms), rel=1e-5)


def test_budget_caps_growth_and_prefers_prompt_candidates():
    # Two prompt Gaussians in the score's tail and three outside candidates, room for two.
    s, state, params, opts, _ = _prompt_and_outside_candidates(outside_offset=False)
    n = params["means"].shape[0]
    s.budget = n + 2
    s._grow_gs(params, opts, state, step=100)
    assert params["means"].shape[0] == n + 2
    assert bool((params["means"][n:].detach().norm(dim=-1) < 1.0).all())  # both grown from inside


def test_young_gaussians_in_prompts_survive_the_opacity_prune():
    pts = torch.tensor([[0.0, 0.0, 0.0], [3.0, 0.0, 0.0]])
    params, opts = _params(pts, opacity=0.001)  # both below prune_opa
    s, state = _strategy([UNIT_BOX], protect_steps=500)
    s._ensure_state(params, state)
    state["born"][:] = 100.0
    assert s._prune_gs(params, opts, state, step=200) == 1  # only the one outside
    assert params["means"].shape[0] == 1 and float(params["means"][0].detach().abs().max()) == 0.0
    assert s._prune_gs(params, opts, state, step=700) == 1  # protection has expired


def test_append_gaussians_extends_parameters_optimizer_state_and_strategy_state():
    params, opts = _params(torch.randn(5, 3))
    s, state = _strategy([UNIT_BOX])
    s._ensure_state(params, state)
    loss = sum(p.sum() for p in params.values())
    loss.backward()
    for o in opts.values():
        o.step()
    added = append_gaussians(params, opts, state, torch.zeros(3, 3), torch.full((3, 3), 0.5), scale=0.01, opacity=0.5, step=42)
    assert added == 3 and params["means"].shape[0] == 8
    for k, o in opts.items():
        st = o.state[params[k]]
        assert st["exp_avg"].shape == params[k].shape
        assert torch.all(st["exp_avg"][5:] == 0)
    assert state["born"].shape[0] == 8 and torch.all(state["born"][5:] == 42)
    assert torch.allclose(torch.exp(params["scales"][5:]), torch.full((3, 3), 0.01))


def _camera(center, target, size=64, f=60.0):
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float32)
    m = look_at(np.asarray(center, float), np.asarray(target, float))
    return Camera("c", size, size, K, torch.tensor(m, dtype=torch.float32), Path("none"))


def _render_points(means, color, cam, bg, scale=0.03):
    n = means.shape[0]
    img, _, _ = render(
        means, torch.tensor([[1.0, 0, 0, 0]]).repeat(n, 1), torch.full((n, 3), scale), torch.full((n,), 0.99),
        color.repeat(n, 1), cam.world_to_camera[None], cam.K[None], cam.width, cam.height,
        backgrounds=bg[None], backend="cpu",
    )
    return img[0]


def test_carving_finds_a_missing_object_inside_the_box_only():
    obj = torch.tensor([[0.2, -0.1, 0.1]])
    bg = torch.tensor([0.2, 0.3, 0.4])
    views = []
    for a in np.linspace(0, 2 * math.pi, 6, endpoint=False):
        cam = _camera(np.array([3 * math.cos(a), 3 * math.sin(a), 1.0]), [0, 0, 0])
        gt = _render_points(obj, torch.tensor([[1.0, 0.9, 0.1]]), cam, bg, scale=0.06)  # ~2 px across
        current = torch.ones_like(gt) * bg  # the model has no object yet
        views.append((cam, current, gt))
    box = PromptBox(center=(0.0, 0.0, 0.0), size=(1.0, 1.0, 1.0))
    carved = carve_prompt(box, views)
    assert carved.means.shape[0] > 0
    assert bool(box.contains(carved.means).all())
    # The visual hull of the object (its ~2σ footprint, one pixel of dilation, one voxel)
    # from 6 views: local to the object and through it, not spread over the 1 m box.
    dist = (carved.means - obj).norm(dim=-1)
    assert float(dist.max()) < 0.4 and float(dist.min()) < 0.05
    grid_points = math.prod(math.ceil(1.0 / carved.voxel) for _ in range(3))
    assert carved.means.shape[0] < 0.1 * grid_points
    # At the object the colour is the object's (hull-edge points see blended pixels).
    assert torch.allclose(carved.colors[dist.argmin()], torch.tensor([1.0, 0.9, 0.1]), atol=0.2)
    # Asked for the colour a half-opaque Gaussian needs over the render, it is pushed
    # away from the background: an object blended into a pixel gets its own colour back.
    blended = [(c, current, 0.5 * gt + 0.5 * current) for c, current, gt in views]
    plain, unmixed = carve_prompt(box, blended), carve_prompt(box, blended, opacity=0.5)
    assert torch.equal(plain.means, unmixed.means)
    near = (plain.means - obj).norm(dim=-1).argmin()
    assert torch.allclose(plain.colors[near], 0.5 * torch.tensor([1.0, 0.9, 0.1]) + 0.5 * bg, atol=0.12)
    assert torch.allclose(unmixed.colors[near], torch.tensor([1.0, 0.9, 0.1]), atol=0.2)
    # With a correct model nothing is wrong and nothing is carved.
    explained = [(c, gt, gt) for c, _, gt in views]
    assert carve_prompt(box, explained).means.shape[0] == 0


def _points_on_pixel_corners(camera, n: int, g: torch.Generator) -> torch.Tensor:
    """World points (float32) whose exact projection into ``camera`` is a pixel corner: in
    float the projection lands a few ulps to either side, so the pixel a point votes for
    depends on how each step of its projection is rounded."""
    w2c, k = camera.world_to_camera.double(), camera.K.double()
    a = torch.randint(0, camera.width + 1, (n,), generator=g).double()
    b = torch.randint(0, camera.height + 1, (n,), generator=g).double()
    d = torch.rand(n, generator=g, dtype=torch.float64) * 4 + 0.5
    cam = torch.stack([(a - k[0, 2]) / k[0, 0] * d, (b - k[1, 2]) / k[1, 1] * d, d], -1)
    return ((cam - w2c[:3, 3]) @ w2c[:3, :3]).float()  # R^T (cam - t), row by row


def test_view_votes_in_cpp_are_the_torch_expressions_numbers():
    pytest.importorskip("promptgs_engine._C")
    g = torch.Generator().manual_seed(3)
    h, w, n = 37, 53, 20_000
    # A view through the origin along +z (u = x / z, v = y / z) for the edges, ...
    straight = SimpleNamespace(world_to_camera=torch.eye(4), K=torch.eye(3), width=w, height=h)
    z = torch.rand(n, generator=g) * 2 - 0.5
    u = torch.rand(n, generator=g) * (w + 20) - 10
    v = torch.rand(n, generator=g) * (h + 20) - 10
    # The edges: on the image's borders, at the near bar, NaN and infinities.
    edges = torch.tensor([0.0, w, w - 1e-4, -1e-7, float("nan"), float("inf"), -float("inf"), 1e30])
    k = len(edges)
    u[:k], v[:k] = edges, 5.5
    u[k : 2 * k], v[k : 2 * k] = 5.5, torch.tensor([0.0, h, h - 1e-4, -1e-7, float("nan"), float("inf"), -1.0, 1e30])
    u[2 * k : 3 * k], v[2 * k : 3 * k] = 5.5, 5.5
    z[: 2 * k] = 1.0
    z[2 * k : 2 * k + 4] = torch.tensor([1e-3, 1.0001e-3, float("nan"), float("inf")])
    straight_points = torch.stack([u * z, v * z, z], -1)  # at z = 1 the edges' u and v exactly
    # ... and a turned, shifted view whose points project onto pixel corners.
    rot = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0]
    turned_w2c = torch.eye(4)
    turned_w2c[:3, :3], turned_w2c[:3, 3] = rot.float(), torch.tensor([0.3, -0.2, 0.7])
    turned = SimpleNamespace(world_to_camera=turned_w2c, K=torch.tensor([[41.3, 0, 26.1], [0, 39.7, 18.4], [0, 0, 1]]),
                             width=w, height=h)
    for camera, points in ((straight, straight_points), (turned, _points_on_pixel_corners(turned, n, g))):
        err = torch.rand(h, w, generator=g)
        worst = torch.randint(0, h * w, (h, w), generator=g)
        seen, hits = torch.full((n,), 2.0), torch.zeros(n)
        seen_ref, hits_ref = seen.clone(), hits.clone()
        index, pixel = view_votes(points, camera, err, 0.7, worst, seen, hits)
        index_ref, pixel_ref = view_votes_torch(points, camera.world_to_camera, camera.K, err, 0.7, worst, seen_ref,
                                                hits_ref)
        assert 0 < index.numel() < n
        assert torch.equal(index, index_ref) and torch.equal(pixel, pixel_ref)
        assert torch.equal(seen, seen_ref) and torch.equal(hits, hits_ref)


def test_vote_projection_is_the_cameras_up_to_rounding():
    g = torch.Generator().manual_seed(4)
    rot = torch.linalg.qr(torch.randn(3, 3, generator=g, dtype=torch.float64))[0].float()
    w2c = torch.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rot, torch.tensor([0.3, -0.2, 4.0])
    camera = Camera("c", 64, 48, torch.tensor([[50.0, 0, 31.0], [0, 52.0, 23.5], [0, 0, 1]]), w2c, None)
    points = torch.randn(1000, 3, generator=g)
    for ours, theirs in zip(project_points_torch(points, w2c, camera.K), camera.project(points)):
        assert torch.allclose(ours, theirs, rtol=1e-5, atol=1e-4)


def test_carving_capped_keeps_each_chosen_points_own_colour():
    # Under the cap the chosen points carry the colours they have in the uncapped result:
    # colours are summed per view for the points kept, after the choice.
    gen = torch.Generator().manual_seed(1)
    objs = torch.tensor([[0.2, -0.1, 0.1], [-0.25, 0.2, -0.1], [0.1, 0.3, 0.25]])
    colours = torch.tensor([[1.0, 0.9, 0.1], [0.1, 0.8, 0.9], [0.9, 0.2, 0.6]])
    bg = torch.tensor([0.2, 0.3, 0.4])
    views = []
    for a in np.linspace(0, 2 * math.pi, 6, endpoint=False):
        cam = _camera(np.array([3 * math.cos(a), 3 * math.sin(a), 1.0]), [0, 0, 0])
        gt = bg.expand(cam.height, cam.width, 3).clone()
        for obj, colour in zip(objs, colours):
            gt = torch.maximum(gt, _render_points(obj[None], colour[None], cam, torch.zeros(3), scale=0.06))
        current = torch.ones_like(gt) * bg + 0.01 * torch.rand(gt.shape, generator=gen)
        views.append((cam, current, gt))
    box = PromptBox(center=(0.0, 0.0, 0.0), size=(1.0, 1.0, 1.0))
    full = carve_prompt(box, views, max_points=10**6, opacity=0.5)
    capped = carve_prompt(box, views, max_points=full.means.shape[0] // 3, generator=torch.Generator().manual_seed(0),
                          opacity=0.5)
    assert 0 < capped.means.shape[0] == full.means.shape[0] // 3
    index = {tuple(m.tolist()): i for i, m in enumerate(full.means)}
    rows = [index[tuple(m.tolist())] for m in capped.means]
    assert torch.equal(capped.colors, full.colors[rows])
    assert len({round(float(c.sum()), 3) for c in capped.colors}) > 1  # the objects' different colours


def test_carving_finds_a_faint_object_above_the_noise_and_nothing_in_noise_alone():
    # A drone of two pixels over terrain of a similar colour differs from it by a few
    # hundredths; a rendered dataset's noise is about a hundredth a pixel and differs view
    # to view. Carving must vote for the first and not for the second.
    obj = torch.tensor([[0.2, -0.1, 0.1]])
    bg = torch.tensor([0.40, 0.35, 0.30])
    gen = torch.Generator().manual_seed(0)
    faint, noise_only = [], []
    for a in np.linspace(0, 2 * math.pi, 6, endpoint=False):
        cam = _camera(np.array([3 * math.cos(a), 3 * math.sin(a), 1.0]), [0, 0, 0])
        clean = _render_points(obj, bg + 0.06, cam, bg, scale=0.06)
        noise = 0.01 * torch.randn(clean.shape, generator=gen)
        current = torch.ones_like(clean) * bg  # the model has the terrain, not the object
        faint.append((cam, current, clean + noise))
        noise_only.append((cam, current, current + noise))
    box = PromptBox(center=(0.0, 0.0, 0.0), size=(1.0, 1.0, 1.0))
    assert float((faint[0][2] - faint[0][1]).abs().mean(-1).max()) < 0.08  # under the bar of boxes the run made
    assert carve_prompt(box, faint).means.shape[0] == 0
    carved = carve_prompt(box, faint, error_threshold=DRAWN_CARVE_ERROR_THRESHOLD)  # a box drawn around it
    assert carved.means.shape[0] > 0
    assert float((carved.means - obj).norm(dim=-1).min()) < 0.05
    assert float((carved.means - obj).norm(dim=-1).max()) < 0.4
    assert carve_prompt(box, noise_only, error_threshold=DRAWN_CARVE_ERROR_THRESHOLD).means.shape[0] == 0


def test_crop_camera_renders_the_crop_of_the_full_image():
    cam = _camera(np.array([3.0, 0.5, 1.0]), [0, 0, 0])
    g = torch.Generator().manual_seed(0)
    means = torch.randn(40, 3, generator=g) * 0.5
    cols = torch.rand(40, 3, generator=g)
    full = _render_points(means, cols[:1], cam, torch.zeros(3))
    crop = crop_camera(cam, 10, 20, 32, 24)
    part = _render_points(means, cols[:1], crop, torch.zeros(3))
    assert torch.allclose(part, full[20:44, 10:42], atol=1e-5)


def test_resampling_never_runs_right_after_an_opacity_reset():
    """After a reset the render is nearly empty and carving would scatter Gaussians."""
    from promptgs_engine.focus import PromptFocus
    from promptgs_engine.strategies import DefaultSchedule

    for iterations in (600, 1000, 3000, 30_000):
        sched = DefaultSchedule.for_iterations(iterations)
        focus = PromptFocus.__new__(PromptFocus)
        focus.growth_schedule = sched
        focus.resample_every = max(2 * sched.refine_every, 20)
        steps = [s for s in range(iterations) if focus.is_resample_step(s)]
        assert len(steps) >= 3, iterations
        assert all(s % sched.reset_every >= sched.refine_every for s in steps), iterations
        assert all(sched.refine_start_iter < s < sched.refine_stop_iter for s in steps)
