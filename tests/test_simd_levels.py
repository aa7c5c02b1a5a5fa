"""The CPU backend's kernels (rasterizer, projection, SSIM) are compiled for several x86-64
instruction set levels and the best one the CPU supports is picked at load time, so a
machine with AVX-512 would never run the AVX2 or SSE2 kernels that most other machines use.
PROMPTGS_SIMD caps the level: these tests run the parity checks of test_render_cpu.py, the
fused SSIM's of test_losses_metrics.py and resampling's vote against its torch expression
(test_promptgs_strategy.py) once per lower level, in a subprocess."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
PARITY_FILES = ("test_render_cpu.py", "test_losses_metrics.py", "test_promptgs_strategy.py")
PARITY = ("features or sh_two_cameras or sh_rest_apart or dense_opaque or thin_slanted or absgrad or "
          "projection_matches or sh_matches or culling or large_gaussians or fused_cpu_ssim or fused_photometric or "
          "view_votes_in_cpp")


def variant_under(level: str) -> str:
    env = dict(os.environ, PROMPTGS_SIMD=level)
    code = "import torch; from promptgs_engine import _C; print(_C.simd_variant())"
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    return out.stdout.strip()


@pytest.mark.parametrize("level", ["avx2", "sse2"])
def test_kernels_of_each_instruction_set_level_match_the_reference(level):
    if variant_under(level) != level:
        pytest.skip(f"this build or CPU has no {level} variant of the kernels")
    env = dict(os.environ, PROMPTGS_SIMD=level)
    cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *(str(TESTS / f) for f in PARITY_FILES),
           "-k", PARITY]
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, cwd=TESTS.parent)
    assert run.returncode == 0, f"parity tests failed with PROMPTGS_SIMD={level}:\n{run.stdout[-4000:]}{run.stderr[-2000:]}"
    assert " passed" in run.stdout and "deselected" in run.stdout


def test_an_unknown_level_keeps_the_best_one():
    assert variant_under("avx1024") == variant_under("")
