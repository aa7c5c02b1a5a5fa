"""PromptGS through the trainer on the toy scene: prompts, resampling, auto prompts."""

import json

import numpy as np
import pytest
import torch

from promptgs_engine.cli import build_parser, main, train_config_from_args
from promptgs_engine.config import TrainConfig
from promptgs_engine.errors import PromptError
from promptgs_engine.prompts import load_prompts
from promptgs_engine.train import Trainer


def _inside(points, box) -> int:
    return int(box.contains(torch.as_tensor(points)).sum())


def test_promptgs_resamples_into_the_prompt_and_snapshots_the_field(toy, tmp_path, caplog):
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


def test_progressive_resolution_levels(toy, tmp_path):
    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), iterations=300, strategy="promptgs", center_prompt=False)
    focus = Trainer(cfg, quiet=True).focus
    # 128 px wide: 8x and 4x would leave under 64 px, so 2x (64 px) takes their place
    # and full size comes at 70% of the run, as in the paper.
    levels = [focus.downscale_at(s) for s in (0, 69, 70, 139, 140, 209, 210, 299)]
    assert levels == [2, 2, 2, 2, 2, 2, 1, 1]
    # While densification runs (to step 150), every second single-view step is at full
    # size: the strategy's growth statistics come from those. The strategy learns each
    # step's downscale (1 at full size).
    sched = focus.trainer.schedule
    assert sched.refine_stop_iter == 150
    for step, kind, expected in ((1, "random_multiview", 2.0), (2, "single", 1.0), (3, "single", 2.0), (152, "single", 2.0), (251, "random_multiview", 1.0)):
        assert focus.schedule.batch(step).kind == kind
        views = focus.plan(step)
        n, (h, w) = len(views), views[0].gt.shape[:2]
        info: dict = {}
        maps = torch.zeros(n, h, w)
        focus.observe(step, views, torch.zeros(n, h, w, 3), maps, maps, None, maps, info)
        assert info["downscale"] == expected and views[0].camera.width == 128 / expected, step
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
