"""`promptgs sfm` on tumbler's photos at 200x150 (../shared/data/tumbler): collected only
where that scene is (tests/conftest.py); tests/test_sfm.py covers the same routes on
scenes the tests make."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from promptgs_engine.cli import main as cli_main
from promptgs_engine.sfm.compare import camera_centres, compare_centres
from scenes import TUMBLER, subset_of_model


@pytest.fixture(scope="module")
def tumbler_sfm(tmp_path_factory) -> tuple[Path, dict]:
    out = tmp_path_factory.mktemp("tumbler") / "sfm"
    # One thread: the same model every run (with every core the camera centres' largest
    # error moved between 3.4% and 6.2% of the extent over four runs, 12.8% under load).
    assert cli_main(["sfm", str(TUMBLER.path / "images_4"), "--out", str(out), "--quiet", "--min-registered", "0.3",
                     "--threads", "1"]) == 0
    return out, json.loads((out / "sfm_summary.json").read_text())


def test_tumbler_thumbnails_register_and_align(tumbler_sfm):
    """At 200x150 incremental mapping ties 57 of tumbler's 77 photos together (with the
    thumbnail settings; COLMAP's defaults 21): a jump to top-down views leaves one pair
    with 19 inliers between the two halves. `--mapper auto` then runs the global mapper,
    which registers 75 (97%). The cameras match the given model's up to a similarity
    (measured: median 4.2%, nine in ten under 8.2%, all under 13.7% of the extent; the 2%
    asked for is not met, docs/sfm.md), and agree with the incremental model's where both
    register (median 1.0%)."""
    out, summary = tumbler_sfm
    assert summary["images_given"] == 77 and summary["matcher"] == "exhaustive" and summary["thumbnail_settings"]
    assert summary["mapper"] == "global" and summary["mappers_tried"]["incremental"] < 70
    assert summary["images_registered"] >= 70  # 90% of 77
    report = compare_centres(camera_centres(out / "sparse" / "0"), camera_centres(TUMBLER.model_dir))
    assert report["common"] == summary["images_registered"]
    errors = np.array(list(report["per_image"].values()))
    assert report["median_error"] < 0.05 and np.percentile(errors, 90) < 0.10 and report["max_error"] < 0.16, report
    # Where the incremental mapper's largest model registers the same photos, the two agree.
    models = [camera_centres(d) for d in sorted((out / "colmap" / "models").iterdir())]
    largest = max(models, key=len)
    assert len(largest) == summary["mappers_tried"]["incremental"]
    agreement = compare_centres(camera_centres(out / "sparse" / "0"), largest)
    assert agreement["common"] == len(largest) and agreement["median_error"] < 0.02, agreement


@pytest.mark.slow
def test_training_on_the_sfm_model_matches_the_given_model(tumbler_sfm, tmp_path):
    """Same images, same steps: the PSNR on the held-out views is no more than 0.5 dB below
    the given model's (measured on the global mapper's 75 photos, seeds 0-4: +0.95, +0.95,
    −0.23, +0.25, −0.10 dB, docs/sfm.md; a short training's spread is large both ways)."""
    from promptgs_engine.config import TrainConfig
    from promptgs_engine.train import run_training

    out, summary = tumbler_sfm
    names = set(camera_centres(out / "sparse" / "0"))
    given = subset_of_model(TUMBLER.model_dir, TUMBLER.path / "images_4", names, tmp_path / "given")
    psnr = {}
    for label, dataset in (("sfm", out), ("given", given)):
        cfg = TrainConfig(dataset=str(dataset), out=str(tmp_path / f"run_{label}"), iterations=300, checkpoint_every=0, sh_degree=1)
        psnr[label] = run_training(cfg, quiet=True)["psnr"]
    assert psnr["sfm"] > psnr["given"] - 0.5, psnr
