"""Compaction (--compact): blending-weight importance, the cut, and prompt protection."""

import json
import math
from pathlib import Path

import numpy as np
import torch

from promptgs_engine.bench.toy_scene import look_at
from promptgs_engine.compaction import Importance, blending_weights, compact, removal_mask
from promptgs_engine.config import TrainConfig
from promptgs_engine.data import Camera
from promptgs_engine.gaussians import init_from_points
from promptgs_engine.prompts import PromptBox, load_prompts
from promptgs_engine.render import render
from promptgs_engine.train import Trainer, make_optimizers


def _camera(center, target=(0.0, 0.0, 0.0), size=48, f=50.0):
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float32)
    m = look_at(np.asarray(center, float), np.asarray(target, float))
    return Camera("c", size, size, K, torch.tensor(m, dtype=torch.float32), Path("none"))


def _scene():
    """A wall of large Gaussians at x = -1 and, in front of it, a tiny object: three
    Gaussians a few hundredths across (about one pixel in the views, the third one faint)
    inside a prompt box, and three alike outside it."""
    ys, zs = torch.meshgrid(torch.linspace(-1.5, 1.5, 12), torch.linspace(-1.5, 1.5, 12), indexing="ij")
    wall = torch.stack([torch.full_like(ys, -1.0), ys, zs], -1).reshape(-1, 3)
    tiny_in = torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.04, 0.0], [0.0, 0.0, 0.04]])
    tiny_out = tiny_in + torch.tensor([0.0, 0.8, 0.6])
    means = torch.cat([wall, tiny_in, tiny_out])
    n = means.shape[0]
    params = init_from_points(means, torch.full((n, 3), 0.5), sh_degree=0, init_opacity=0.9)
    with torch.no_grad():
        params["scales"][: wall.shape[0]] = math.log(0.15)
        params["scales"][wall.shape[0] :] = math.log(0.01)
        faint = torch.tensor([wall.shape[0] + 2, wall.shape[0] + 5])
        params["opacities"][faint] = math.log(0.03 / 0.97)  # opacity 0.03
    optimizers = make_optimizers(params, TrainConfig(dataset="d", out="o"), extent=1.0)
    cams = [_camera((3.0, 0.6 * math.sin(a), 0.6 * math.cos(a))) for a in np.linspace(0, 2 * math.pi, 5, endpoint=False)]
    box = PromptBox(center=(0.0, 0.02, 0.02), size=(0.2, 0.2, 0.2))
    idx_in = torch.arange(wall.shape[0], wall.shape[0] + 3)
    idx_out = torch.arange(wall.shape[0] + 3, n)
    return params, optimizers, cams, box, idx_in, idx_out


def _render_fn(params):
    def fn(cams, colors):
        return render(
            params["means"].detach(), params["quats"].detach(), torch.exp(params["scales"].detach()),
            torch.sigmoid(params["opacities"].detach()), colors, torch.stack([c.world_to_camera for c in cams]),
            torch.stack([c.K for c in cams]), cams[0].width, cams[0].height, sh_degree=None, backend="cpu",
        )

    return fn


def test_importance_is_each_gaussians_share_of_the_rendered_alpha():
    params, _, cams, _, idx_in, _ = _scene()
    imp = blending_weights(_render_fn(params), params, cams)
    # Σ_g α_g·T_g = 1 − T_final = the pixel's alpha: the importances add up to the alpha
    # rendered over all pixels of all views.
    alpha = sum(float(_render_fn(params)([c], torch.ones(params["means"].shape[0], 1))[1].sum()) for c in cams)
    assert abs(float(imp.total.sum()) - alpha) < 1e-3 * alpha
    # The wall's Gaussians cover tens of pixels in each view, the tiny ones one or two.
    wall = imp.total[: idx_in[0]]
    assert float(wall.min()) > 5 * float(imp.total[idx_in].max())
    assert bool((imp.peak_view <= imp.total + 1e-6).all())


def test_removal_takes_the_least_important_fraction_within_the_weight_cap():
    total = torch.tensor([5.0, 0.1, 3.0, 0.2, 0.3, 91.4])  # sums to 100
    imp = Importance(total=total, peak_view=total)
    # Half of the six: the three smallest, 0.6 of the weight in all.
    assert removal_mask(imp, None, 0.5, 0.05).tolist() == [False, True, False, True, True, False]
    # At most 0.4 of the weight: 0.1 + 0.2 fit, 0.3 more does not.
    assert removal_mask(imp, None, 0.5, 0.004).tolist() == [False, True, False, True, False, False]
    # A protected one is skipped, and the next least important is taken in its place.
    protected = torch.tensor([False, True, False, False, False, False])
    assert removal_mask(imp, protected, 0.5, 0.05).tolist() == [False, False, True, True, True, False]


def test_compaction_never_removes_a_prompted_objects_gaussians():
    params, optimizers, cams, box, idx_in, idx_out = _scene()
    object_means = params["means"][idx_in].detach().clone()
    outside_means = params["means"][idx_out].detach().clone()
    imp = blending_weights(_render_fn(params), params, cams)
    n = params["means"].shape[0]
    # The six tiny Gaussians are the least important: removing 6 takes them all ...
    assert bool(removal_mask(imp, None, 6 / n)[torch.cat([idx_in, idx_out])].all())
    # ... but the object inside the prompt draws its pixels with them, so they stay; the
    # faint one too, though it carries only a few hundredths of a pixel in any view.
    assert float(imp.peak_view[idx_in[:2]].min()) >= 0.25 and 0.0 < float(imp.peak_view[idx_in[2]]) < 0.1
    state = {"grad2d": torch.zeros(n), "count": torch.zeros(n)}
    summary = compact(params, optimizers, state, imp, prompts=[box], fraction=6 / n)
    assert summary["removed"] == 6 and summary["protected"] == 3
    kept = params["means"].detach()
    for m in object_means:
        assert bool((kept - m).norm(dim=-1).min() < 1e-6)
    # The same tiny Gaussians outside the prompt are not protected: they go.
    for m in outside_means:
        assert bool((kept - m).norm(dim=-1).min() > 1e-3)
    # Optimizer and strategy state follow the removal.
    assert state["grad2d"].shape[0] == n - 6
    assert optimizers["means"].param_groups[0]["params"][0].shape[0] == n - 6


def test_compact_in_training_keeps_the_drones_in_the_prompt(toy, tmp_path, monkeypatch):
    import promptgs_engine.compaction as compaction

    seen = {}
    real_compact = compaction.compact

    def checked(params, optimizers, state, importance, prompts=(), **kw):
        # What the prompts' objects are drawn with, and what a cut without the
        # protection would have taken of it.
        protected = compaction.prompt_protection(params["means"], importance, prompts, kw["protect_pixels"])
        unprotected_cut = compaction.removal_mask(importance, None, kw["fraction"], kw["max_weight"])
        seen["object"] = params["means"][protected].detach().clone()
        seen["at_risk"] = int((protected & unprotected_cut).sum())
        summary = real_compact(params, optimizers, state, importance, prompts, **kw)
        seen["after"] = params["means"].detach().clone()
        return summary

    monkeypatch.setattr(compaction, "compact", checked)
    prompts = load_prompts(toy / "prompts_2.json")
    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), iterations=60, strategy="promptgs",
                      prompts=str(toy / "prompts_2.json"), compact=True, checkpoint_every=0)
    trainer = Trainer(cfg, quiet=True)
    trainer.out.mkdir()
    summary = trainer.train()
    done = summary["compaction"]
    # 60 whole-view steps and 15 related ones (focus.run_length); 3DGS's schedule for 60
    # steps (growth until 30) stretched by 75/60.
    assert (trainer.total_steps, trainer.schedule.refine_stop_iter) == (75, 38)
    assert done["step"] == trainer.compaction_at == 45  # 60% of the run, after densification stops
    assert done["removed"] > 0 and done["after"] == done["before"] - done["removed"]
    assert done["protected"] == seen["object"].shape[0] > 0
    # A global cut would have taken some of the drones' Gaussians; every one is still there.
    assert seen["at_risk"] > 0
    exact = torch.cdist(seen["object"], seen["after"], compute_mode="donot_use_mm_for_euclid_dist")
    assert float(exact.min(dim=1).values.max()) < 1e-6
    inside = torch.stack([b.contains(trainer.params["means"].detach()) for b in prompts]).any(0)
    assert int(inside.sum()) >= done["protected"]
    (tmp_path / "job.json").write_text(json.dumps({"compact": True}))
    from promptgs_engine.cli import build_parser, train_config_from_args

    args = build_parser().parse_args(["train", str(toy), "--out", str(tmp_path / "b"), "--job", str(tmp_path / "job.json")])
    assert train_config_from_args(args).compact is True


def test_a_progressive_run_compacts_once_its_whole_views_are_at_full_size(toy, tmp_path, monkeypatch):
    # Compacting while PromptGS still trains below full size left its fine-tuning at full
    # size shorter than 3DGS's: the mountain lost up to 0.18 dB to the cut.
    import promptgs_engine.focus as focus_module

    monkeypatch.setattr(focus_module, "MIN_PROGRESSIVE_WIDTH", 64)  # the 128 px toy gets 2x levels
    common = dict(dataset=str(toy), iterations=300, compact=True, checkpoint_every=0)
    pgs = Trainer(TrainConfig(out=str(tmp_path / "p"), strategy="promptgs", prompts=str(toy / "prompts_1.json"), **common), quiet=True)
    step = pgs.compaction_at
    assert pgs.total_steps == 375 and step > int(0.6 * 375)
    assert step == pgs.focus.full_size_step()
    assert pgs.focus.downscale_at(step - 1) == 2 and pgs.focus.downscale_at(step) == 1
    baseline = Trainer(TrainConfig(out=str(tmp_path / "b"), strategy="3dgs", **common), quiet=True)
    assert baseline.compaction_at == int(0.6 * 300)
