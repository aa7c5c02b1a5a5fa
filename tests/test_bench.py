"""`promptgs bench`: the grid, its JSONL bookkeeping, resume, failures; the recall metric;
the automatic budget."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from promptgs_engine import cli
from promptgs_engine.bench.grid import (
    SCHEMA,
    Cell,
    Grid,
    SceneSpec,
    enclosing_box,
    grid_from_args,
    read_results,
    run_grid,
)
from promptgs_engine.errors import PromptGSError
from promptgs_engine.evaluation import summarize_recall
from promptgs_engine.metrics import object_recall
from promptgs_engine.prompts import PromptBox, load_prompts

# -- recall on hand-made images --------------------------------------------------------


def _images():
    """A grey 8×8 real image with two objects: id 1 (white, 2×2) and id 2 (red, 1×2)."""
    free = torch.full((8, 8, 3), 0.5)
    real = free.clone()
    ids = torch.zeros(8, 8, dtype=torch.long)
    real[1:3, 1:3] = 1.0
    ids[1:3, 1:3] = 1
    real[5, 5:7] = torch.tensor([1.0, 0.0, 0.0])
    ids[5, 5:7] = 2
    return real, free, ids


def test_recall_counts_an_object_when_the_render_explains_most_of_its_contrast():
    real, free, ids = _images()
    # A render equal to the drone-free image explains nothing: no object reconstructed.
    assert object_recall(free, real, free, ids) == {1: False, 2: False}
    # The real image itself explains everything.
    assert object_recall(real, real, free, ids) == {1: True, 2: True}
    # Object 1 rendered 40% of the way from background to white: error 0.3 vs contrast 0.5 -> not yet.
    render = free.clone()
    render[1:3, 1:3] = 0.5 + 0.4 * 0.5
    assert object_recall(render, real, free, ids)[1] is False
    # 60% of the way: error 0.2 < 0.25 -> reconstructed.
    render[1:3, 1:3] = 0.5 + 0.6 * 0.5
    assert object_recall(render, real, free, ids)[1] is True


def test_recall_skips_objects_invisible_in_a_view():
    real, free, ids = _images()
    real[1:3, 1:3] = 0.5  # object 1 hidden: same as what is behind it
    assert set(object_recall(free, real, free, ids)) == {2}


def test_recall_summary_over_views():
    rows = [{"objects": {"1": True, "2": False}}, {"objects": {"1": True}}, {}]
    s = summarize_recall(rows)
    assert s["recall"] == pytest.approx(2 / 3)
    assert s["n_recall_pairs"] == 3
    assert s["recall_per_object"] == {"1": 1.0, "2": 0.0}


# -- the grid with a fake trainer process ------------------------------------------------


def _scene(tmp_path: Path, prompts: list[dict] | None = None) -> SceneSpec:
    folder = tmp_path / "scene"
    folder.mkdir()
    if prompts is not None:
        (folder / "scene.json").write_text(json.dumps({"prompts": {"prompts": prompts}}))
    return SceneSpec(name="s", path=folder)


class FakeTrainer:
    """Stands in for the training process: reads the job, writes metrics.json."""

    def __init__(self, fail: set[str] = frozenset()):
        self.jobs: list[dict] = []
        self.fail = fail

    def __call__(self, command: list[str], log_path: Path):
        job = json.loads(Path(command[command.index("--job") + 1]).read_text())
        self.jobs.append(job)
        if job["strategy"] in self.fail:
            log_path.write_text("Traceback ...\npromptgs: error: something named went wrong\n")
            return 2, 0.1, 50.0
        run = Path(job["out"])
        run.mkdir(parents=True, exist_ok=True)
        metrics = {"psnr": 20.0 + job["seed"], "ssim": 0.5, "n_gaussians": 1000, "train_seconds": 2.0}
        (run / "metrics.json").write_text(json.dumps(metrics))
        log_path.write_text("ok\n")
        return 0, 3.0, 100.0


def test_grid_rows_follow_the_schema_and_resume_skips_finished_cells(tmp_path: Path):
    scene = _scene(tmp_path, prompts=[PromptBox(center=(0, 0, 0), size=(1, 1, 1)).to_dict()])
    grid = Grid(scenes=[scene], methods=["3dgs", "promptgs-2"], budgets=[None, 500], iterations=[50], seeds=[0, 1])
    fake = FakeTrainer()
    rows = run_grid(grid, tmp_path / "b", run=fake, quiet=True)
    assert len(rows) == 8 and len(fake.jobs) == 8
    assert len({r["cell"] for r in rows}) == 8
    row = next(r for r in rows if r["cell"] == "s/promptgs-2/500/i50/s1")
    assert row["schema"] == SCHEMA and row["status"] == "ok" and row["error"] is None
    assert (row["method"], row["strategy"], row["prompt"], row["budget"], row["seed"]) == ("promptgs-2", "promptgs", "2", 500, 1)
    assert row["psnr"] == 21.0 and row["wall_seconds"] == 3.0 and row["peak_rss_mb"] == 100.0
    assert row["seconds_per_step"] == pytest.approx(2.0 / 50)
    job = next(j for j in fake.jobs if j["strategy"] == "promptgs" and j["budget"] == 500 and j["seed"] == 1)
    assert job["save_test_renders"] and job["iterations"] == 50
    assert len(load_prompts(job["prompts"])) == 1  # the suggested prompts
    # Run again: nothing is trained, nothing is appended.
    again = FakeTrainer()
    assert len(run_grid(grid, tmp_path / "b", run=again, quiet=True)) == 8
    assert again.jobs == []
    # An extended grid trains only the new cells.
    grid.seeds = [0, 1, 2]
    more = FakeTrainer()
    assert len(run_grid(grid, tmp_path / "b", run=more, quiet=True)) == 12
    assert {j["seed"] for j in more.jobs} == {2}


def test_failed_cell_is_recorded_with_its_message_and_retried(tmp_path: Path):
    grid = Grid(scenes=[_scene(tmp_path)], methods=["3dgs", "absgs"], iterations=[10])
    rows = run_grid(grid, tmp_path / "b", run=FakeTrainer(fail={"absgs"}), quiet=True)
    failed = [r for r in rows if r["status"] == "error"]
    assert len(failed) == 1 and failed[0]["method"] == "absgs"
    assert failed[0]["error"] == "exit 2: something named went wrong"
    retry = FakeTrainer()
    run_grid(grid, tmp_path / "b", run=retry, quiet=True)
    assert [j["strategy"] for j in retry.jobs] == ["absgs"]


def test_a_grid_of_several_processes_asks_each_cell_for_them(tmp_path: Path):
    grid = Grid(scenes=[_scene(tmp_path)], methods=["3dgs"], iterations=[10], nproc=2)
    fake = FakeTrainer()
    rows = run_grid(grid, tmp_path / "b", run=fake, quiet=True)
    assert fake.jobs[0]["nproc"] == 2  # the job-file key the trainer honours
    assert rows[0]["cell"] == "s/3dgs/none/i10/s0/p2" and rows[0]["nproc"] == 2
    # One bench folder holds one process count: the default batch follows it.
    with pytest.raises(PromptGSError, match="trained with 2 processes, this grid asks for 1"):
        run_grid(Grid(scenes=[_scene_again(tmp_path)], methods=["3dgs"], iterations=[10]), tmp_path / "b", run=fake, quiet=True)
    args = cli.build_parser().parse_args(["bench", "--scene", str(tmp_path), "--nproc", "3", "--out", str(tmp_path / "o")])
    assert grid_from_args(args).nproc == 3
    with pytest.raises(PromptGSError, match="nproc 0"):
        Grid(scenes=[_scene_again(tmp_path)], nproc=0).validate()


def _scene_again(tmp_path: Path) -> SceneSpec:
    return SceneSpec(name="s", path=tmp_path / "scene")


def test_prompt_methods_without_prompts_are_not_applicable(tmp_path: Path):
    grid = Grid(scenes=[_scene(tmp_path)], methods=["promptgs-1", "promptgs-center", "promptgs-auto"], iterations=[10])
    fake = FakeTrainer()
    rows = run_grid(grid, tmp_path / "b", run=fake, quiet=True)
    assert sorted(r["method"] for r in rows) == ["promptgs-auto", "promptgs-center"]
    center = next(j for j in fake.jobs if j.get("center_prompt"))
    assert "prompts" not in center
    assert any(j.get("auto_prompts") for j in fake.jobs)


def test_one_prompt_encloses_the_suggested_boxes(tmp_path: Path):
    boxes = [PromptBox(center=(0, 0, 0), size=(2, 2, 2)), PromptBox(center=(5, 1, 0), size=(1, 1, 4))]
    box = enclosing_box(boxes)
    assert box.center == pytest.approx((2.25, 0.25, 0.0)) and box.size == pytest.approx((6.5, 2.5, 4.0))
    scene = _scene(tmp_path, prompts=[b.to_dict() for b in boxes])
    fake = FakeTrainer()
    run_grid(Grid(scenes=[scene], methods=["promptgs-1"], iterations=[10]), tmp_path / "b", run=fake, quiet=True)
    (only,) = load_prompts(fake.jobs[0]["prompts"])
    assert only.size == pytest.approx((6.5, 2.5, 4.0))


def test_bad_grid_input_is_a_clear_error(tmp_path: Path):
    with pytest.raises(PromptGSError, match="dataset folder not found"):
        run_grid(Grid(scenes=[SceneSpec("x", tmp_path / "missing")]), tmp_path / "b", run=FakeTrainer())
    with pytest.raises(PromptGSError, match="unknown method"):
        Grid(scenes=[_scene(tmp_path)], methods=["nerf"]).validate()
    (tmp_path / "b2").mkdir()
    (tmp_path / "b2" / "results.jsonl").write_text('{"cell": "a", "status": "ok"}\nnot json\n')
    with pytest.raises(PromptGSError, match=r"results.jsonl:2"):
        read_results(tmp_path / "b2" / "results.jsonl")


def test_scene_spec_parsing(tmp_path: Path):
    spec = SceneSpec.parse(f"tumbler={tmp_path}@images_4")
    assert (spec.name, spec.path, spec.images) == ("tumbler", tmp_path.resolve(), "images_4")
    assert SceneSpec.parse(str(tmp_path)).name == tmp_path.name
    cell = Cell(spec, "promptgs-center", "auto", 300, 2)
    assert cell.id == "tumbler/promptgs-center/auto/i300/s2" and cell.prompt == "center"


def test_iterations_on_the_command_line_override_every_scene(tmp_path: Path):
    """`--iterations` replaces the grid's iterations, also where a scene sets its own."""
    (tmp_path / "grid.json").write_text(json.dumps({
        "scenes": [{"name": "a", "path": ".", "iterations": [600]}, {"name": "b", "path": "."}],
        "iterations": [300],
    }))
    args = cli.build_parser().parse_args(["bench", "--grid", str(tmp_path / "grid.json"), "--out", str(tmp_path / "o")])
    assert {(c.scene.name, c.iterations) for c in grid_from_args(args).cells()} == {("a", 600), ("b", 300)}
    args = cli.build_parser().parse_args(
        ["bench", "--grid", str(tmp_path / "grid.json"), "--iterations", "1500", "--out", str(tmp_path / "o")]
    )
    assert {(c.scene.name, c.iterations) for c in grid_from_args(args).cells()} == {("a", 1500), ("b", 1500)}


# -- the real thing, tiny ------------------------------------------------------------------


def test_bench_command_trains_each_cell_in_its_own_process(toy: Path, tmp_path: Path, capsys):
    out = tmp_path / "bench"
    argv = ["bench", "--scene", f"toy={toy}", "--methods", "3dgs", "promptgs-2", "--iterations", "30", "--out", str(out)]
    assert cli.main(argv) == 0
    rows = read_results(out / "results.jsonl")
    assert [r["status"] for r in rows] == ["ok", "ok"], rows
    for r in rows:
        assert r["masked_psnr"] is not None and r["recall"] is not None and r["n_recall_pairs"] > 0
        assert r["peak_rss_mb"] > 50 and r["wall_seconds"] > r["train_seconds"] > 0
        renders = sorted(Path(r["run_dir"], "renders").glob("*.png"))
        assert len(renders) == 2  # the toy fixture's test views
    assert cli.main(argv) == 0  # resumed: nothing new
    assert len(read_results(out / "results.jsonl")) == 2
    assert "2 already done" in capsys.readouterr().out


# -- automatic budget ------------------------------------------------------------------------


def _auto_run(toy: Path, tmp_path: Path, probe_losses: dict[int, float]):
    """Train the toy scene 600 steps (opacity resets at 100 and 200, growth until 300)
    with a scripted probe loss per reset step; returns the trainer and its Gaussian
    counts per step."""
    from promptgs_engine.config import TrainConfig
    from promptgs_engine.train import Trainer

    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "r"), iterations=600, strategy="3dgs", budget="auto", checkpoint_every=0)
    trainer = Trainer(cfg, quiet=True)
    assert (trainer.schedule.reset_every, trainer.schedule.refine_stop_iter) == (100, 300)
    trainer.strategy.loss_probe = lambda: probe_losses[trainer.step]
    counts = []
    while trainer.step < cfg.iterations:
        trainer.train_step()
        trainer.step += 1
        counts.append(trainer.n_gaussians)
    return trainer, counts


def test_auto_budget_stops_growth_when_a_reset_cycle_stops_paying(toy: Path, tmp_path: Path):
    # Between the resets at 100 and 200 the Gaussians grow but the probe loss barely moves.
    trainer, counts = _auto_run(toy, tmp_path, {100: 0.200, 200: 0.199})
    ab = trainer.strategy_state["auto_budget"]
    (judged,) = ab["history"]
    assert judged["step"] == 200 and judged["elasticity"] < 0.1
    assert ab["frozen_at"] == counts[199]
    assert max(counts[200:]) <= ab["frozen_at"]  # no growth past the frozen count
    assert counts[199] > counts[99]  # (it did grow in the judged cycle)


def test_auto_budget_keeps_growing_while_growth_pays(toy: Path, tmp_path: Path):
    trainer, counts = _auto_run(toy, tmp_path, {100: 0.20, 200: 0.10})
    ab = trainer.strategy_state["auto_budget"]
    assert ab["frozen_at"] is None and ab["history"][0]["elasticity"] > 0.1
    assert max(counts[200:300]) > counts[199]  # grew after the judged reset


def test_budget_option_accepts_a_number_or_auto():
    from promptgs_engine.config import TrainConfig

    TrainConfig(dataset="d", out="o", budget="auto").validate()
    TrainConfig(dataset="d", out="o", budget=100).validate()
    for bad in (0, "many", 2.5, True):
        with pytest.raises(PromptGSError, match="--budget"):
            TrainConfig(dataset="d", out="o", budget=bad).validate()


def test_demo_trains_both_methods_and_writes_the_report(toy: Path, tmp_path: Path, capsys):
    out = tmp_path / "demo"
    assert cli.main(["demo", "--scene", str(toy), "--iterations", "30", "--out", str(out)]) == 0
    rows = read_results(out / "results.jsonl")
    assert sorted(r["method"] for r in rows) == ["3dgs", "promptgs-2"]
    report = out / "report"
    for name in ("table.md", "psnr_vs_time.png", "masked_psnr_vs_time.png", "recall.png", "crops.png"):
        assert (report / name).is_file(), name
    table = (report / "table.md").read_text()
    assert "3DGS" in table and "PromptGS" in table
    printed = capsys.readouterr().out
    assert "report:" in printed and "table.md" in printed
