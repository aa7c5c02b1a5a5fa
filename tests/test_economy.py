"""Gaussian economy: PromptGS grows no more Gaussians than 3DGS on a sparse, smooth scene."""

import pytest

from promptgs_engine.config import TrainConfig
from promptgs_engine.train import Trainer


@pytest.fixture(scope="module")
def smooth_toy(tmp_path_factory):
    """A 64×48 toy scene without texture noise, its SfM points dense on the ground: the
    start already draws most of it, so what PromptGS adds (resampling, growth in the box,
    growth the narrow screen filter provokes) is not lost in 3DGS's own growth. (When
    every PromptGS step voted for growth outside the prompts, with the 0.1 px² filter,
    PromptGS ended with 24.1k Gaussians here against 3DGS's 22.9k, and this test failed.)"""
    from promptgs_engine.bench.toy_scene import ToySceneConfig, make_toy_scene

    cfg = ToySceneConfig(width=64, height=48, focal=55.0, n_views=12, ground_grid=30, texture_noise=0.0, n_sfm_points=3000)
    return make_toy_scene(tmp_path_factory.mktemp("smooth") / "scene", cfg)


def _train(dataset, out, **kw) -> Trainer:
    cfg = TrainConfig(dataset=str(dataset), out=str(out), iterations=100, checkpoint_every=0, sky=False, **kw)
    trainer = Trainer(cfg, quiet=True)
    trainer.out.mkdir(parents=True)
    trainer.train()
    return trainer


def test_promptgs_grows_no_more_than_3dgs_on_a_sparse_scene(smooth_toy, tmp_path):
    base = _train(smooth_toy, tmp_path / "3dgs", strategy="3dgs")
    pgs = _train(smooth_toy, tmp_path / "pgs", strategy="promptgs", prompts=str(smooth_toy / "prompts_1.json"))
    ledger = pgs.strategy_state["ledger"]
    # Resampling did add Gaussians to the box (the economy is not bought by doing nothing) ...
    assert ledger["resampled"] > 0 and ledger["refinements"]
    # ... and the model still ends with no more Gaussians than 3DGS's.
    assert pgs.n_gaussians <= base.n_gaussians, (pgs.n_gaussians, base.n_gaussians, ledger)
    assert base.strategy_state["ledger"]["grown"] > 0
