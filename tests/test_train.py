"""The trainer and the CLI end to end, on the pinhole scenes (tests/scenes.py) and a small toy scene."""

import json
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from promptgs_engine.cli import main
from promptgs_engine.config import TrainConfig
from promptgs_engine.data import load_colmap_scene
from promptgs_engine.errors import PromptGSError, TrainingError
from promptgs_engine.evaluation import evaluate
from promptgs_engine.run import run_training
from promptgs_engine.train import Trainer


def test_training_raises_test_psnr(pinhole_scene, tmp_path):
    scene = load_colmap_scene(pinhole_scene.path, images=pinhole_scene.small)
    cfg = TrainConfig(dataset=str(pinhole_scene.path), out=str(tmp_path / "run"), images=pinhole_scene.small, iterations=200,
                      checkpoint_every=0)
    trainer = Trainer(cfg, scene=scene, quiet=True)
    before = evaluate(trainer.params, scene.test_cameras[:4], quiet=True)["psnr"]
    trainer.out.mkdir()
    trainer.train()
    after = evaluate(trainer.params, scene.test_cameras[:4], quiet=True)["psnr"]
    assert after > before + 3.0, (before, after)
    assert trainer.n_gaussians > scene.points.shape[0]  # densification happened


def test_cli_train_eval_render_and_resume(toy, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", str(toy), "--out", str(out), "--iterations", "30", "--quiet"]) == 0
    for name in ("cfg.json", "ckpt.pt", "point_cloud.ply", "metrics.json", "train.log"):
        assert (out / name).is_file(), name
    metrics = json.loads((out / "metrics.json").read_text())
    for key in ("psnr", "ssim", "n_gaussians", "train_seconds", "iterations", "backend", "masked_psnr", "object_region_psnr"):
        assert key in metrics, key
    # "auto" trains on a CUDA GPU when there is one.
    assert metrics["iterations"] == 30 and metrics["backend"] == ("cuda" if torch.cuda.is_available() else "cpu")
    # The toy scene has object masks: every test view has a drone in it.
    assert metrics["n_masked_views"] == metrics["n_test_views"] > 0

    # A finished run is never overwritten by accident...
    capsys.readouterr()
    assert main(["train", str(toy), "--out", str(out), "--iterations", "30", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("promptgs: error:") and "already holds a finished run" in err and "\n" not in err
    # ...but can be extended from its checkpoint.
    assert main(["train", str(toy), "--out", str(out), "--iterations", "40", "--resume", "--quiet"]) == 0
    assert json.loads((out / "metrics.json").read_text())["iterations"] == 40

    assert main(["eval", str(out), "--masks", str(toy / "object_masks"), "--quiet"]) == 0
    assert main(["render", str(out), "--camera", "view_003.png", "--out", str(tmp_path / "png"), "--quiet"]) == 0
    assert (tmp_path / "png" / "view_003.png").is_file()
    assert main(["render", str(out), "--camera", "nope.png", "--out", str(tmp_path / "png")]) == 2


def test_a_far_sky_shell_starts_beside_the_sfm_points_unless_turned_off(toy, tmp_path):
    from promptgs_engine.cli import build_parser, train_config_from_args

    scene = load_colmap_scene(toy)
    n_sfm = scene.points.shape[0]
    with_sky = Trainer(TrainConfig(dataset=str(toy), out=str(tmp_path / "a")), scene=scene, quiet=True)
    assert with_sky.n_sky_points > 0
    assert with_sky.n_gaussians == n_sfm + with_sky.n_sky_points
    assert with_sky.run_summary()["initial_gaussians"] == with_sky.n_gaussians  # train.json
    # The shell lies outside every SfM point, seen from the cameras' centre.
    centre = torch.stack([c.center for c in scene.train_cameras]).mean(dim=0)
    shell = with_sky.params["means"][n_sfm:].detach().cpu()  # on the GPU where "auto" picks it
    assert float((shell - centre).norm(dim=1).min()) > float((scene.points.float() - centre).norm(dim=1).max())
    args = build_parser().parse_args(["train", str(toy), "--out", str(tmp_path / "b"), "--no-sky"])
    cfg = train_config_from_args(args)
    assert cfg.sky is False
    without = Trainer(cfg, scene=scene, quiet=True)
    assert without.n_sky_points == 0 and without.n_gaussians == n_sfm


def test_an_interrupted_run_resumes_to_the_same_result(toy, tmp_path, monkeypatch):
    # The CPU backend adds in a fixed order; gsplat's CUDA backward adds with atomics, so
    # there two runs, resumed or not, agree only to rounding.
    a = TrainConfig(dataset=str(toy), out=str(tmp_path / "a"), iterations=40, checkpoint_every=20, seed=3, backend="cpu")
    run_training(a, quiet=True)
    straight = torch.load(tmp_path / "a" / "ckpt.pt", weights_only=False)

    b = TrainConfig(dataset=str(toy), out=str(tmp_path / "b"), iterations=40, checkpoint_every=20, seed=3, backend="cpu")
    real_step = Trainer.train_step

    def interrupted(self, **kwargs):
        if self.step == 25:
            raise KeyboardInterrupt
        return real_step(self, **kwargs)

    monkeypatch.setattr(Trainer, "train_step", interrupted)
    with pytest.raises(KeyboardInterrupt):
        run_training(b, quiet=True)
    assert torch.load(tmp_path / "b" / "ckpt.pt", weights_only=False)["step"] == 20
    assert not (tmp_path / "b" / "point_cloud.ply").exists()
    monkeypatch.setattr(Trainer, "train_step", real_step)
    run_training(b, resume=True, quiet=True)
    resumed = torch.load(tmp_path / "b" / "ckpt.pt", weights_only=False)
    assert resumed["step"] == straight["step"] == 40
    assert "resumed at step 20" in (tmp_path / "b" / "train.log").read_text()
    # Same camera order, optimizer and strategy state, and a backward that adds in a fixed
    # order: the resumed run ends with exactly the parameters of the straight one.
    assert resumed["order"] == straight["order"]
    for name, value in straight["params"].items():
        assert torch.equal(resumed["params"][name], value), name
    psnr_a = json.loads((tmp_path / "a" / "metrics.json").read_text())["psnr"]
    psnr_b = json.loads((tmp_path / "b" / "metrics.json").read_text())["psnr"]
    assert psnr_a == psnr_b


@pytest.mark.parametrize(
    "make_bad, expected",
    [
        (lambda d: d / "missing", "missing"),
        (lambda d: d, "sparse"),  # an empty folder: no model
    ],
)
def test_bad_dataset_is_one_line_error_and_writes_nothing(tmp_path, capsys, make_bad, expected):
    bad = make_bad(tmp_path / "data")
    if bad.name == "data":
        bad.mkdir()
    out = tmp_path / "out"
    assert main(["train", str(bad), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("promptgs: error:") and "\n" not in err and expected in err
    assert not out.exists()


def test_train_without_a_run_folder_or_dataset_names_the_missing_option(toy, capsys):
    assert main(["train", str(toy), "--quiet"]) == 2
    assert "train needs a run folder (--out" in capsys.readouterr().err
    assert main(["train", "--out", "unused", "--quiet"]) == 2
    assert "train needs a dataset (the DATASET argument" in capsys.readouterr().err


def test_a_run_folder_without_a_checkpoint_is_not_offered_for_resume(toy, tmp_path, capsys):
    out = tmp_path / "out"
    out.mkdir()
    (out / "cfg.json").write_text("{}")  # a run that failed before its first checkpoint
    assert main(["train", str(toy), "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "stopped before its first checkpoint (use --overwrite" in err and "--resume" not in err
    assert (out / "cfg.json").read_text() == "{}"


def test_prompts_with_a_baseline_strategy_are_a_one_line_error_and_write_nothing(toy, tmp_path, capsys):
    """3DGS and AbsGS train without prompts: boxes given to them are refused, not ignored
    (a run the user took for PromptGS would otherwise train plain 3DGS)."""
    boxes = tmp_path / "boxes.json"
    boxes.write_text(json.dumps({"prompts": [{"center": [0, 0, 0], "size": [1, 1, 1], "rotation_wxyz": [1, 0, 0, 0]}]}))
    out = tmp_path / "out"
    assert main(["train", str(toy), "--out", str(out), "--prompts", str(boxes), "--quiet"]) == 2  # default strategy: 3dgs
    err = capsys.readouterr().err.strip()
    assert err.startswith("promptgs: error:") and "\n" not in err
    assert "--prompts needs --strategy promptgs" in err and "'3dgs'" in err
    assert not out.exists()
    with pytest.raises(PromptGSError, match="--center-prompt and --auto-prompts needs --strategy promptgs"):
        TrainConfig(dataset=str(toy), out=str(out), strategy="absgs", center_prompt=True, auto_prompts=2).validate()
    # an inline prompt object without boxes asks for none; with PromptGS every option is accepted
    TrainConfig(dataset=str(toy), out=str(out), strategy="3dgs", prompts={"prompts": []}).validate()
    TrainConfig(dataset=str(toy), out=str(out), strategy="promptgs", prompts=str(boxes), center_prompt=True).validate()
    # with PromptGS, a missing prompt file or a box that no camera sees writes nothing either
    far = tmp_path / "far.json"
    far.write_text(json.dumps({"prompts": [{"center": [0, 0, 1e6], "size": [1, 1, 1], "rotation_wxyz": [1, 0, 0, 0]}]}))
    for prompt_file, expected in ((tmp_path / "missing.json", "prompt file not found"), (far, "far.json: prompt 0")):
        assert main(["train", str(toy), "--out", str(out), "--strategy", "promptgs", "--prompts", str(prompt_file), "--quiet"]) == 2
        err = capsys.readouterr().err.strip()
        assert err.startswith("promptgs: error:") and "\n" not in err and expected in err, err
        assert not out.exists()
    # a 3DGS run folder written before (the add-on sent its boxes with every strategy) still loads
    saved = TrainConfig(dataset=str(toy), out=str(out), strategy="3dgs").to_json() | {"prompts": str(boxes), "auto_prompts": 2}
    (tmp_path / "cfg.json").write_text(json.dumps(saved))
    loaded = TrainConfig.load(tmp_path / "cfg.json")
    loaded.validate()
    assert loaded.prompts is None and loaded.auto_prompts == 0


def test_nan_is_reported_with_step_and_parameter_and_keeps_the_checkpoint(toy, tmp_path):
    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), iterations=40, checkpoint_every=10)
    trainer = Trainer(cfg, quiet=True)
    trainer.out.mkdir()
    real_step = trainer.train_step

    def poisoned_step(**kwargs):
        result = real_step(**kwargs)
        if trainer.step == 14:
            with torch.no_grad():
                trainer.params["opacities"][0] = float("nan")
            trainer.check_finite()
        return result

    trainer.train_step = poisoned_step
    with pytest.raises(TrainingError, match=r"step 14: NaN/inf in parameter 'opacities'"):
        trainer.train()
    ckpt = torch.load(trainer.out / "ckpt.pt", weights_only=False)
    assert ckpt["step"] == 10
    assert torch.isfinite(ckpt["params"]["opacities"]).all()


def test_events_stream_is_json_lines_from_start_to_done(toy, tmp_path):
    job = {"dataset": str(toy), "out": str(tmp_path / "run"), "iterations": 20, "snapshot_every": 10, "strategy": "3dgs"}
    (tmp_path / "job.json").write_text(json.dumps(job))
    proc = subprocess.run(
        [sys.executable, "-m", "promptgs_engine", "train", "--job", str(tmp_path / "job.json"), "--events"],
        capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    events = [json.loads(line) for line in proc.stdout.splitlines()]
    kinds = [e["event"] for e in events]
    assert kinds[0] == "start" and kinds[-1] == "done"
    assert kinds.count("snapshot") == 2 and "progress" in kinds
    assert all(math.isfinite(e["psnr"]) for e in events if e["event"] == "progress")  # measured on reported steps
    snap = np.load(next(e["path"] for e in events if e["event"] == "snapshot"))
    n = snap["means"].shape[0]
    for key, shape in {"opacity": (n,), "scale": (n, 3), "rotation": (n, 4), "color": (n, 3), "score": (n,), "error": (n,)}.items():
        assert snap[key].shape == shape, key
    assert np.allclose(np.linalg.norm(snap["rotation"], axis=1), 1.0, atol=1e-5)
    done = events[-1]
    assert Path(done["ply"]).is_file() and math.isfinite(done["metrics"]["psnr"])


def test_a_step_that_skips_its_psnr_trains_the_same_to_the_bit(toy, tmp_path):
    def three_steps(psnr: bool):
        cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / f"run-{psnr}"), iterations=10, checkpoint_every=0)
        trainer = Trainer(cfg, quiet=True)
        results = []
        for _ in range(3):
            results.append(trainer.train_step(psnr=psnr))
            trainer.step += 1
        return results, {k: v.detach().clone() for k, v in trainer.params.items()}

    measured, params = three_steps(True)
    skipped, params_skipped = three_steps(False)
    assert all(math.isfinite(r.psnr) for r in measured) and all(r.psnr is None for r in skipped)
    assert [r.loss for r in measured] == [r.loss for r in skipped]
    for key in params:
        assert torch.equal(params[key], params_skipped[key]), key


def test_events_report_errors_as_an_event_and_exit_code(tmp_path):
    proc = subprocess.run(
        [sys.executable, "-m", "promptgs_engine", "train", str(tmp_path / "nowhere"), "--out", str(tmp_path / "o"), "--events"],
        capture_output=True, text=True, timeout=120,
    )
    assert proc.returncode == 2
    assert "nowhere" in proc.stderr


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), float("-inf")])
def test_first_non_finite_finds_one_bad_value_anywhere_and_ignores_large_finite_values(bad):
    from promptgs_engine.train import first_non_finite

    params = {"means": torch.randn(1000, 3), "scales": torch.full((1001, 3), 3e38), "opacities": torch.randn(37)}
    assert first_non_finite(params) is None  # sums of the scales overflow; the values are finite
    for key in params:
        for index in (0, params[key].numel() // 2, params[key].numel() - 1):  # vector body and tail
            poisoned = {k: v.clone() for k, v in params.items()}
            poisoned[key].view(-1)[index] = bad
            assert first_non_finite(poisoned) == key


def test_fused_adam_step_equals_the_optimisers_own_step_bit_for_bit():
    from promptgs_engine.adam import fused_adam_step
    from promptgs_engine.gaussians import init_from_points
    from promptgs_engine.train import make_optimizers

    g = torch.Generator().manual_seed(1)
    runs = []
    for direct in (False, True):
        points = torch.randn(300, 6, generator=torch.Generator().manual_seed(0))
        params = init_from_points(points[:, :3], points[:, 3:].sigmoid(), sh_degree=1, init_opacity=0.5)
        opts = make_optimizers(params, TrainConfig(dataset="d", out="o"), extent=2.0)
        g.manual_seed(1)
        for step in range(4):
            for p in params.values():
                p.grad = torch.randn(p.shape, generator=g)
            opts["means"].param_groups[0]["lr"] *= 0.9  # as the scheduler changes it
            if direct:
                fused_adam_step(opts)
            else:
                for opt in opts.values():
                    opt.step()
                    opt.zero_grad(set_to_none=True)
        assert all(p.grad is None for p in params.values())
        runs.append((params, opts))
    (p_a, o_a), (p_b, o_b) = runs
    for k in p_a:
        assert torch.equal(p_a[k], p_b[k])
        sa, sb = o_a[k].state[p_a[k]], o_b[k].state[p_b[k]]
        assert sa.keys() == sb.keys() and all(torch.equal(sa[s], sb[s]) and sa[s].dtype == sb[s].dtype for s in sa)
    assert float(o_b["means"].state[p_b["means"]]["step"]) == 4
