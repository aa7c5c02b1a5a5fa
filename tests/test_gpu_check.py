"""tools/gpu_check.sh, the one-command GPU check (docs/gpu.md): its plan, its rules for
skips and failures, and its CPU-only path end to end."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch

REPO = Path(__file__).resolve().parents[1]
SCRIPT = REPO / "tools" / "gpu_check.sh"
sys.path.insert(0, str(REPO / "tools"))
import gpu_check  # noqa: E402

GPU_STEPS = ["gsplat-compile", "train-cuda-3dgs", "train-cuda-promptgs", "side-by-side", "nccl-test",
             "plain-8", "torchrun-8", "torchrun-equals-plain", "torchrun-3dgs"]


def _check(args: list[str], timeout: float) -> subprocess.CompletedProcess:
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    return subprocess.run(["bash", str(SCRIPT), *args], cwd=REPO, env=env, capture_output=True, text=True, timeout=timeout)


def _machine_with_a_gpu(monkeypatch) -> None:
    real = gpu_check.describe_machine

    def with_gpu():
        machine, text = real()
        machine["gpus"] = [{"name": "NVIDIA H200", "memory": "143771 MiB", "driver": "580", "compute_cap": "9.0"}]
        machine["nvidia_smi"] = True
        return machine, text

    monkeypatch.setattr(gpu_check, "describe_machine", with_gpu)


def test_the_dry_run_lists_every_check_and_writes_nothing(tmp_path):
    out = tmp_path / "check"
    proc = _check(["--dry-run", "--skip-install", "--out", str(out)], timeout=60)
    assert proc.returncode == 0, proc.stderr
    for command in ("-m pytest tests/test_render_cuda.py tests/test_train_cuda.py",
                    "benchmarks/gsplat_side_by_side.py", "--backend cuda --strategy promptgs",
                    "--backend cpu --strategy 3dgs", "-m torch.distributed.run --standalone --nproc-per-node 1 -m promptgs_engine train",
                    "helper compile-gsplat", "helper compare-runs"):
        assert command in proc.stdout, command
    assert not out.exists()


def test_on_a_gpu_machine_it_installs_with_the_readme_commands_into_its_own_venv(monkeypatch, tmp_path):
    _machine_with_a_gpu(monkeypatch)
    check = gpu_check.Check(gpu_check.parse_args(["--out", str(tmp_path / "c"), "--venv", str(tmp_path / "venv")]))
    steps = {s.name: s for s in check.steps()}
    venv_python = str(tmp_path / "venv" / "bin" / "python")
    torch_cmd, project_cmd = steps["install-torch"].command, steps["install-project"].command
    assert torch_cmd[:4] == [venv_python, "-m", "pip", "install"] and "torch==2.13.0" in torch_cmd and "setuptools>=64" in torch_cmd
    assert project_cmd[-3:] == ["--no-build-isolation", "-e", ".[test]"] and not any("blender" in a for a in project_cmd)
    # Every later step runs the venv's Python, with its bin/ (ninja) first on PATH and gsplat
    # compiled for this card only.
    assert all(s.command[0] == venv_python for name, s in steps.items() if name != "install-venv")
    assert check.env["PATH"].startswith(str(tmp_path / "venv" / "bin"))
    assert check.env["TORCH_CUDA_ARCH_LIST"] == "9.0" and "PYTHONPATH" not in check.env


def _junit(path: Path, skipped: int, passed: int) -> None:
    cases = "".join(f'<testcase name="s{i}"><skipped message="needs a CUDA GPU"/></testcase>' for i in range(skipped))
    cases += "".join(f'<testcase name="p{i}"/>' for i in range(passed))
    path.write_text(f'<testsuites><testsuite tests="{skipped + passed}" skipped="{skipped}" failures="0" errors="0">'
                    f"{cases}</testsuite></testsuites>")


@pytest.mark.parametrize("cuda, skipped, passed, status", [
    (True, 1, 8, "failed"),    # a CUDA test that skips where torch sees a GPU
    (True, 0, 9, "passed"),
    (False, 9, 0, "skipped"),  # without a GPU: ran, and all skipped
])
def test_a_parity_test_that_skips_on_a_gpu_fails_the_check(tmp_path, cuda, skipped, passed, status):
    check = gpu_check.Check(gpu_check.parse_args(["--skip-install", "--out", str(tmp_path)]))
    check.logs.mkdir(parents=True)
    check.cuda = cuda
    _junit(check.logs / "parity-tests.xml", skipped, passed)
    result = gpu_check.Result("parity-tests", "t", "passed", 1.0)
    check._collect_parity(result)
    assert result.status == status, result.reason
    assert check.figures["tests"]["parity-tests"]["skipped"] == skipped


def test_a_failed_step_skips_what_needs_it_and_sets_the_exit_status(tmp_path):
    out = tmp_path / "check"
    proc = _check(["--skip-install", "--python", "/bin/false", "--out", str(out)], timeout=120)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    steps = {s["name"]: s for s in summary["steps"]}
    assert steps["versions"]["status"] == "failed" and "versions" in summary["failed"]
    assert steps["toy-scene"]["status"] == "skipped" and steps["toy-scene"]["reason"] == "needs versions (failed)"
    assert steps["train-cpu-3dgs"]["reason"] == "needs toy-scene (skipped)"
    assert (out / "logs" / "versions.log").is_file() and "versions" in (out / "commands.sh").read_text()


@pytest.mark.slow
@pytest.mark.skipif(torch.cuda.is_available(), reason="on a GPU machine the check runs its GPU steps: run tools/gpu_check.sh itself")
def test_without_a_gpu_the_cpu_parts_run_and_the_gpu_parts_skip_with_the_reason(tmp_path):
    out = tmp_path / "check"
    proc = _check(["--skip-install", "--quick", "--out", str(out)], timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    summary = json.loads((out / "summary.json").read_text())
    steps = {s["name"]: s for s in summary["steps"]}
    assert summary["failed"] == [] and summary["cuda"]["available"] is False
    for name in GPU_STEPS:
        assert steps[name]["status"] == "skipped" and steps[name]["reason"].startswith("no CUDA GPU"), steps[name]
    # The parity tests ran and skipped, each for want of a GPU.
    assert steps["parity-tests"]["status"] == "skipped" and steps["parity-tests"]["reason"].startswith("ran; all")
    assert summary["figures"]["tests"]["parity-tests"]["skip_reasons"] == ["needs a CUDA GPU"]
    for name in ("train-cpu-3dgs", "train-cpu-promptgs"):
        row = summary["figures"]["training"][name]
        assert steps[name]["status"] == "passed" and row["backend"] == "cpu" and row["iterations"] == 30
        assert row["n_gaussians"] > 0 and 10 < row["psnr"] < 60 and row["peak_gpu_mb"] is None
        assert (out / "logs" / f"{name}.log").is_file()
    commands = (out / "commands.sh").read_text()
    assert "--backend cpu --strategy promptgs" in commands and "--backend cuda" not in commands
    assert summary["versions"]["torch"] == torch.__version__ and (out / "env.txt").is_file()
    assert "exit status 0" in proc.stdout
