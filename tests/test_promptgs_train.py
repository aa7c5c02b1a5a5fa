"""PromptGS through the trainer on the toy scene: prompts, resampling, auto prompts."""

import json

import numpy as np
import pytest
import torch

from promptgs_engine.cli import build_parser, main, train_config_from_args
from promptgs_engine.config import TrainConfig
from promptgs_engine.errors import PromptError, PromptGSError
from promptgs_engine.prompts import load_prompts
from promptgs_engine.train import Trainer
from promptgs_engine.views import rank_views


def _inside(points, box) -> int:
    return int(box.contains(torch.as_tensor(points)).sum())


def test_promptgs_resamples_into_the_prompt_and_snapshots_the_field(toy, tmp_path, caplog):
    # The toy's 128 px train at full size throughout (under the progressive floor). This
    # run once ended in NaN at step 105: the fused SSIM backward divided 0 by 0 where a
    # crop's local covariance was exactly -C2/2.
    caplog.set_level("INFO", logger="promptgs")
    box = load_prompts(toy / "prompts_1.json")[0]
    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), iterations=120, strategy="promptgs",
                      prompts=str(toy / "prompts_1.json"), checkpoint_every=0)
    trainer = Trainer(cfg, quiet=True)
    before = _inside(trainer.params["means"].detach(), box)
    assert before == 0  # the SfM points miss the drones entirely
    trainer.out.mkdir()
    trainer.train()
    assert "resampled" in caplog.text
    assert _inside(trainer.params["means"].detach(), box) > 0
    snap = np.load(trainer.snapshot())
    assert snap["field_centers"].shape[1] == 3 and snap["field_loss"].shape == snap["field_attention"].shape
    assert snap["score"].shape[0] == snap["means"].shape[0] and snap["score"].max() > 0


def test_progressive_resolution_levels(toy, tmp_path, monkeypatch):
    import promptgs_engine.focus as focus_module

    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), iterations=300, strategy="promptgs", center_prompt=False)
    focus = Trainer(cfg, quiet=True).focus
    assert [focus.downscale_at(s) for s in (0, 100, 299)] == [1, 1, 1]  # 128 px: 64 px would be under the floor of 100
    monkeypatch.setattr(focus_module, "MIN_PROGRESSIVE_WIDTH", 64)
    # With a floor of 64: 8x and 4x would leave under 64 px, so 2x (64 px) takes their
    # place and full size comes at 70% of the run, as in the paper.
    levels = [focus.downscale_at(s) for s in (0, 69, 70, 139, 140, 209, 210, 299)]
    assert levels == [2, 2, 2, 2, 2, 2, 1, 1]
    # While densification runs (steps 5 to 150), every second single-view step is at full
    # size, and from the middle of that window (step 77) every one: the strategy's growth
    # statistics come from those. The strategy learns each step's downscale (1 at full size).
    sched = focus.growth_schedule
    assert (sched.refine_start_iter, sched.refine_stop_iter) == (5, 150)
    assert focus.every_single_view_step() == 77
    cases = ((1, "random_multiview", 2.0), (2, "single", 1.0), (3, "single", 2.0), (73, "single", 2.0), (82, "single", 1.0),
             (83, "single", 1.0), (152, "single", 2.0), (153, "single", 2.0), (251, "random_multiview", 1.0))
    for step, kind, expected in cases:
        assert focus.schedule.batch(step).kind == kind
        views = focus.plan(step)
        n, (h, w) = len(views), views[0].gt.shape[:2]
        info: dict = {}
        maps = torch.zeros(n, h, w)
        focus.observe(step, views, torch.zeros(n, h, w, 3), maps, maps, None, maps, info)
        assert info["downscale"] == expected and views[0].camera.width == 128 / expected, step
        # Below full size the steps keep 3DGS's screen filter, and so do the statistics
        # steps (the only ones that vote for growth outside the prompts); other full-size
        # steps use the run's.
        statistics = step < sched.refine_stop_iter and kind == "single" and (step % 2 == 0 or step >= 77)
        assert views[0].statistics == statistics and info["votes_outside"] == statistics, step
        assert views[0].screen_filter == (0.3 if expected > 1 or statistics else None), step
    args = build_parser().parse_args(["train", str(toy), "--out", str(tmp_path / "b"), "--strategy", "promptgs", "--no-progressive"])
    cfg = train_config_from_args(args)
    assert cfg.progressive is False
    assert Trainer(cfg, quiet=True).focus.downscale_at(0) == 1


def test_auto_prompts_come_from_the_error_field(toy, tmp_path, caplog):
    caplog.set_level("INFO", logger="promptgs")
    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), iterations=200, strategy="promptgs", auto_prompts=2, checkpoint_every=0)
    trainer = Trainer(cfg, quiet=True)
    assert trainer.focus.prompts == []
    trainer.out.mkdir()
    trainer.train()
    assert "automatic prompts from the error field" in caplog.text
    assert 1 <= len(trainer.focus.prompts) <= 2


def test_a_prompt_no_camera_sees_is_a_clear_error(toy, tmp_path, capsys):
    far = {"prompts": [{"center": [0.0, 0.0, -50.0], "size": [0.5, 0.5, 0.5], "rotation_wxyz": [1, 0, 0, 0]}]}
    (tmp_path / "far.json").write_text(json.dumps(far))
    code = main(["train", str(toy), "--out", str(tmp_path / "run"), "--strategy", "promptgs", "--prompts", str(tmp_path / "far.json"), "--quiet"])
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert "prompt 0" in err and "seen by none" in err and "\n" not in err


def test_screen_filter_per_step_and_in_evaluation(toy, tmp_path, monkeypatch):
    """PromptGS renders full-size steps with its 0.1 px² filter, and low-resolution and
    statistics steps with 3DGS's 0.3; the run folder records the filter, and evaluation
    renders with it."""
    import promptgs_engine.evaluation as evaluation
    import promptgs_engine.train as train
    from promptgs_engine.run import run_training

    used: list[tuple[int, float]] = []

    def recording(module):
        real = module.render

        def render(*args, **kwargs):
            used.append((args[7], kwargs["eps2d"]))  # (width, filter)
            return real(*args, **kwargs)

        monkeypatch.setattr(module, "render", render)

    import promptgs_engine.focus as focus_module

    monkeypatch.setattr(focus_module, "MIN_PROGRESSIVE_WIDTH", 64)  # the toy's 128 px then train at 2x below
    recording(train)
    recording(evaluation)
    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), iterations=20, strategy="promptgs",
                      prompts=str(toy / "prompts_1.json"), checkpoint_every=0)
    run_training(cfg, quiet=True)
    n_train = len(used)
    assert json.loads((tmp_path / "run" / "cfg.json").read_text())["screen_filter"] == 0.1
    assert {f for w, f in used if w == 64} == {0.3}  # 2x below the toy's 128 px
    assert {f for w, f in used if w == 128} == {0.1, 0.3}  # full size: the run's, and 3DGS's on statistics steps
    evaluation.evaluate_run(tmp_path / "run", quiet=True)
    assert {f for _, f in used[n_train:]} == {0.1}  # evaluation: the run's
    n_train = len(used)
    # An old run folder (no screen_filter in cfg.json) was trained with 3DGS's filter.
    saved = json.loads((tmp_path / "run" / "cfg.json").read_text())
    del saved["screen_filter"]
    (tmp_path / "run" / "cfg.json").write_text(json.dumps(saved))
    evaluation.evaluate_run(tmp_path / "run", quiet=True)
    assert {f for _, f in used[n_train:]} == {0.3}


def test_antialiased_filter_in_training_and_evaluation(toy, tmp_path, monkeypatch):
    """An --antialiased run renders every step (low-resolution ones too) and its
    evaluation antialiased; cfg.json records it, and an old run folder reads as classic."""
    import promptgs_engine.evaluation as evaluation
    import promptgs_engine.train as train
    from promptgs_engine.run import run_training

    used: list[tuple[str, str]] = []

    def recording(module, where):
        real = module.render

        def render(*args, **kwargs):
            used.append((where, kwargs.get("rasterize_mode", "classic")))
            return real(*args, **kwargs)

        monkeypatch.setattr(module, "render", render)

    recording(train, "train")
    recording(evaluation, "eval")
    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), iterations=20, strategy="promptgs",
                      prompts=str(toy / "prompts_1.json"), checkpoint_every=0, antialiased=True)
    run_training(cfg, quiet=True)
    assert json.loads((tmp_path / "run" / "cfg.json").read_text())["antialiased"] is True
    assert {m for w, m in used if w == "train"} == {"antialiased"}
    assert {m for w, m in used if w == "eval"} == {"antialiased"}
    saved = json.loads((tmp_path / "run" / "cfg.json").read_text())
    del saved["antialiased"]
    (tmp_path / "run" / "cfg.json").write_text(json.dumps(saved))
    used.clear()
    evaluation.evaluate_run(tmp_path / "run", quiet=True)
    assert {m for _, m in used} == {"classic"}


def test_antialiased_settings(toy, tmp_path):
    def mode(**kw):
        return TrainConfig(dataset="d", out="o", **kw).rasterize_mode

    assert mode(strategy="promptgs", prompts="p.json") == "classic"
    assert mode(strategy="3dgs") == "classic"
    assert mode(strategy="promptgs", prompts="p.json", antialiased=True) == "antialiased"
    assert mode(strategy="3dgs", antialiased=True) == "antialiased"
    args = build_parser().parse_args(["train", str(toy), "--out", str(tmp_path / "r")])
    assert train_config_from_args(args).antialiased is False
    args = build_parser().parse_args(["train", str(toy), "--out", str(tmp_path / "r"), "--antialiased"])
    assert train_config_from_args(args).rasterize_mode == "antialiased"
    with pytest.raises(PromptGSError, match="antialiased"):
        TrainConfig(dataset="d", out="o", antialiased="yes").validate()


def test_screen_filter_settings(toy, tmp_path):
    assert TrainConfig(dataset="d", out="o", strategy="promptgs").effective_screen_filter == 0.1
    assert TrainConfig(dataset="d", out="o", strategy="3dgs").effective_screen_filter == 0.3
    args = build_parser().parse_args(["train", str(toy), "--out", str(tmp_path / "r"), "--screen-filter", "0.2"])
    cfg = train_config_from_args(args)
    assert cfg.screen_filter == 0.2 and cfg.effective_screen_filter == 0.2
    for bad in (0.0, -1.0, float("nan"), "wide"):
        with pytest.raises(PromptGSError, match="--screen-filter"):
            TrainConfig(dataset="d", out="o", screen_filter=bad).validate()


def test_related_steps_come_on_top_of_the_whole_view_steps(toy, tmp_path):
    # --iterations counts whole-view steps; with prompts, the related steps (crops around
    # a prompt) are added, so the rest of the scene gets as many steps as under 3DGS.
    common = dict(dataset=str(toy), iterations=40, checkpoint_every=0)
    focused = Trainer(TrainConfig(out=str(tmp_path / "p"), strategy="promptgs", prompts=str(toy / "prompts_1.json"), **common), quiet=True)
    assert focused.total_steps == 50
    crops = [any(v.crop for v in focused.plan_step(step)) for step in range(focused.total_steps)]
    assert crops.count(False) == 40 and crops.count(True) == 10
    three = Trainer(TrainConfig(out=str(tmp_path / "b"), strategy="3dgs", **common), quiet=True)
    unprompted = Trainer(TrainConfig(out=str(tmp_path / "u"), strategy="promptgs", **common), quiet=True)
    assert three.total_steps == unprompted.total_steps == 40
    # 3DGS's schedule for the iterations, stretched over the whole run.
    assert focused.schedule == three.schedule.stretched(50 / 40)
    # The centre box alone: one related step per cycle of nine (focus.CENTRE_PROMPT_RATIO),
    # the same whole-view steps; with a drawn box beside it, the paper's two in ten.
    centre = Trainer(TrainConfig(out=str(tmp_path / "c"), strategy="promptgs", center_prompt=True, **common), quiet=True)
    assert centre.total_steps == 45
    crops = [any(v.crop for v in centre.plan_step(step)) for step in range(centre.total_steps)]
    assert crops.count(False) == 40 and crops.count(True) == 5
    both = Trainer(TrainConfig(out=str(tmp_path / "cb"), strategy="promptgs", center_prompt=True,
                               prompts=str(toy / "prompts_1.json"), **common), quiet=True)
    assert both.total_steps == 50


def test_the_centre_prompt_takes_one_view_a_related_step_and_a_drawn_box_two(toy, tmp_path):
    # The centre box marks no object: one crop per related step (focus.CENTRE_PROMPT_VIEWS_PER_STEP).
    # A box drawn around objects keeps the multiview pair its tiny objects need.
    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), iterations=80, strategy="promptgs",
                      prompts=str(toy / "prompts_1.json"), center_prompt=True, checkpoint_every=0)
    focus = Trainer(cfg, quiet=True).focus
    assert len(focus.prompts) == 2 and focus.prompts[1] == focus.centre_prompt

    def crops_per_region() -> dict[int, set[int]]:
        out: dict[int, set[int]] = {}
        for entry in range(focus.total_steps):
            batch = focus.schedule.batch(entry)
            if batch.kind == "related_multiview":
                views = focus.plan(entry)
                assert all(v.crop for v in views)
                out.setdefault(batch.region, set()).add(len(views))
        return out

    assert crops_per_region() == {0: {2}, 1: {1}}
    focus.load_state_dict(focus.state_dict())  # a resumed run still knows which box is the centre
    assert crops_per_region() == {0: {2}, 1: {1}}


def test_the_centre_prompts_crops_rotate_over_every_view_that_sees_it(toy, tmp_path):
    # The centre box marks where all the cameras look: its related steps crop every view
    # that sees it in turn, a drawn box's its related_k most relevant; resampling votes in
    # the related_k best views of both.
    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), iterations=400, strategy="promptgs",
                      prompts=str(toy / "prompts_1.json"), center_prompt=True, checkpoint_every=0)
    focus = Trainer(cfg, quiet=True).focus
    seeing = [v.index for v in rank_views(focus.centre_prompt, focus.full_cameras)]
    assert len(seeing) > focus.related_k
    assert focus.schedule.regions == [focus.related[0], seeing]
    assert [len(r) for r in focus.related] == [focus.related_k, focus.related_k]

    def cropped(region: int) -> set[int]:
        out: set[int] = set()
        for entry in range(focus.total_steps):
            batch = focus.schedule.batch(entry)
            if batch.kind == "related_multiview" and batch.region == region:
                out.update(batch.views)
        return out

    assert cropped(1) == set(seeing)
    assert cropped(0) <= set(focus.related[0])
    focus.load_state_dict(focus.state_dict())  # a resumed run rotates the same way
    assert focus.schedule.regions == [focus.related[0], seeing]


def test_resampling_votes_for_fainter_errors_in_a_drawn_box_than_in_boxes_the_run_made(toy, tmp_path, monkeypatch):
    # A box the user drew around objects carves where the render misses by 0.03 (faint
    # drones); the centre box and a box the run adds later (a proposal) keep 0.08
    # (strategies.promptgs.CARVE_ERROR_THRESHOLD says why).
    from promptgs_engine import focus as focus_module
    from promptgs_engine.prompts import PromptBox
    from promptgs_engine.strategies.promptgs import CARVE_ERROR_THRESHOLD, DRAWN_CARVE_ERROR_THRESHOLD, CarvedPoints

    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), iterations=80, strategy="promptgs",
                      prompts=str(toy / "prompts_1.json"), center_prompt=True, checkpoint_every=0)
    trainer = Trainer(cfg, quiet=True)
    focus = trainer.focus
    drawn = focus.prompts[0]
    proposed = PromptBox(center=drawn.center, size=tuple(0.5 * v for v in drawn.size))
    focus.set_prompts(focus.prompts + [proposed])
    asked = {}

    def carve(box, views, **kw):
        asked[focus.prompts.index(box)] = kw["error_threshold"]
        return CarvedPoints(torch.zeros(0, 3), torch.zeros(0, 3), 0.1)

    monkeypatch.setattr(focus_module, "carve_prompt", carve)
    focus.resample(step=30, model=trainer.live_model(30))
    assert asked == {0: DRAWN_CARVE_ERROR_THRESHOLD, 1: CARVE_ERROR_THRESHOLD, 2: CARVE_ERROR_THRESHOLD}
    assert DRAWN_CARVE_ERROR_THRESHOLD < CARVE_ERROR_THRESHOLD
