"""The CUDA path checked on an NVIDIA machine in one command (docs/gpu.md).

Run through ``tools/gpu_check.sh`` from the repository root. It installs the project into
a fresh virtual environment with the README's commands (a CUDA torch from the registry,
then ``pip install --no-build-isolation -e ".[test]"``, which brings gsplat 1.5.3; no
bpy), compiles gsplat's CUDA extension once (timed), and then runs, each step with its own
time limit inside one overall budget:

- the CUDA parity tests (``tests/test_render_cuda.py``, ``tests/test_train_cuda.py``),
  which must not skip where torch sees a GPU;
- a short training of the embedded toy scene on the CUDA backend (3DGS and PromptGS with
  the scene's prompts): PSNR, Gaussians, wall time, peak GPU memory;
- ``benchmarks/gsplat_side_by_side.py`` on the same scene: our CUDA step against gsplat's
  own default training step (the goal: within 10%);
- ``torchrun --nproc-per-node 1`` with NCCL against the plain run;
- the same toy trainings on the CPU backend, beside the CUDA figures.

Everything goes into one folder (default ``runs/gpu-check/``): ``summary.json``, one log
per step under ``logs/``, ``commands.sh`` (every command, in order), ``env.txt``
(nvidia-smi, compilers, the commit), the run folders and the side-by-side's JSON and PNG.
A step that fails or runs out of time is reported and the check goes on; the steps that
need it are skipped with the reason. Without a CUDA GPU the GPU steps are skipped with
the reason and the rest runs. The exit status is 1 when a step that ran failed, else 0.

The sub-command ``helper`` holds the small pieces the steps run with the checked
interpreter (they import torch; the orchestrator itself needs only the standard library).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

REPO = Path(__file__).resolve().parents[1]
THIS = Path(__file__).resolve()
PARITY_TESTS = ["tests/test_render_cuda.py", "tests/test_train_cuda.py"]
NCCL_TEST = "tests/test_distributed.py::test_world_size_one_with_nccl_is_the_single_process_trainer"
# Before the toy scene's first refinement: two GPU runs then agree to float rounding
# (gsplat's backward adds with atomics), as tests/test_distributed.py's NCCL test relies on.
EQUAL_STEPS = 8
# What two GPU runs of one seed may differ by once refinement has amplified rounding
# (the bounds of tests/test_train_cuda.py for a CUDA run against a CPU one).
PSNR_SPREAD_DB = 1.5
GAUSSIAN_RATIO = (0.8, 1.25)
SIDE_BY_SIDE_GOAL = 1.10
MIN_STEP_S = 15  # a step is not started with less of the budget left


# ----------------------------------------------------------------------------------------
# Steps and their results


@dataclass
class Step:
    """One command of the check. ``skip`` returns a reason not to run it (checked just
    before it would start); ``collect`` reads its figures afterwards and may turn a run
    that exited 0 into a failure (or an all-skipped test run into a skip) with a note."""

    name: str
    title: str
    command: list[str]
    cap_s: int
    needs: tuple[str, ...] = ()
    gpu: bool = False
    skip: Callable[[], str | None] | None = None
    collect: Callable[["Result"], None] | None = None


@dataclass
class Result:
    name: str
    title: str
    status: str  # passed | failed | timeout | skipped
    seconds: float = 0.0
    timeout_s: int | None = None
    returncode: int | None = None
    reason: str = ""
    log: str | None = None
    command: str = ""

    def as_json(self) -> dict:
        return {k: v for k, v in vars(self).items() if v not in (None, "")}


def run_logged(command: list[str], log: Path, timeout_s: float, env: dict[str, str]) -> tuple[int | None, float]:
    """Run ``command`` from the repository root, stdout and stderr into ``log``; on
    timeout its whole process group is stopped (torchrun's and pytest's children too).
    Returns (exit status or None on timeout, seconds)."""
    t0 = time.perf_counter()
    with open(log, "w") as out:
        out.write("$ " + shlex.join(command) + "\n")
        out.flush()
        try:
            proc = subprocess.Popen(command, cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, start_new_session=True)
        except OSError as exc:
            out.write(f"cannot start: {exc}\n")
            return 127, time.perf_counter() - t0
        try:
            return proc.wait(timeout=timeout_s), time.perf_counter() - t0
        except subprocess.TimeoutExpired:
            for sig, grace in ((signal.SIGTERM, 10), (signal.SIGKILL, 5)):
                try:
                    os.killpg(proc.pid, sig)
                except ProcessLookupError:
                    break
                try:
                    proc.wait(timeout=grace)
                    break
                except subprocess.TimeoutExpired:
                    continue
            out.write(f"\n[gpu_check] stopped after {timeout_s:.0f} s (its time limit)\n")
            return None, time.perf_counter() - t0


def log_tail(path: Path, lines: int = 3) -> str:
    try:
        text = [l for l in path.read_text(errors="replace").splitlines() if l.strip()]
    except OSError:
        return ""
    return " | ".join(l.strip()[:200] for l in text[-lines:])


# ----------------------------------------------------------------------------------------
# The machine


def quiet_output(command: list[str], timeout_s: float = 20) -> str | None:
    """A short command's stdout, or None when it is missing or fails."""
    try:
        proc = subprocess.run(command, capture_output=True, text=True, timeout=timeout_s, cwd=REPO)
    except (OSError, subprocess.TimeoutExpired):
        return None
    return proc.stdout.strip() if proc.returncode == 0 else None


def describe_machine() -> tuple[dict, str]:
    """GPUs (nvidia-smi), compilers, CPU, OS and the commit: (summary fields, env.txt text)."""
    probes = {
        "nvidia-smi": ["nvidia-smi"],
        "gpus": ["nvidia-smi", "--query-gpu=name,memory.total,driver_version,compute_cap", "--format=csv,noheader"],
        "nvcc": ["nvcc", "--version"],
        "c++": ["c++", "--version"],
        "uname": ["uname", "-a"],
        "commit": ["git", "rev-parse", "HEAD"],
        "changed files": ["git", "status", "--porcelain"],
    }
    found = {name: quiet_output(cmd) for name, cmd in probes.items()}
    cpu = None
    try:
        cpu = next((l.split(":", 1)[1].strip() for l in Path("/proc/cpuinfo").read_text().splitlines()
                    if l.startswith("model name")), None)
    except OSError:
        pass
    gpus = []
    for line in (found["gpus"] or "").splitlines():
        parts = [p.strip() for p in line.split(",")]
        if parts and parts[0]:
            gpus.append(dict(zip(("name", "memory", "driver", "compute_cap"), parts)))
    nvcc = re.search(r"release (\d+\.\d+)", found["nvcc"] or "")
    machine = {
        "gpus": gpus,
        "nvidia_smi": found["nvidia-smi"] is not None,
        "nvcc": nvcc.group(1) if nvcc else None,
        "cxx": (found["c++"] or "").splitlines()[0] if found["c++"] else None,
        "cpu": cpu, "cores": os.cpu_count(), "os": found["uname"],
        "commit": found["commit"],
        "changed_files": len((found["changed files"] or "").splitlines()) if found["changed files"] is not None else None,
    }
    text = "\n".join(f"## {' '.join(cmd)}\n{found[name] if found[name] is not None else '(not available)'}\n"
                     for name, cmd in probes.items())
    return machine, text + f"## /proc/cpuinfo model name\n{cpu}\n## cores\n{os.cpu_count()}\n"


# ----------------------------------------------------------------------------------------
# The check


class Check:
    def __init__(self, args: argparse.Namespace):
        self.args = args
        self.out: Path = args.out.resolve()
        self.logs = self.out / "logs"
        self.start = time.perf_counter()
        self.deadline = self.start + args.budget
        self.results: dict[str, Result] = {}
        self.figures: dict = {}
        self.notes: list[str] = []
        self.versions: dict = {}
        self.machine, self.env_text = describe_machine()
        self.has_gpu = bool(self.machine.get("gpus"))
        # torch.cuda.is_available() in the checked Python, known after the versions step.
        self.cuda: bool | None = None if self.has_gpu else False
        self.smi_reason = "nvidia-smi " + ("lists no GPU" if self.machine.get("nvidia_smi") else "not found")
        self.no_cuda_reason = f"no CUDA GPU ({self.smi_reason})"
        self.extra_results: list[Result] = []
        self.install = not args.skip_install and self.has_gpu
        if not args.skip_install and not self.install:
            self.notes.append(f"{self.no_cuda_reason}: no CUDA torch installed; the CPU parts run with {args.python}")
        venv = args.venv.resolve()
        self.python = str(venv / "bin" / "python") if self.install else args.python
        self.env = self._environment(venv)
        self.toy = self.out / "toy_scene"
        self.iterations = 30 if args.quick else args.iterations

    def _environment(self, venv: Path) -> dict[str, str]:
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        if self.install:
            # The venv is the whole environment: its bin/ first on PATH (torch finds ninja
            # there to compile extensions), nothing from another PYTHONPATH, and gsplat's
            # compiled extension kept beside the venv for a second run.
            env["PATH"] = str(venv / "bin") + os.pathsep + env.get("PATH", "")
            env["VIRTUAL_ENV"] = str(venv)
            env.pop("PYTHONPATH", None)
            env.setdefault("TORCH_EXTENSIONS_DIR", str(venv / "torch_extensions"))
        env.setdefault("MAX_JOBS", str(os.cpu_count() or 4))
        caps = sorted({g["compute_cap"] for g in self.machine.get("gpus", []) if re.fullmatch(r"\d+\.\d+", g.get("compute_cap", ""))})
        if caps:
            env.setdefault("TORCH_CUDA_ARCH_LIST", ";".join(caps))  # compile gsplat for this card only
        return env

    def _set_environment(self) -> dict[str, str]:
        """The variables the check's commands depend on, as they are set for them."""
        names = ("MAX_JOBS", "TORCH_CUDA_ARCH_LIST", "TORCH_EXTENSIONS_DIR", "VIRTUAL_ENV", "PYTHONPATH", "OMP_NUM_THREADS")
        return {k: self.env[k] for k in names if k in self.env}

    # --- the plan ------------------------------------------------------------------------

    def steps(self) -> list[Step]:
        py, a = self.python, self.args
        helper = [py, str(THIS), "helper"]
        steps: list[Step] = []
        if self.install:
            # README command 1, and ninja (a dependency of gsplat's anyway), so that the C++
            # CPU rasterizer of command 2 compiles its files in parallel.
            torch_cmd = [py, "-m", "pip", "install", "--progress-bar", "off", *shlex.split(a.torch), "setuptools>=64", "ninja"]
            if a.torch_index:
                torch_cmd += ["--extra-index-url", a.torch_index]
            steps += [
                Step("install-venv", "a fresh virtual environment",
                     [a.python, "-m", "venv", *(["--clear"] if a.fresh_venv else []), str(a.venv.resolve())], 120,
                     skip=lambda: "reused (it exists; --fresh-venv makes a new one)" if Path(self.python).exists() and not a.fresh_venv else None),
                Step("install-torch", "README command 1: torch (a CUDA build from the registry), setuptools, and ninja", torch_cmd, 360,
                     needs=("install-venv",)),
                Step("install-project", 'README command 2 without bpy: pip install --no-build-isolation -e ".[test]" (gsplat 1.5.3, the C++ CPU rasterizer)',
                     [py, "-m", "pip", "install", "--progress-bar", "off", "--no-build-isolation", "-e", ".[test]"], 300,
                     needs=("install-torch",)),
            ]
        else:
            steps.append(Step("build-cpu-extension", "the C++ CPU rasterizer (python setup.py build_ext --inplace), when the current Python has none",
                              [py, "setup.py", "build_ext", "--inplace"], 300, skip=self._cpu_extension_present))
        installed = ("install-project",) if self.install else ()
        toy_sizes = ["--quick"] if a.quick else []
        steps += [
            Step("versions", "Python, torch, CUDA, gsplat and the project as the checked Python sees them",
                 [*helper, "versions", str(self.logs / "versions.json")], 120, needs=installed, collect=self._collect_versions),
            Step("gsplat-compile", "gsplat's CUDA extension, compiled on first use (timed)",
                 [*helper, "compile-gsplat"],
                 420, needs=("versions",), gpu=True, collect=self._collect_compile),
            Step("parity-tests", "python -m pytest tests/test_render_cuda.py tests/test_train_cuda.py -q (none may skip on a GPU)",
                 [py, "-m", "pytest", *PARITY_TESTS, "-q", "-rs", "-p", "no:cacheprovider",
                  f"--junitxml={self.logs / 'parity-tests.xml'}"], 300, needs=("versions",), collect=self._collect_parity),
            Step("toy-scene", "the embedded toy scene (promptgs_engine.bench.toy_scene), made here",
                 [*helper, "make-toy", str(self.toy), *toy_sizes], 180, needs=("versions",)),
        ]
        trainings = [("3dgs", []), ("promptgs", ["--prompts", str(self.toy / "prompts_2.json")])]
        for strategy, extra in trainings:
            steps.append(self._train_step("cuda", strategy, extra, self.iterations))
        steps.append(Step(
            "side-by-side", "benchmarks/gsplat_side_by_side.py on the toy scene: our CUDA step against gsplat's default step",
            [py, "benchmarks/gsplat_side_by_side.py", str(a.sbs_scene.resolve() if a.sbs_scene else self.toy),
             "--steps", str(50 if a.quick else a.sbs_steps), "--runs", str(a.sbs_runs), "--out", str(self.out / "side_by_side")],
            300, needs=("gsplat-compile",) if a.sbs_scene else ("gsplat-compile", "toy-scene"), gpu=True, collect=self._collect_side_by_side))
        steps += [
            Step("nccl-test", "torch.distributed with NCCL, one rank in this process, equals the plain trainer (8 steps)",
                 [py, "-m", "pytest", NCCL_TEST, "-q", "-rs", "-p", "no:cacheprovider",
                  f"--junitxml={self.logs / 'nccl-test.xml'}"], 180, needs=("gsplat-compile",), gpu=True, collect=self._collect_parity),
            self._train_step("cuda", "3dgs", [], EQUAL_STEPS, name="plain-8"),
            self._train_step("cuda", "3dgs", [], EQUAL_STEPS, name="torchrun-8", torchrun=True),
            Step("torchrun-equals-plain", f"torchrun's Gaussians after {EQUAL_STEPS} steps against the plain run's",
                 [*helper, "compare-runs", str(self.out / "runs" / "torchrun-8"), str(self.out / "runs" / "plain-8"),
                  str(self.out / "torchrun_vs_plain.json")], 120, needs=("plain-8", "torchrun-8"), gpu=True,
                 collect=self._collect_compare),
            self._train_step("cuda", "3dgs", [], self.iterations, name="torchrun-3dgs", torchrun=True),
        ]
        # The CPU side last: it needs no GPU, and it would disturb the GPU timings.
        for strategy, extra in trainings:
            steps.append(self._train_step("cpu", strategy, extra, self.iterations))
        return steps

    def _train_step(self, backend: str, strategy: str, extra: list[str], iterations: int,
                    name: str | None = None, torchrun: bool = False) -> Step:
        name = name or f"train-{backend}-{strategy}"
        run = self.out / "runs" / name
        launcher = [self.python, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "1"] if torchrun \
            else [self.python]
        command = [*launcher, "-m", "promptgs_engine", "train", str(self.toy), "--out", str(run), "--backend", backend,
                   "--strategy", strategy, "--iterations", str(iterations), "--seed", "0", "--quiet", *extra]
        what = f"{strategy} on the toy scene, {iterations} steps, {backend} backend" + \
            (", under torchrun --nproc-per-node 1 (NCCL)" if torchrun else "")
        needs = ("toy-scene", "gsplat-compile") if backend == "cuda" else ("toy-scene",)
        cap = 240 if backend == "cpu" else 150
        return Step(name, what, command, cap, needs=needs, gpu=backend == "cuda",
                    collect=lambda result: self._collect_training(result, run))

    # --- skips ---------------------------------------------------------------------------

    def _cpu_extension_present(self) -> str | None:
        probe = quiet_output([self.python, "-c", "import torch, promptgs_engine._C"], timeout_s=120) if not self.args.dry_run else None
        return "promptgs_engine._C imports already" if probe is not None else None

    def skip_reason(self, step: Step) -> str | None:
        if step.gpu and self.cuda is False:
            return self.no_cuda_reason
        for need in step.needs:
            got = self.results.get(need)
            if got is None or got.status != "passed":
                # A skipped step that did its job (a reused venv) counts as done.
                if got is not None and got.status == "skipped" and got.reason.startswith("reused"):
                    continue
                return f"needs {need} ({got.status if got else 'not run'})"
        if self.deadline - time.perf_counter() < MIN_STEP_S:
            return f"no time left in the --budget of {self.args.budget} s"
        return step.skip() if step.skip is not None else None

    # --- figures -------------------------------------------------------------------------

    def _collect_versions(self, result: Result) -> None:
        path = self.logs / "versions.json"
        if not path.is_file():
            return
        self.versions = json.loads(path.read_text())
        self.cuda = bool(self.versions.get("cuda_available"))
        if not self.cuda:
            torch_v, cuda_v = self.versions.get("torch"), self.versions.get("torch_cuda")
            build = f"torch {torch_v} (CUDA {cuda_v}) sees no GPU" if cuda_v else f"torch {torch_v} is a CPU build"
            self.no_cuda_reason = f"no CUDA GPU ({build}" + (f"; {self.smi_reason})" if not self.has_gpu else ")")
        nvcc, torch_cuda = self.machine.get("nvcc"), self.versions.get("torch_cuda")
        if self.cuda and nvcc and torch_cuda and nvcc.split(".")[0] != str(torch_cuda).split(".")[0]:
            self.notes.append(f"nvcc is CUDA {nvcc} but torch was built for CUDA {torch_cuda}: gsplat's compile "
                              "needs the same major version (choose a torch build with --torch and --torch-index)")
        if self.has_gpu and not self.cuda:
            # A failure of its own, so that the CPU parts still run.
            self.extra_results.append(Result(
                "torch-sees-the-gpu", "torch.cuda.is_available() where nvidia-smi lists a GPU", "failed",
                reason=f"nvidia-smi lists {self.machine['gpus'][0]['name']}, but {self.no_cuda_reason}"))
        engine = Path(self.versions.get("promptgs_engine", "")).resolve()
        if engine != REPO / "promptgs_engine":
            raise CheckFailure(f"promptgs_engine is imported from {engine}, not from this checkout "
                               f"(with --skip-install: PYTHONPATH={REPO})")

    def _collect_compile(self, result: Result) -> None:
        text = Path(result.log).read_text(errors="replace") if result.log else ""
        found = re.search(r"set up successfully in ([\d.]+) seconds", text)
        self.figures["gsplat_compile"] = {"seconds": result.seconds,
                                          "gsplat_reported_s": float(found.group(1)) if found else None,
                                          "note": None if found else "no compile reported: an extension built before was loaded"}

    def _collect_parity(self, result: Result) -> None:
        xml = self.logs / f"{result.name}.xml"
        if not xml.is_file():
            return
        counts = junit_counts(xml)
        self.figures.setdefault("tests", {})[result.name] = counts
        if result.status != "passed":
            return
        if counts["skipped"] and self.cuda:
            result.status = "failed"
            result.reason = f"{counts['skipped']} of {counts['tests']} skipped with a CUDA GPU: {'; '.join(counts['skip_reasons'])}"
        elif counts["skipped"] == counts["tests"]:
            result.status = "skipped"
            result.reason = f"ran; all {counts['tests']} skipped: {'; '.join(counts['skip_reasons'])}"
        else:
            result.reason = f"{counts['passed']} passed, {counts['skipped']} skipped"

    def _collect_training(self, result: Result, run: Path) -> None:
        metrics = read_json(run / "metrics.json")
        train = read_json(run / "train.json")
        if metrics is None and train is None:
            return
        row = {key: (metrics or {}).get(key, (train or {}).get(key)) for key in (
            "backend", "strategy", "iterations", "steps", "psnr", "ssim", "masked_psnr", "recall",
            "n_gaussians", "train_seconds", "peak_gpu_mb", "peak_rss_mb", "world_size")}
        row["wall_seconds"] = round(result.seconds, 2)
        self.figures.setdefault("training", {})[result.name] = row
        if result.status == "passed" and not (isinstance(row["psnr"], (int, float)) and math.isfinite(row["psnr"])):
            result.status, result.reason = "failed", f"test PSNR is {row['psnr']}"
        if result.name == "torchrun-3dgs" and result.status == "passed":
            result.reason = self._torchrun_against_plain(row)

    def _torchrun_against_plain(self, row: dict) -> str:
        plain = self.figures.get("training", {}).get("train-cuda-3dgs")
        if not plain or plain.get("psnr") is None:
            return "no plain CUDA run to compare with"
        d_psnr = row["psnr"] - plain["psnr"]
        ratio = row["n_gaussians"] / plain["n_gaussians"]
        self.figures["torchrun_vs_plain_full_run"] = {"psnr_difference_db": d_psnr, "gaussian_ratio": ratio,
                                                      "bounds": {"psnr_db": PSNR_SPREAD_DB, "gaussian_ratio": GAUSSIAN_RATIO}}
        text = f"PSNR {row['psnr']:.2f} against {plain['psnr']:.2f} dB, {row['n_gaussians']} against {plain['n_gaussians']} Gaussians"
        if abs(d_psnr) >= PSNR_SPREAD_DB or not GAUSSIAN_RATIO[0] < ratio < GAUSSIAN_RATIO[1]:
            raise CheckFailure(f"{text}: beyond two GPU runs' spread")
        return text

    def _collect_side_by_side(self, result: Result) -> None:
        data = read_json(self.out / "side_by_side.json")
        if data is None:
            return
        ratio = data.get("median_ratio")
        self.figures["side_by_side"] = {
            "scene": data.get("dataset"), "steps": data.get("steps"), "runs": len(data.get("runs", [])),
            "device_name": data.get("device_name"), "median_ratio": ratio,
            "within_10_percent": ratio is not None and ratio <= SIDE_BY_SIDE_GOAL,
            "ours": data.get("ours"), "gsplat": data.get("gsplat"),
            "simple_trainer": "gsplat's examples/simple_trainer.py is not run as is: the gsplat wheel does not ship it, and it "
                              "needs viser, nerfview, fused-ssim and LPIPS weights; side B restates its default step "
                              "(benchmarks/gsplat_side_by_side.py's docstring)",
        }
        if ratio is not None:
            result.reason = f"median ours/gsplat {ratio:.3f} ({'within' if ratio <= SIDE_BY_SIDE_GOAL else 'not within'} 10%)"

    def _collect_compare(self, result: Result) -> None:
        data = read_json(self.out / "torchrun_vs_plain.json")
        if data is None:
            return
        self.figures["torchrun_vs_plain"] = data
        result.reason = data.get("verdict", "")

    # --- running -------------------------------------------------------------------------

    def run(self) -> int:
        steps = self.steps()
        if self.args.dry_run:
            self._print_plan(steps)
            return 0
        self._prepare_out()
        (self.out / "env.txt").write_text(self.env_text)
        commands = [f"# {shlex.join(['tools/gpu_check.sh', *self.args.argv])}, from {REPO}",
                    "cd " + shlex.quote(str(REPO))]
        commands += [f"export {k}={shlex.quote(v)}" for k, v in self._set_environment().items()]
        if self.install:
            commands += ["unset PYTHONPATH", f"export PATH={shlex.quote(self.env['VIRTUAL_ENV'] + '/bin')}:\"$PATH\""]
        gpus = ", ".join(g["name"] for g in self.machine["gpus"]) or "none"
        self.say(f"GPU: {gpus}; Python for the check: {self.python}; output: {self.out}")
        for step in steps:
            reason = self.skip_reason(step)
            if reason:
                self.results[step.name] = Result(step.name, step.title, "skipped", reason=reason, command=shlex.join(step.command))
                self.say(f"{step.name}: skipped ({reason})")
                self._write_summary()
                continue
            commands.append(f"# {step.name}: {step.title} (time limit {step.cap_s} s)")
            commands.append(shlex.join(step.command))
            (self.out / "commands.sh").write_text("\n".join(commands) + "\n")
            self._run_step(step)
            self._write_summary()
        return self._finish()

    def _run_step(self, step: Step) -> None:
        timeout = int(min(step.cap_s, self.deadline - time.perf_counter()))
        log = self.logs / f"{step.name}.log"
        self.say(f"{step.name}: {step.title} (up to {timeout} s) ...")
        rc, seconds = run_logged(step.command, log, timeout, self.env)
        status = "passed" if rc == 0 else ("timeout" if rc is None else "failed")
        result = Result(step.name, step.title, status, round(seconds, 2), timeout, rc, log=str(log),
                        command=shlex.join(step.command))
        if status == "timeout":
            result.reason = f"stopped at its time limit of {timeout} s"
        elif status == "failed":
            result.reason = f"exit status {rc}: {log_tail(log)}"
        if step.collect is not None:
            try:
                step.collect(result)
            except CheckFailure as exc:
                result.status, result.reason = "failed", str(exc)
            except (OSError, ValueError, KeyError, TypeError) as exc:  # unreadable output: report, go on
                result.reason = (result.reason + "; " if result.reason else "") + f"figures not read: {exc}"
        result.log = str(log.relative_to(self.out))
        self.results[step.name] = result
        self.say(f"{step.name}: {result.status} in {seconds:.0f} s" + (f" ({result.reason})" if result.reason else ""))
        for extra in self.extra_results:
            self.results[extra.name] = extra
            self.say(f"{extra.name}: {extra.status} ({extra.reason})")
        self.extra_results.clear()

    def _prepare_out(self) -> None:
        if self.out.exists():
            if any(self.out.iterdir()) and not (self.out / "summary.json").is_file():
                raise SystemExit(f"gpu_check: {self.out} exists and is not an earlier check's folder; choose another --out")
            shutil.rmtree(self.out)
        self.logs.mkdir(parents=True)

    def _write_summary(self) -> dict:
        failed = [r.name for r in self.results.values() if r.status in ("failed", "timeout")]
        summary = {
            "command": shlex.join(["tools/gpu_check.sh", *self.args.argv]),
            "repository": str(REPO), "python": self.python, "installed_venv": self.install,
            "budget_s": self.args.budget, "wall_s": round(time.perf_counter() - self.start, 1),
            "machine": self.machine, "versions": self.versions,
            "cuda": {"available": bool(self.cuda), "reason": None if self.cuda else self.no_cuda_reason},
            "environment": self._set_environment(),
            "notes": self.notes, "steps": [r.as_json() for r in self.results.values()], "figures": self.figures,
            "failed": failed,
            "skipped": {r.name: r.reason for r in self.results.values() if r.status == "skipped"},
            "exit_status": 1 if failed else 0,
        }
        (self.out / "summary.json").write_text(json.dumps(summary, indent=2) + "\n")
        return summary

    def _finish(self) -> int:
        summary = self._write_summary()
        print("\n" + format_summary(summary))
        (self.out / "summary.txt").write_text(format_summary(summary) + "\n")
        return summary["exit_status"]

    def _print_plan(self, steps: list[Step]) -> None:
        print(f"gpu_check --dry-run: {len(steps)} steps, budget {self.args.budget} s, Python {self.python}, output {self.out}")
        for note in self.notes:
            print(f"note: {note}")
        for i, step in enumerate(steps, 1):
            flags = ", ".join(filter(None, ["needs a CUDA GPU" if step.gpu else "",
                                            f"after {', '.join(step.needs)}" if step.needs else ""]))
            print(f"{i:2d}. {step.name}: {step.title} [limit {step.cap_s} s{'; ' + flags if flags else ''}]")
            print(f"      {shlex.join(step.command)}")

    def say(self, text: str) -> None:
        print(f"[gpu_check +{time.perf_counter() - self.start:4.0f}s] {text}", flush=True)


class CheckFailure(Exception):
    """A step ran but what it measured fails the check."""


def read_json(path: Path) -> dict | None:
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def junit_counts(path: Path) -> dict:
    """Test counts and skip reasons of a pytest --junitxml file."""
    root = ET.parse(path).getroot()
    suites = [root] if root.tag == "testsuite" else list(root.iter("testsuite"))
    counts = {key: sum(int(s.get(key, 0)) for s in suites) for key in ("tests", "failures", "errors", "skipped")}
    counts["passed"] = counts["tests"] - counts["failures"] - counts["errors"] - counts["skipped"]
    reasons = sorted({el.get("message", "") for s in suites for el in s.iter("skipped")})
    counts["skip_reasons"] = [r for r in reasons if r]
    return counts


def format_summary(summary: dict) -> str:
    lines = [f"gpu_check: {summary['wall_s']:.0f} s of a {summary['budget_s']} s budget; "
             f"GPU: {', '.join(g['name'] for g in summary['machine'].get('gpus', [])) or 'none'}; "
             f"CUDA in torch: {'yes' if summary['cuda']['available'] else 'no'}"]
    lines += [f"note: {n}" for n in summary["notes"]]
    lines.append(f"{'step':<24} {'status':<8} {'s':>6}  what / why")
    for step in summary["steps"]:
        lines.append(f"{step['name']:<24} {step['status']:<8} {step.get('seconds', 0):>6.0f}  {step.get('reason') or step['title']}")
    training = summary["figures"].get("training", {})
    if training:
        lines.append("")
        lines.append(f"{'toy-scene run':<24} {'PSNR':>6} {'Gaussians':>10} {'train s':>8} {'wall s':>7} {'GPU MiB':>8}")
        for name, row in training.items():
            psnr = f"{row['psnr']:.2f}" if isinstance(row.get("psnr"), (int, float)) else "-"
            gpu = f"{row['peak_gpu_mb']:.0f}" if isinstance(row.get("peak_gpu_mb"), (int, float)) else "-"
            train = f"{row['train_seconds']:.1f}" if isinstance(row.get("train_seconds"), (int, float)) else "-"
            lines.append(f"{name:<24} {psnr:>6} {row.get('n_gaussians') or '-':>10} {train:>8} {row['wall_seconds']:>7.1f} {gpu:>8}")
    sbs = summary["figures"].get("side_by_side")
    if sbs and sbs.get("median_ratio") is not None:
        lines.append(f"side by side: ours {sbs['ours']['median_ms_per_step']:.2f} ms/step, gsplat "
                     f"{sbs['gsplat']['median_ms_per_step']:.2f} ms/step, median ratio {sbs['median_ratio']:.3f}")
    lines.append("failed: " + (", ".join(summary["failed"]) or "nothing") + f"; exit status {summary['exit_status']}")
    return "\n".join(lines)


# ----------------------------------------------------------------------------------------
# Helpers the steps run with the checked Python (these import torch)


def helper_versions(out: Path) -> int:
    import importlib.metadata as md
    import platform

    import torch

    info: dict = {"python": platform.python_version(), "executable": sys.executable,
                  "torch": torch.__version__, "torch_cuda": torch.version.cuda,
                  "cudnn": torch.backends.cudnn.version() if torch.backends.cudnn.is_available() else None,
                  "cuda_available": torch.cuda.is_available(), "devices": []}
    if torch.cuda.is_available():
        for i in range(torch.cuda.device_count()):
            p = torch.cuda.get_device_properties(i)
            info["devices"].append({"name": p.name, "memory_mib": p.total_memory // 2**20, "capability": f"{p.major}.{p.minor}"})
    import torch.distributed as dist

    info["nccl"] = dist.is_available() and dist.is_nccl_available()
    if info["nccl"] and torch.cuda.is_available():
        info["nccl_version"] = ".".join(map(str, torch.cuda.nccl.version()))
    for name in ("gsplat", "numpy", "pycolmap", "plyfile", "pytest", "av", "promptgs"):
        try:
            info[name] = md.version(name)
        except md.PackageNotFoundError:
            info[name] = None
    import promptgs_engine

    info["promptgs_engine"] = str(Path(promptgs_engine.__file__).parent)
    from promptgs_engine import _C  # noqa: F401  (the C++ CPU rasterizer must be built)

    out.write_text(json.dumps(info, indent=2) + "\n")
    print(json.dumps(info, indent=2))
    return 0


def helper_compile_gsplat() -> int:
    """gsplat's CUDA extension: compiled with nvcc on first use, loaded afterwards."""
    t0 = time.perf_counter()
    from gsplat.cuda._backend import _C

    if _C is None:
        print("gsplat has no CUDA extension: it found no CUDA toolkit (nvcc on PATH, or CUDA_HOME)")
        return 1
    print(f"gsplat CUDA extension ready in {time.perf_counter() - t0:.1f} s: {getattr(_C, '__file__', _C)}")
    return 0


def helper_make_toy(folder: Path, quick: bool) -> int:
    from promptgs_engine.bench.toy_scene import QUICK_TOY, ToySceneConfig, make_toy_scene

    cfg = QUICK_TOY if quick else ToySceneConfig()
    make_toy_scene(folder, cfg)
    print(f"toy scene {cfg.width}x{cfg.height}, {cfg.n_views} views -> {folder}")
    return 0


def helper_compare_runs(a: Path, b: Path, out: Path) -> int:
    """Two runs' Gaussians, equal up to float rounding (gsplat's atomics): at most 0.1% of
    the entries more than 1e-4 apart and none more than 1e-2, the rule of
    tests/test_distributed.py's NCCL test; a wiring error moves most entries."""
    from promptgs_engine.run_folder import load_run

    (_, pa), (_, pb) = load_run(a), load_run(b)
    keys: dict = {}
    equal = set(pa.keys()) == set(pb.keys())
    for key in sorted(set(pa.keys()) & set(pb.keys())):
        x, y = pa[key].detach().float().cpu(), pb[key].detach().float().cpu()
        if x.shape != y.shape:
            keys[key] = {"shapes": [list(x.shape), list(y.shape)]}
            equal = False
            continue
        diff = (x - y).abs()
        over = float((diff > 1e-4).float().mean()) if diff.numel() else 0.0
        largest = float(diff.max()) if diff.numel() else 0.0
        keys[key] = {"max_abs_difference": largest, "fraction_over_1e-4": over, "bit_equal": bool((diff == 0).all())}
        equal = equal and over <= 1e-3 and largest <= 1e-2
    verdict = ("equal to float rounding" if equal else "NOT equal") + f" ({a.name} against {b.name})"
    if equal and all(k.get("bit_equal") for k in keys.values()):
        verdict = f"bit for bit equal ({a.name} against {b.name})"
    result = {"verdict": verdict, "equal": equal, "parameters": keys,
              "rule": "at most 0.1% of the entries more than 1e-4 apart, none more than 1e-2"}
    out.write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps(result, indent=2))
    return 0 if equal else 1


def helper(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="gpu_check.py helper")
    sub = ap.add_subparsers(dest="name", required=True)
    p = sub.add_parser("versions")
    p.add_argument("out", type=Path)
    sub.add_parser("compile-gsplat")
    p = sub.add_parser("make-toy")
    p.add_argument("folder", type=Path)
    p.add_argument("--quick", action="store_true")
    p = sub.add_parser("compare-runs")
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    p.add_argument("out", type=Path)
    args = ap.parse_args(argv)
    if args.name == "versions":
        return helper_versions(args.out)
    if args.name == "compile-gsplat":
        return helper_compile_gsplat()
    if args.name == "make-toy":
        return helper_make_toy(args.folder, args.quick)
    return helper_compare_runs(args.a, args.b, args.out)


# ----------------------------------------------------------------------------------------


def parse_args(argv: list[str]) -> argparse.Namespace:
    ap = argparse.ArgumentParser(prog="tools/gpu_check.sh", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=REPO / "runs" / "gpu-check", help="the folder everything goes into (replaced; default runs/gpu-check)")
    ap.add_argument("--skip-install", action="store_true", help="check the current Python (--python) instead of installing a venv")
    ap.add_argument("--python", default=sys.executable, help="the Python to check with --skip-install, or to make the venv with (default: this one)")
    ap.add_argument("--venv", type=Path, default=REPO / ".gpu-venv", help="the virtual environment to install into (default .gpu-venv)")
    ap.add_argument("--fresh-venv", action="store_true", help="make the venv anew even when it exists (gsplat's compiled extension in it goes too)")
    ap.add_argument("--torch", default="torch==2.13.0", help="what pip installs for torch (default torch==2.13.0, the README's)")
    ap.add_argument("--torch-index", help="an extra package index for torch, e.g. https://download.pytorch.org/whl/cu126 (with --torch torch==2.13.0+cu126)")
    ap.add_argument("--budget", type=int, default=540, help="seconds for the whole check; no step starts past it (default 540)")
    ap.add_argument("--iterations", type=int, default=300, help="steps of the toy-scene trainings (default 300)")
    ap.add_argument("--sbs-steps", type=int, default=1000, help="steps of each side-by-side run (default 1000)")
    ap.add_argument("--sbs-runs", type=int, default=2, help="side-by-side pairs (default 2)")
    ap.add_argument("--sbs-scene", type=Path, help="a COLMAP scene for the side-by-side instead of the toy scene (e.g. ../shared/data/tumbler)")
    ap.add_argument("--quick", action="store_true", help="a smoke run: the tests' small toy scene, 30 training steps, 50 side-by-side steps")
    ap.add_argument("--dry-run", action="store_true", help="list the steps and their commands; run nothing")
    args = ap.parse_args(argv)
    args.argv = argv
    return args


def main(argv: list[str] | None = None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    if argv[:1] == ["helper"]:
        return helper(argv[1:])
    if sys.version_info < (3, 10):
        raise SystemExit("gpu_check needs Python 3.10 or newer")
    return Check(parse_args(argv)).run()


if __name__ == "__main__":
    sys.exit(main())
