"""promptgs report: results loading, aggregation, Pareto front, charts, tables, crop sheets."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from promptgs_engine.bench import report
from promptgs_engine.bench.report import (
    CROP_GAP,
    CROP_HEADER_H,
    CROP_LABEL_W,
    aggregate,
    crop_window,
    load_results,
    pareto_front,
    write_report,
)
from promptgs_engine.errors import PromptGSError

FULL_W, FULL_H = 128, 96  # dataset images and masks
EVAL_W, EVAL_H = 64, 48  # evaluation resolution (downscale 2)
VIEWS = ["v00.jpg", "v01.jpg"]
# objects at full resolution: id -> {view: (y0, y1, x0, x1)}
OBJECTS = {
    1: {"v00.jpg": (40, 52, 60, 72), "v01.jpg": (20, 26, 30, 36)},  # 12×12 in v00, 6×6 in v01
    2: {"v00.jpg": (70, 74, 100, 104)},  # 4×4
}
METHODS = ["3dgs", "absgs", "promptgs-1"]
PSNR = {  # (method, budget) -> psnr per seed
    ("3dgs", None): [20.0, 21.0],
    ("absgs", None): [22.0, 22.0],
    ("promptgs-1", None): [24.0, 26.0],
    ("promptgs-1", 1000): [23.0, 23.5],
}
WALL = {("3dgs", None): 100.0, ("absgs", None): 120.0, ("promptgs-1", None): 150.0, ("promptgs-1", 1000): 90.0}
GAUSSIANS = {("3dgs", None): 4000, ("absgs", None): 5000, ("promptgs-1", None): 6000, ("promptgs-1", 1000): 1000}
FAIL_MESSAGE = "training stopped: NaN in means at step 312"


def _row(scene: str, dataset: Path, run_dir: Path, method: str, budget, seed: int, **kw) -> dict:
    b = "none" if budget is None else str(budget)
    row = {
        "schema": "promptgs-bench/1",
        "cell": f"{scene}/{method}/{b}/i600/s{seed}",
        "scene": scene, "dataset": str(dataset), "images": "images",
        "method": method, "strategy": method.split("-")[0], "prompt": None,
        "budget": budget, "iterations": 600, "seed": seed, "status": "ok", "error": None,
        "run_dir": str(run_dir), "wall_seconds": 0.0, "train_seconds": 0.0, "seconds_per_step": 0.0,
        "peak_rss_mb": 500.0, "n_gaussians": 0, "psnr": 0.0, "ssim": 0.5,
        "masked_psnr": None, "object_region_psnr": None, "recall": None, "n_recall_pairs": None,
        "recall_per_object": None, "finished_at": "2026-11-21T18:00:00+00:00", "load_avg": 1.0,
    }
    row.update(kw)
    return row


@pytest.fixture(scope="module")
def bench(tmp_path_factory) -> dict:
    """Two scenes: 'mountain' (dataset with object masks, run folders with renders), 'fern' (no masks)."""
    root = tmp_path_factory.mktemp("bench")
    rng = np.random.default_rng(0)
    ds = root / "mountain"
    (ds / "images").mkdir(parents=True)
    (ds / "object_masks").mkdir()
    gts = {}
    for view in VIEWS:
        img = rng.integers(0, 256, (FULL_H, FULL_W, 3), dtype=np.uint8)
        # the metrics name a .jpg; store lossless PNG data under that name so pixels compare exactly
        Image.fromarray(img).save(ds / "images" / view, format="PNG")
        gts[view] = img
        mask = np.zeros((FULL_H, FULL_W), np.uint8)
        for obj, boxes in OBJECTS.items():
            if view in boxes:
                y0, y1, x0, x1 = boxes[view]
                mask[y0:y1, x0:x1] = obj
        Image.fromarray(mask).save(ds / "object_masks" / view.replace(".jpg", ".png"))
    fern = root / "fern"
    (fern / "images").mkdir(parents=True)

    rows = []
    for (method, budget), psnrs in PSNR.items():
        for seed, p in enumerate(psnrs):
            run_dir = root / "runs" / f"{method}_{budget}_{seed}"
            (run_dir / "renders").mkdir(parents=True)
            per_image = [{"image": "v00.jpg", "psnr": p, "objects": {"1": True, "2": False}},
                         {"image": "v01.jpg", "psnr": p, "objects": {"1": True}}]
            (run_dir / "metrics.json").write_text(json.dumps({"resolution": [EVAL_W, EVAL_H], "per_image": per_image}))
            for view in VIEWS:
                Image.fromarray(rng.integers(0, 256, (EVAL_H, EVAL_W, 3), dtype=np.uint8)).save(
                    run_dir / "renders" / view.replace(".jpg", ".png"))
            rows.append(_row(
                "mountain", ds, run_dir, method, budget, seed,
                psnr=p, wall_seconds=WALL[(method, budget)] + 10 * seed, n_gaussians=GAUSSIANS[(method, budget)],
                masked_psnr=p - 5, recall=0.5 + 0.25 * seed if method.startswith("promptgs") else 0.25,
                peak_rss_mb=None if seed == 1 else 800.0,
            ))
    # a failed cell (a group with no ok seed), and an earlier failure of a cell that later succeeded
    rows.append(_row("mountain", ds, root / "runs" / "x", "absgs", 1000, 0, status="error", error=FAIL_MESSAGE))
    rows.insert(0, dict(rows[0], status="error", error="an old failure, re-run since"))
    for method in METHODS:
        for seed in (0, 1):
            rows.append(_row("fern", fern, root / "runs" / "none", method, None, seed,
                             psnr=25.0 + seed, wall_seconds=50.0, n_gaussians=3000))
    results = root / "RESULTS.jsonl"
    results.write_text("\n".join(json.dumps(r) for r in rows) + "\n")
    out = root / "report"
    return {"results": results, "out": out, "summary": write_report(results, out), "gts": gts, "rows": rows}


def test_aggregate_means_and_population_std(bench):
    aggs = aggregate(load_results(bench["results"]))
    by = {(a["scene"], a["method"], a["budget"]): a for a in aggs}
    assert set(by) == {("mountain", m, b) for m, b in PSNR} | {("fern", m, None) for m in METHODS}
    a = by[("mountain", "promptgs-1", None)]
    assert a["n_seeds"] == 2 and a["seeds"] == [0, 1]
    assert a["psnr_mean"] == pytest.approx(25.0) and a["psnr_std"] == pytest.approx(1.0)  # population std
    assert a["wall_seconds_mean"] == pytest.approx(155.0) and a["wall_seconds_std"] == pytest.approx(5.0)
    assert a["recall_mean"] == pytest.approx(0.625) and a["recall_std"] == pytest.approx(0.125)
    # None-aware: peak memory only from seed 0; no masks in fern -> None
    assert a["peak_rss_mb_mean"] == pytest.approx(800.0) and a["peak_rss_mb_std"] == 0.0 and a["peak_rss_mb_n"] == 1
    assert by[("fern", "3dgs", None)]["masked_psnr_mean"] is None
    # the old failure of a cell that later succeeded does not remove its ok row
    assert by[("mountain", "3dgs", None)]["n_seeds"] == 2
    # order: methods in the fixed order, budgets None first
    assert [(a["method"], a["budget"]) for a in aggs if a["scene"] == "mountain"] == list(PSNR)


def test_pareto_front():
    pts = [(10, 20), (20, 25), (15, 19), (30, 25), (5, 18), (25, 30), (20, 24), (None, 40), (40, float("nan"))]
    # (15,19) beaten by (10,20); (30,25) by (20,25); (20,24) by (20,25); None/NaN ignored
    assert pareto_front(pts) == [4, 0, 1, 5]
    assert pareto_front([(1.0, 1.0), (1.0, 1.0)]) == [0, 1]  # ties do not dominate each other
    assert pareto_front([]) == []


def test_crop_window_stays_inside():
    assert crop_window(31.5, 23.5, 24, 64, 48) == (20, 12, 24)
    assert crop_window(1.0, 46.0, 24, 64, 48) == (0, 24, 24)
    assert crop_window(5.0, 5.0, 24, 16, 10) == (1, 0, 10)  # window shrinks to the image


def test_charts_are_pngs(bench):
    out = bench["out"]
    for name in ("psnr_vs_time.png", "masked_psnr_vs_time.png", "psnr_vs_gaussians.png", "recall.png", "crops.png",
                 "crops_mountain.png"):
        assert out / name in bench["summary"]["files"]
        with Image.open(out / name) as im:
            assert im.format == "PNG" and im.width > 100 and im.height > 100
    assert not (out / "crops_fern.png").exists()
    assert any("crops_fern.png" in n and "object masks" in n for n in bench["summary"]["notes"])
    summary = json.loads((out / "summary.json").read_text())
    assert "table.md" in summary["files"] and len(summary["aggregate"]) == 7


def test_no_masks_no_masked_chart(tmp_path, bench):
    rows = [r for r in bench["rows"] if r["scene"] == "fern"]
    results = tmp_path / "r.jsonl"
    results.write_text("\n".join(json.dumps(r) for r in rows))
    rep = write_report(results, tmp_path / "out")
    assert not (tmp_path / "out" / "masked_psnr_vs_time.png").exists()
    assert not (tmp_path / "out" / "recall.png").exists()
    assert any(n.startswith("masked_psnr_vs_time.png not written") for n in rep["notes"])
    assert (tmp_path / "out" / "psnr_vs_time.png").is_file()


def test_table(bench):
    text = (bench["out"] / "table.md").read_text()
    mountain, fern = text.split("## mountain")[1].split("## fern")
    for name in ("3DGS", "AbsGS", "PromptGS, 1 box"):
        assert f"| {name} |" in mountain and f"| {name} |" in fern
    assert "| PromptGS, 1 box · budget 1,000 |" in mountain
    assert "| AbsGS · budget 1,000 | failed |" in mountain
    assert FAIL_MESSAGE in text and "mountain/absgs/1000/i600/s0" in text
    assert "an old failure" not in text
    assert "| 20.50 ± 0.50 |" in mountain  # 3DGS PSNR over seeds 20, 21
    assert "| 25.00 ± 1.00 |" in mountain  # PromptGS 1 box
    assert "| 22.00 ± 0.00 |" in mountain  # AbsGS
    # wall time vs 3DGS (105 s): AbsGS 125 s, PromptGS 155 s, PromptGS budget 1000 95 s
    assert "1.19×" in mountain and "1.48×" in mountain and "0.90×" in mountain and "| 1.00× |" in mountain
    assert "| 800 (1 of 2 seeds) |" in mountain  # peak memory known for seed 0 only
    assert "LPIPS is not computed" in text
    # the Gaussian economy of promptgs-1: budget 1000 vs none: 1000 of 6000 Gaussians, 23.25 - 25.00 dB
    econ = text.split("### Gaussian economy")[1].split("##")[0]
    assert "| PromptGS, 1 box | 1,000 | 1,000 ± 0 | 23.25 ± 0.25 | -1.75 | 17% |" in econ
    assert "3DGS" not in econ
    # every table row has as many cells as its header
    for block in text.split("\n\n"):
        lines = [l for l in block.splitlines() if l.startswith("|")]
        if lines:
            assert {l.count("|") for l in lines} == {lines[0].count("|")}


def test_crop_sheet_size_and_pixels(bench):
    window, scale = 24, 6
    # pairs: object 1 in v00 (6×6 at eval res), object 2 in v00 (2×2), object 1 in v01 (3×3): 3 rows
    # columns: ground truth + 3 methods
    pitch = window * scale + CROP_GAP
    with Image.open(bench["out"] / "crops_mountain.png") as im:
        sheet = np.asarray(im.convert("RGB"))
    assert sheet.shape[:2] == (CROP_HEADER_H + CROP_GAP + 3 * pitch, CROP_LABEL_W + CROP_GAP + 4 * pitch)
    assert np.array_equal(sheet, np.asarray(Image.open(bench["out"] / "crops.png").convert("RGB")))
    # first row: object 1 in v00, eval-res box rows 20..25, cols 30..35 -> centroid (32.5, 22.5)
    gt = np.asarray(Image.fromarray(bench["gts"]["v00.jpg"]).reduce(2))
    x0, y0, s = crop_window(32.5, 22.5, window, EVAL_W, EVAL_H)
    assert (x0, y0, s) == (21, 11, 24)
    left, top = CROP_LABEL_W + CROP_GAP, CROP_HEADER_H + CROP_GAP
    for dy, dx in [(0, 0), (11, 11), (23, 5), (9, 23)]:
        block = sheet[top + dy * scale: top + (dy + 1) * scale, left + dx * scale: left + (dx + 1) * scale]
        assert (block == gt[y0 + dy, x0 + dx]).all()
    # second column: 3dgs seed 0 render, same window
    render = np.asarray(Image.open(Path(bench["rows"][1]["run_dir"]) / "renders" / "v00.png").convert("RGB"))
    assert bench["rows"][1]["method"] == "3dgs" and bench["rows"][1]["seed"] == 0
    block = sheet[top + 4 * scale, left + pitch + 7 * scale]
    assert (block == render[y0 + 4, x0 + 7]).all()
    # second row: object 2 in v00 (eval rows 35..36, cols 50..51)
    x0, y0, _ = crop_window(50.5, 35.5, window, EVAL_W, EVAL_H)
    assert (sheet[top + pitch + 12 * scale, left + 12 * scale] == gt[y0 + 12, x0 + 12]).all()


def test_choose_pairs_prefers_distinct_large_objects():
    c = [{"image": "a", "object": 1, "size": 30}, {"image": "b", "object": 1, "size": 20},
         {"image": "a", "object": 2, "size": 5}, {"image": "c", "object": 3, "size": 10}]
    assert [(p["image"], p["object"]) for p in report.choose_pairs(c, 3)] == [("a", 1), ("c", 3), ("a", 2)]
    assert len(report.choose_pairs(c, 8)) == 4


def test_bad_results(tmp_path):
    good = json.dumps({"schema": "promptgs-bench/1", "cell": "a", "scene": "s", "method": "3dgs",
                       "iterations": 1, "seed": 0, "status": "ok"})
    path = tmp_path / "RESULTS.jsonl"
    path.write_text(good + "\n\n{not json\n")
    with pytest.raises(PromptGSError, match=r"RESULTS\.jsonl, line 3"):
        load_results(path)
    path.write_text(good + "\n" + good.replace("promptgs-bench/1", "other/2") + "\n")
    with pytest.raises(PromptGSError, match=r"line 2: schema"):
        load_results(path)
    path.write_text(json.dumps({"schema": "promptgs-bench/1", "cell": "a"}) + "\n")
    with pytest.raises(PromptGSError, match=r"line 1: missing key"):
        load_results(path)
    with pytest.raises(PromptGSError, match="not found"):
        load_results(tmp_path / "missing.jsonl")
    path.write_text("")
    with pytest.raises(PromptGSError, match="no result rows"):
        write_report(path, tmp_path / "out")


def test_cli(tmp_path, bench, capsys):
    import argparse

    parser = argparse.ArgumentParser(prog="promptgs")
    report.add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(["report", str(bench["results"]), "--out", str(tmp_path / "cli")])
    assert args.func(args) == 0
    lines = capsys.readouterr().out.splitlines()
    assert f"wrote {tmp_path / 'cli' / 'table.md'}" in lines
    args = parser.parse_args(["report", str(tmp_path / "nope.jsonl"), "--out", str(tmp_path / "cli2")])
    assert args.func(args) == 2
    assert "nope.jsonl" in capsys.readouterr().err
