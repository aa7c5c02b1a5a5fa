"""`threads.one_thread`: a training step's bookkeeping on one thread, the same bits as on two."""

import math

import pytest
import torch

from promptgs_engine.losses import edge_losses
from promptgs_engine.prompts import PromptBox
from promptgs_engine.strategies.default import ResettingDefaultStrategy
from promptgs_engine.strategies.promptgs import PromptGSStrategy
from promptgs_engine.threads import one_thread


@pytest.fixture
def two_threads():
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    yield
    torch.set_num_threads(before)


def test_one_thread_inside_and_the_callers_count_after_also_on_an_error(two_threads):
    with one_thread():
        assert torch.get_num_threads() == 1
        with one_thread():  # nested: still one, and the outer block keeps its one
            assert torch.get_num_threads() == 1
        assert torch.get_num_threads() == 1
    assert torch.get_num_threads() == 2
    with pytest.raises(RuntimeError, match="inside"):
        with one_thread():
            raise RuntimeError("inside")
    assert torch.get_num_threads() == 2


def _step(n: int, cameras: int, seed: int = 0):
    """A PromptGS statistics step's inputs: ``n`` Gaussians (over torch's 32,768-element
    grain, two threads split the work), ``cameras`` views of 200×150."""
    g = torch.Generator().manual_seed(seed)
    params = {
        "means": torch.rand(n, 3, generator=g) * 4 - 2, "scales": torch.randn(n, 3, generator=g) - 4,
        "opacities": torch.randn(n, generator=g),
    }
    means2d = (torch.rand(cameras, n, 2, generator=g) * torch.tensor([200.0, 150.0])).requires_grad_()
    means2d.grad = torch.randn(cameras, n, 2, generator=g) * 1e-4
    radii = (torch.rand(cameras, n, 2, generator=g) * 6).to(torch.int32)  # about a sixth unseen
    info = {
        "means2d": means2d, "radii": radii, "depths": torch.rand(cameras, n, generator=g) * 5, "width": 200,
        "height": 150, "n_cameras": cameras, "gaussian_ids": None, "view_loss": torch.rand(cameras, generator=g),
        "error_map": torch.rand(cameras, 150, 200, generator=g), "votes_outside": False,
    }
    return params, info


def test_a_steps_statistics_run_on_one_thread(two_threads, monkeypatch):
    seen = []
    add_statistics = PromptGSStrategy.add_statistics

    def spy(self, *args, **kwargs):
        seen.append(torch.get_num_threads())
        return add_statistics(self, *args, **kwargs)

    monkeypatch.setattr(PromptGSStrategy, "add_statistics", spy)
    params, info = _step(1000, 1)
    s = PromptGSStrategy(refine_start_iter=0, refine_stop_iter=10_000, refine_every=100, reset_every=10_000)
    s._update_state(params, s.initialize_state(scene_scale=1.0), dict(info, votes_outside=True))
    assert seen == [1] and torch.get_num_threads() == 2


@pytest.mark.parametrize("cameras", [1, 2])
def test_prompt_statistics_on_one_thread_are_the_bits_of_two(two_threads, monkeypatch, cameras):
    """`PromptGSStrategy._update_state` runs under `one_thread`; its growth statistics,
    scores, view counts and errors equal those of the same step on two threads (both
    strategies' `_update_state` undecorated)."""
    params, info = _step(40_000, cameras)
    results = []
    for on_two in (False, True):
        update = PromptGSStrategy._update_state
        if on_two:  # both strategies' statistics undecorated: two threads split the work
            monkeypatch.setattr(ResettingDefaultStrategy, "_update_state", ResettingDefaultStrategy._update_state.__wrapped__)
            update = update.__wrapped__
        s = PromptGSStrategy(refine_start_iter=0, refine_stop_iter=10_000, refine_every=100, reset_every=10_000,
                             prompts=[PromptBox(center=(0.0, 0.0, 0.0), size=(2.0, 2.0, 2.0))])
        state = s.initialize_state(scene_scale=1.0)
        update(s, params, state, dict(info, votes_outside=True))  # a whole view at full size
        update(s, params, state, info)  # a crop: statistics inside the prompt only
        results.append(state)
        assert torch.get_num_threads() == 2
    for key in ("grad2d", "count", "score", "views", "error"):
        assert torch.equal(results[0][key], results[1][key]), key
    assert float(results[0]["score"].sum()) > 0 and float(results[0]["error"].sum()) > 0


def test_edge_losses_on_one_thread_are_the_bits_of_two(two_threads):
    g = torch.Generator().manual_seed(1)
    img, ref = torch.rand(2, 150, 200, 3, generator=g), torch.rand(2, 150, 200, 3, generator=g)
    on_two = edge_losses(img, ref)
    with one_thread():
        on_one = edge_losses(img, ref)
    assert torch.equal(on_one, on_two) and math.isfinite(float(on_one.sum()))
