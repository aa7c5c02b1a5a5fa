"""The stability suite (promptgs_engine.bench.stability): every case at tiny size ends as
expected, the targeted checks hold, and the outcome of a process is classified right."""

import json
import math
import sys

import pytest

from promptgs_engine.bench import stability as st
from promptgs_engine.data import load_colmap_scene
from promptgs_engine.prompts import check_visible, load_prompts
from promptgs_engine.views import related_views

ITERATIONS = 30


@pytest.fixture(scope="module")
def suite(tmp_path_factory):
    """The whole suite at tiny size (64x48, 12 views), both strategies: 16 processes,
    about 50 s on 2 busy cores."""
    out = tmp_path_factory.mktemp("stability")
    return out, st.run_stability(out, iterations=ITERATIONS, size="tiny")


def _row(rows, case, strategy, iterations=ITERATIONS):
    found = [r for r in rows if (r["case"], r["strategy"], r["iterations"]) == (case, strategy, iterations)]
    assert len(found) == 1, (case, strategy, iterations)
    return found[0]


def test_every_case_ends_as_expected_without_nan_or_crash(suite):
    out, rows = suite
    assert {r["case"] for r in rows} == set(st.CASES)
    for case in st.CASES.values():
        strategies = {r["strategy"] for r in rows if r["case"] == case.name}
        assert strategies == ({"3dgs", "promptgs"} if case.baseline else {"promptgs"}), case.name
    for r in rows:
        where = f"{r['case']} {r['strategy']} i{r['iterations']}: {r['outcome']} {r['message']} {r.get('check')}"
        assert r["outcome"] in (st.OK, st.CLEAR_ERROR), where
        assert r["outcome"] == r["expected"] and r["check"] is None and r["passed"], where
        if r["outcome"] == st.OK:
            assert math.isfinite(r["psnr"]) and math.isfinite(r["ssim"]) and r["n_gaussians"] > 0, where
    assert json.loads((out / "stability.json").read_text()) == rows
    table = (out / "stability.md").read_text().strip().splitlines()
    assert table[0].startswith("| case | strategy |") and len(table) == 2 + len(rows)
    assert all(line.endswith("| yes |") for line in table[2:])


def test_a_prompt_no_camera_sees_is_one_clear_line(suite):
    _, rows = suite
    r = _row(rows, "prompt_seen_by_no_camera", "promptgs")
    assert r["outcome"] == st.CLEAR_ERROR and r["returncode"] == 2
    assert r["message"].startswith("promptgs: error: ") and "seen by none" in r["message"] and "\n" not in r["message"]


def test_the_two_camera_prompt_trains(suite):
    out, rows = suite
    box = load_prompts(out / "prompts" / "two_cameras.json")
    cameras = load_colmap_scene(out / "datasets" / "base").train_cameras
    assert len(check_visible(box, cameras)[0]) == 2  # the case tests what it says
    r = _row(rows, "prompt_seen_by_two_cameras", "promptgs")
    assert r["outcome"] == st.OK and r["psnr"] > r["start_psnr"] + st.MIN_GAIN_DB
    # only two views to relate the prompt to (resampling, which needs 3, is skipped)
    assert [len(v) for v in related_views(box, cameras, 8)] == [2]


def test_the_extent_outlier_still_trains(suite):
    """The far camera inflates the extent ~40x (the position learning rate and the
    split / prune size thresholds scale with it). Floor: the unmodified scene's PSNR
    minus 1 dB; measured here +2.7 dB above it (both strategies), at 200 steps on the
    small scene +4.2 / +4.1 dB: the faster positions help short runs. A
    divergence, or everything pruned as "too big", would fall far below."""
    out, rows = suite
    base = load_colmap_scene(out / "datasets" / "base")
    outlier = load_colmap_scene(out / "datasets" / "extent_outlier")
    assert outlier.extent > 10 * base.extent
    assert [c.name for c in outlier.test_cameras] == [c.name for c in base.test_cameras]
    for strategy in ("3dgs", "promptgs"):
        r = _row(rows, "extent_outlier_camera", strategy)
        ref = _row(rows, "no_sfm_points_on_objects", strategy)
        assert r["outcome"] == st.OK
        assert r["psnr"] >= ref["psnr"] - st.OUTLIER_MAX_DROP_DB, (r["psnr"], ref["psnr"])
        assert r["psnr"] > r["start_psnr"] + st.MIN_GAIN_DB


def test_constant_images_give_a_finite_psnr_and_no_gaussian_explosion(suite):
    """PSNR rises over the untrained start (measured +2.6 dB at 30 steps) and stays
    finite; no Gaussian explosion against the textured scene (tiny: measured 1.02x /
    0.87x; bound 1.5x, see stability.py)."""
    _, rows = suite
    for strategy in ("3dgs", "promptgs"):
        r = _row(rows, "constant_colour_images", strategy)
        ref = _row(rows, "no_sfm_points_on_objects", strategy)
        assert r["outcome"] == st.OK and math.isfinite(r["psnr"]) and math.isfinite(r["ssim"])
        assert r["psnr"] > r["start_psnr"] + st.MIN_GAIN_DB
        assert r["n_gaussians"] <= st.CONSTANT_MAX_COUNT_RATIO * ref["n_gaussians"]


def test_very_short_runs_train_and_change_nothing_structural(suite):
    _, rows = suite
    for strategy in ("3dgs", "promptgs"):
        for iterations in st.SHORT_ITERATIONS:
            r = _row(rows, "very_short_runs", strategy, iterations)
            assert r["outcome"] == st.OK and math.isfinite(r["psnr"])
            # no refinement or resampling step falls inside 1 or 5 steps: the Gaussians
            # are the SfM points and the far sky shell the run started with
            assert r["sky_points"] > 0
            assert r["n_gaussians"] == st.SIZES["tiny"].n_sfm_points + r["sky_points"]


def test_odd_prompts_stay_bounded(suite):
    _, rows = suite
    sky = _row(rows, "prompt_in_empty_sky", "promptgs")
    assert sky["inside_prompt"] <= st.EMPTY_BOX_MAX_FRACTION * sky["n_gaussians"]
    ref = _row(rows, "no_sfm_points_on_objects", "promptgs")
    huge = _row(rows, "box_larger_than_scene", "promptgs")
    assert huge["n_gaussians"] <= st.HUGE_BOX_MAX_COUNT_RATIO * ref["n_gaussians"]
    assert _row(rows, "overlapping_boxes", "promptgs")["outcome"] == st.OK


# -- classification of a process's end, with tiny fake commands ---------------------------


def _py(code: str) -> list[str]:
    return [sys.executable, "-c", code]


def test_exit_2_with_an_error_line_is_a_clear_error(tmp_path):
    r = st.run_command(_py("import sys; print('promptgs: error: bad input here', file=sys.stderr); sys.exit(2)"), tmp_path, 30)
    assert (r["outcome"], r["message"], r["returncode"]) == (st.CLEAR_ERROR, "promptgs: error: bad input here", 2)
    r = st.run_command(_py("import sys; sys.exit(2)"), tmp_path, 30)  # exit 2 but nothing said
    assert r["outcome"] == st.CRASH


def test_a_traceback_a_signal_and_a_timeout_are_crashes(tmp_path):
    r = st.run_command(_py("raise RuntimeError('boom in the rasterizer')"), tmp_path, 30)
    assert (r["outcome"], r["message"]) == (st.CRASH, "RuntimeError: boom in the rasterizer")
    r = st.run_command(_py("import os, signal; os.kill(os.getpid(), signal.SIGKILL)"), tmp_path, 30)
    assert r["outcome"] == st.CRASH and r["message"].startswith("killed by signal 9")
    r = st.run_command(_py("import time; time.sleep(30)"), tmp_path, 0.5)
    assert (r["outcome"], r["returncode"]) == (st.CRASH, None) and "timed out" in r["message"]
    assert r["seconds"] < 10


def test_exit_0_reads_the_metrics_and_catches_nan(tmp_path):
    def write(metrics):
        (tmp_path / "metrics.json").write_text(json.dumps(metrics))

    ok = _py("pass")
    assert st.run_command(ok, tmp_path, 30)["outcome"] == st.CRASH  # exit 0 without metrics.json
    write({"psnr": 21.5, "ssim": 0.7, "n_gaussians": 10, "per_image": [{"image": "a.png", "psnr": 21.5, "ssim": 0.7}]})
    r = st.run_command(ok, tmp_path, 30)
    assert r["outcome"] == st.OK and r["metrics"]["psnr"] == 21.5
    write({"psnr": float("nan"), "ssim": 0.7})
    assert st.run_command(ok, tmp_path, 30)["outcome"] == st.NAN
    write({"psnr": None, "ssim": 0.7})  # evaluation's mean of only non-finite views
    assert st.run_command(ok, tmp_path, 30)["outcome"] == st.NAN
    # the mean skips a NaN view; the per-view row still counts
    write({"psnr": 21.5, "ssim": 0.7, "per_image": [{"image": "a.png", "psnr": float("nan"), "ssim": 0.7}]})
    r = st.run_command(ok, tmp_path, 30)
    assert r["outcome"] == st.NAN and "a.png" in r["message"]


# -- the command ----------------------------------------------------------------------


def test_command_exit_status_follows_the_runs(tmp_path, monkeypatch, capsys):
    assert st.main(["stability", "--out", str(tmp_path / "bad"), "--cases", "no_such_case"]) == 2
    assert "promptgs: error: unknown stability case(s) no_such_case" in capsys.readouterr().err

    # A clear error where one is expected passes (a real trainer process, ~3 s).
    code = st.main(["stability", "--out", str(tmp_path / "a"), "--size", "tiny", "--iterations", "5", "--cases", "prompt_seen_by_no_camera"])
    printed = capsys.readouterr().out
    assert code == 0 and "| prompt_seen_by_no_camera | promptgs | 5 | clear error |" in printed

    # Every trainer crashing: each run fails, the command exits 1.
    def crash(cmd, run_dir, timeout, log_path=None):
        return {**st.classify(1, "Traceback ...\nSegmentation fault", run_dir), "seconds": 0.1, "returncode": 1}

    monkeypatch.setattr(st, "run_command", crash)
    code = st.main(["stability", "--out", str(tmp_path / "b"), "--size", "tiny", "--cases", "very_short_runs"])
    printed = capsys.readouterr().out
    assert code == 1 and printed.count("| crash |") == 4 and "Segmentation fault" in printed
    rows = json.loads((tmp_path / "b" / "stability.json").read_text())
    assert [r["passed"] for r in rows] == [False] * 4
