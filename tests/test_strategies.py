import torch
from gsplat.strategy import DefaultStrategy

from promptgs_engine.gaussians import init_from_points
from promptgs_engine.strategies import DefaultSchedule, make_default_strategy
from promptgs_engine.train import make_optimizers
from promptgs_engine.config import TrainConfig


def _setup(n=20):
    g = torch.Generator().manual_seed(0)
    params = init_from_points(torch.randn(n, 3, generator=g), torch.rand(n, 3, generator=g), sh_degree=0, init_opacity=0.9)
    opts = make_optimizers(params, TrainConfig(dataset="d", out="o"), extent=1.0)
    return params, opts


def _fake_info(n):
    means2d = torch.zeros(1, n, 2, requires_grad=True)
    means2d.grad = torch.zeros(1, n, 2)
    return {
        "means2d": means2d,
        "radii": torch.ones(1, n, 2, dtype=torch.int32),
        "width": 10,
        "height": 10,
        "n_cameras": 1,
        "gaussian_ids": None,
    }


def test_gsplat_default_strategy_never_resets_opacity():
    """Documents gsplat 1.5.3's precedence bug that ResettingDefaultStrategy works around."""
    params, opts = _setup()
    s = DefaultStrategy(refine_start_iter=10_000, refine_stop_iter=20_000, reset_every=100)
    state = s.initialize_state()
    before = params["opacities"].detach().clone()
    s.step_post_backward(params, opts, state, step=100, info=_fake_info(20))
    assert torch.equal(params["opacities"].detach(), before)


def test_resetting_strategy_resets_opacity_on_schedule():
    params, opts = _setup()
    sched = DefaultSchedule(refine_start_iter=10_000, refine_stop_iter=20_000, refine_every=100, reset_every=100, sh_degree_interval=100)
    s = make_default_strategy("3dgs", sched)
    state = s.initialize_state()
    s.step_post_backward(params, opts, state, step=99, info=_fake_info(20))
    assert torch.allclose(torch.sigmoid(params["opacities"]), torch.full((20,), 0.9))
    s.step_post_backward(params, opts, state, step=100, info=_fake_info(20))
    assert torch.all(torch.sigmoid(params["opacities"]) <= s.prune_opa * 2.0 + 1e-6)


def test_absgs_uses_absolute_gradients_with_higher_threshold():
    sched = DefaultSchedule.for_iterations(3000)
    a, b = make_default_strategy("3dgs", sched), make_default_strategy("absgs", sched)
    assert not a.absgrad and b.absgrad and b.grow_grad2d == 4 * a.grow_grad2d


def test_schedule_scales_with_run_length():
    full = DefaultSchedule.for_iterations(30_000)
    assert (full.refine_start_iter, full.refine_stop_iter, full.refine_every, full.reset_every) == (500, 15_000, 100, 3000)
    short = DefaultSchedule.for_iterations(3000)
    assert short.refine_stop_iter == 1500 and short.reset_every == 300
    assert short.refine_start_iter < short.refine_stop_iter


def test_a_stretched_schedule_keeps_its_growth_rounds_and_resets():
    # PromptGS adds its related steps to a run (focus.run_length): the stretched schedule
    # must not fit in an extra growth round (12k Gaussians late in a mountain run).
    def rounds(s):  # gsplat's refinement condition
        return sum(1 for t in range(s.refine_stop_iter) if t > s.refine_start_iter and t % s.refine_every == 0)

    def resets(s):
        return sum(1 for t in range(1, s.refine_stop_iter) if t % s.reset_every == 0)

    for n in (100, 600, 1000, 1500, 3000, 7000, 30_000):
        base = DefaultSchedule.for_iterations(n)
        longer = base.stretched(1.25)
        assert longer.refine_stop_iter > base.refine_stop_iter
        assert (rounds(longer), resets(longer)) == (rounds(base), resets(base)), n


def test_grad2d_statistics_equal_gsplats_bit_for_bit():
    """ResettingDefaultStrategy's masked accumulation against gsplat's gather/index_add_
    version, over two cameras with Gaussians seen by one, both or none."""
    n = 500
    g = torch.Generator().manual_seed(3)
    for absgrad in (False, True):
        ours = make_default_strategy("absgs" if absgrad else "3dgs", DefaultSchedule.for_iterations(1000))
        ref = DefaultStrategy(absgrad=absgrad)
        params, _ = _setup(n)
        s_ours, s_ref = ours.initialize_state(), ref.initialize_state()
        for _ in range(3):
            means2d = torch.zeros(2, n, 2, requires_grad=True)
            means2d.grad = torch.randn(2, n, 2, generator=g) * 1e-3
            means2d.absgrad = means2d.grad.abs() * 1.5
            radii = (torch.rand(2, n, 2, generator=g) * 3).to(torch.int32)  # zeros: not visible
            info = {"means2d": means2d, "radii": radii, "width": 64, "height": 48, "n_cameras": 2, "gaussian_ids": None}
            ours._update_state(params, s_ours, info)
            ref._update_state(params, s_ref, info)
        assert s_ours["count"].max() >= 2 and (s_ours["count"] == 0).any()
        assert torch.equal(s_ours["grad2d"], s_ref["grad2d"]) and torch.equal(s_ours["count"], s_ref["count"])
