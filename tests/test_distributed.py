"""Data-parallel training: gloo ranks on this CPU machine against one process.

The runs use the toy scene at 64×48 without the sky shell and with a budget of 16k
Gaussians, so that 240 views (120 steps of two) take seconds yet clone, split, prune and
reset the opacity. Each rank uses one thread, as does the one-process run it is compared with (the
CPU backward's sums depend on the thread count).
"""

from __future__ import annotations

import json
import multiprocessing
import os
import signal
import socket
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
import torch

from promptgs_engine import distributed
from promptgs_engine.batch import adam_settings, rank_share, scale_schedule, steps_for
from promptgs_engine.cli import main
from promptgs_engine.config import TrainConfig
from promptgs_engine.data import load_colmap_scene
from promptgs_engine.distributed import Dist, DistributedError
from promptgs_engine.errors import PromptGSError
from promptgs_engine.strategies import DefaultSchedule
from promptgs_engine.threads import one_thread
from promptgs_engine.train import Trainer

REPO = Path(__file__).resolve().parents[1]
ITERATIONS = 240
# The CPU backend (gloo): on a machine with one GPU, "auto" would ask two ranks for a GPU each.
COMMON = ["--iterations", str(ITERATIONS), "--resolution-scale", "0.5", "--no-sky", "--budget", "16000", "--backend", "cpu", "--quiet"]


def _config(toy: Path, out: Path, **kw) -> TrainConfig:
    base = dict(dataset=str(toy), out=str(out), iterations=ITERATIONS, resolution_scale=0.5, sky=False, budget=16000,
                backend="cpu")
    base.update(kw)
    return TrainConfig(**base)


def _train_in_process(cfg: TrainConfig, dist: Dist | None = None) -> Trainer:
    """Train ``cfg`` here with one thread (like one rank) and return the trainer."""
    with one_thread():
        trainer = Trainer(cfg, scene=load_colmap_scene(cfg.dataset), quiet=True, dist=dist)
        trainer.out.mkdir(parents=True, exist_ok=True)
        trainer.train()
    return trainer


def _launch(args: list[str], rank_params: Path | None = None, nproc_flag: bool = True, **popen) -> subprocess.Popen:
    """``promptgs train ARGS --nproc 2`` (torchrun underneath; without ``nproc_flag`` the
    job file in ARGS asks for the processes), one thread per rank."""
    env = dict(os.environ, PYTHONPATH=str(REPO) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("OMP_NUM_THREADS", None)
    if rank_params is not None:
        rank_params.mkdir(parents=True, exist_ok=True)
        env[distributed.RANK_PARAMS_ENV] = str(rank_params)
    env.update(popen.pop("env", {}))
    command = [sys.executable, "-m", "promptgs_engine", "train", *args, *(["--nproc", "2"] if nproc_flag else []), "--threads", "1"]
    return subprocess.Popen(command, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **popen)


def _assert_same_params(a: dict, b: dict) -> None:
    assert a["means"].shape == b["means"].shape, (a["means"].shape, b["means"].shape)
    for key in a:
        assert torch.equal(a[key].detach().cpu(), b[key].detach().cpu()), key


@pytest.fixture(scope="module")
def one_process_batch_of_two(toy, tmp_path_factory):
    """The 3DGS run of one process with two views a step, and what its refinement did."""
    from promptgs_engine.strategies import default as ours

    counts = {"duplicate": 0, "split": 0, "remove": 0, "reset_opa": 0}

    def counting(module, name):
        real = getattr(module, name)

        def wrapper(*args, **kwargs):
            mask = kwargs.get("mask")  # Gaussians cloned, split or removed; resets
            counts[name] += 1 if mask is None else int(mask.sum())
            return real(*args, **kwargs)

        return real, wrapper

    patched = [(ours, "duplicate"), (ours, "split"), (ours, "remove"), (ours, "reset_opa")]
    originals = []
    for module, name in patched:
        real, wrapper = counting(module, name)
        originals.append((module, name, real))
        setattr(module, name, wrapper)
    try:
        trainer = _train_in_process(_config(toy, tmp_path_factory.mktemp("batch2"), batch_size=2))
    finally:
        for module, name, real in originals:
            setattr(module, name, real)
    return trainer, counts


def test_batch_rules():
    assert adam_settings(0.01, 1) == {"lr": 0.01, "eps": 1e-15, "betas": (0.9, 0.999)}
    four = adam_settings(0.01, 4)
    assert four["lr"] == pytest.approx(0.02) and four["eps"] == pytest.approx(5e-16)
    assert four["betas"] == pytest.approx((0.9**4, 0.999**4))
    assert steps_for(240, 2) == 120 and steps_for(241, 2) == 121 and steps_for(7, 1) == 7
    s = DefaultSchedule.for_iterations(3000)
    assert scale_schedule(s, 1) == s
    half = scale_schedule(s, 2)
    assert (half.refine_every, half.reset_every, half.refine_stop_iter) == (s.refine_every // 2, s.reset_every // 2, s.refine_stop_iter // 2)
    # Contiguous blocks, the first ranks one view more: every view once.
    assert [rank_share(3, r, 2) for r in range(2)] == [[0, 1], [2]]
    assert [rank_share(5, r, 3) for r in range(3)] == [[0, 1], [2, 3], [4]]
    assert [rank_share(1, r, 2) for r in range(2)] == [[0], []]


def test_two_ranks_of_one_view_equal_one_process_with_two_views(toy, tmp_path, one_process_batch_of_two):
    trainer, counts = one_process_batch_of_two
    # The run is long enough for every kind of refinement.
    assert all(n > 0 for n in counts.values()), counts
    assert trainer.total_steps == ITERATIONS // 2

    out, dumps = tmp_path / "run", tmp_path / "ranks"
    proc = _launch([str(toy), "--out", str(out), *COMMON], rank_params=dumps)
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr[-2000:]
    assert "2 ranks (gloo), 2 views a step" in (out / "train.log").read_text()
    rank0, rank1 = torch.load(dumps / "rank0.pt"), torch.load(dumps / "rank1.pt")
    _assert_same_params(rank0, rank1)  # the ranks agree bit for bit
    _assert_same_params(rank0, dict(trainer.params))  # and equal the one process, bit for bit
    ckpt = torch.load(out / "ckpt.pt", weights_only=False)
    assert ckpt["step"] == ITERATIONS // 2
    _assert_same_params(ckpt["params"], rank0)


def test_a_killed_rank_ends_the_run_with_one_line_and_its_checkpoint_resumes_on_one_rank(
    toy, tmp_path, one_process_batch_of_two
):
    out = tmp_path / "run"
    tag = uuid.uuid4().hex
    proc = _launch([str(toy), "--out", str(out), *COMMON, "--checkpoint-every", "5"], env={"PROMPTGS_TEST_TAG": tag})
    rank1 = None
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and proc.poll() is None:
        if (out / "ckpt.pt").is_file():
            rank1 = _find_rank(tag, 1)
            if rank1 is not None:
                break
        time.sleep(0.02)
    assert rank1 is not None, "the run ended before a checkpoint was written"
    os.kill(rank1, signal.SIGKILL)
    t0 = time.monotonic()
    stdout, stderr = proc.communicate(timeout=120)
    assert time.monotonic() - t0 < 60
    assert proc.returncode == 2
    last = stderr.strip().splitlines()[-1]
    assert last.startswith("promptgs: error: distributed training failed: rank 1 was killed by SIGKILL"), last
    assert str(out) in last
    assert not (out / "point_cloud.ply").exists()

    # The last checkpoint is whole, and one process takes the run to the end: it keeps the
    # run's two views a step, and ends where the uninterrupted run ends, bit for bit.
    step = torch.load(out / "ckpt.pt", weights_only=False)["step"]
    assert 0 < step < ITERATIONS // 2
    threads = torch.get_num_threads()
    try:
        assert main(["train", str(toy), "--out", str(out), "--resume", "--iterations", str(ITERATIONS), "--threads", "1", "--quiet"]) == 0
    finally:
        torch.set_num_threads(threads)
    assert f"resumed at step {step}" in (out / "train.log").read_text()
    resumed = torch.load(out / "ckpt.pt", weights_only=False)
    assert resumed["step"] == ITERATIONS // 2
    reference, _ = one_process_batch_of_two
    _assert_same_params(resumed["params"], dict(reference.params))


def _find_rank(tag: str, rank: int) -> int | None:
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            env = (entry / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if f"PROMPTGS_TEST_TAG={tag}".encode() in env and f"RANK={rank}".encode() in env:
            return int(entry.name)
    return None


def test_promptgs_trains_distributed_like_one_process(toy, tmp_path):
    prompts = str(toy / "prompts_2.json")
    # The job file's `nproc` starts the ranks, as the Blender add-on and the bench ask for them.
    job = tmp_path / "job.json"
    # Proposed prompts and compaction too: every rank proposes and measures importance from
    # the same parameters; rank 0 writes the proposal file.
    job.write_text(json.dumps({"strategy": "promptgs", "prompts": prompts, "budget": 3000, "nproc": 2, "propose_prompts": True,
                                "compact": True}))
    out, dumps = tmp_path / "run", tmp_path / "ranks"
    common = [a for a in COMMON if a not in ("--budget", "16000")]
    proc = _launch([str(toy), "--out", str(out), "--job", str(job), *common], rank_params=dumps, nproc_flag=False)
    one = _train_in_process(_config(toy, tmp_path / "one", batch_size=2, strategy="promptgs", prompts=prompts, budget=3000,
                                    propose_prompts=True, compact=True))
    stdout, stderr = proc.communicate(timeout=300)
    assert proc.returncode == 0, stderr[-2000:]
    assert "resampled" in (out / "train.log").read_text()
    assert "proposed prompts" in (out / "train.log").read_text()
    assert json.loads((out / "train.json").read_text())["compaction"] is not None
    assert (out / "proposals.json").read_text() == (tmp_path / "one" / "proposals.json").read_text().replace(
        str(tmp_path / "one"), str(out))
    rank0, rank1 = torch.load(dumps / "rank0.pt"), torch.load(dumps / "rank1.pt")
    _assert_same_params(rank0, rank1)
    # Steps of three views (a single view and a related pair) split 2 + 1 and still add
    # in the one process's order: equal bit for bit, error field and scores included.
    _assert_same_params(rank0, dict(one.params))
    assert one.entry > one.total_steps  # multiview entries counted as their views


def _torchrun_env_of_one(monkeypatch) -> None:
    """The environment torchrun gives the one rank of a world of one."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    for name, value in {"RANK": "0", "WORLD_SIZE": "1", "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": str(port)}.items():
        monkeypatch.setenv(name, value)


def test_world_size_one_is_the_single_process_trainer(toy, tmp_path, monkeypatch):
    _torchrun_env_of_one(monkeypatch)
    ctx = distributed.init_from_env("cpu", timeout_s=30)
    try:
        assert ctx.backend == "gloo" and ctx.world_size == 1 and ctx.is_writer
        cfg = _config(toy, tmp_path / "world1", iterations=60)
        ranked = _train_in_process(cfg, dist=ctx)
    finally:
        ctx.close()
    assert not ranked.batched and ranked.batch_size == 1
    plain = _train_in_process(_config(toy, tmp_path / "plain", iterations=60))
    _assert_same_params(dict(ranked.params), dict(plain.params))


# -- timeouts and divergence, with forked gloo ranks ---------------------------------------


def _rank_main(rank: int, init_file: str, behaviour: str, queue) -> None:
    import datetime

    import torch.distributed as dist

    dist.init_process_group("gloo", init_method=f"file://{init_file}", rank=rank, world_size=2, timeout=datetime.timedelta(seconds=3))
    ctx = Dist(rank=rank, world_size=2, backend="gloo", timeout_s=3)
    params = {"means": torch.ones(4, 3), "opacities": torch.zeros(4)}
    try:
        if behaviour == "silent" and rank == 1:
            time.sleep(30)  # alive, but never joins the collective
        elif behaviour == "diverge":
            if rank == 1:
                params["means"][2, 1] = 1.0000001
            ctx.check_agreement(40, params)
        else:
            ctx.all_reduce_sum([torch.ones(3)])
        queue.put((rank, "ok"))
    except DistributedError as exc:
        queue.put((rank, str(exc)))


def _run_forked(tmp_path: Path, behaviour: str) -> tuple[dict, float]:
    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    procs = [ctx.Process(target=_rank_main, args=(r, str(tmp_path / "init"), behaviour, queue)) for r in range(2)]
    t0 = time.monotonic()
    for p in procs:
        p.start()
    results = {}
    try:
        while len(results) < (1 if behaviour == "silent" else 2):
            rank, message = queue.get(timeout=60)
            results[rank] = message
        elapsed = time.monotonic() - t0
    finally:
        for p in procs:
            if p.is_alive():
                p.kill()
            p.join()
    return results, elapsed


def test_a_rank_that_stops_answering_makes_the_other_fail_within_the_timeout(tmp_path):
    results, elapsed = _run_forked(tmp_path, "silent")
    message = results[0]
    assert message.startswith("rank 0: lost the other ranks during the gradient all-reduce"), message
    assert "within 3 s" in message and "\n" not in message
    assert elapsed < 20


def test_ranks_that_diverge_stop_with_a_clear_error(tmp_path):
    results, _ = _run_forked(tmp_path, "diverge")
    for rank in (0, 1):
        assert results[rank].startswith("step 40: the ranks diverged (parameters differ between rank"), results[rank]


def test_bad_process_options_are_one_line_errors(toy, tmp_path, capsys):
    assert main(["train", str(toy), "--out", str(tmp_path / "a"), "--nproc", "0"]) == 2
    assert "nproc must be a positive whole number" in capsys.readouterr().err
    assert main(["train", str(toy), "--out", str(tmp_path / "b"), "--batch-size", "0"]) == 2
    assert "--batch-size must be a positive whole number of views" in capsys.readouterr().err
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_ranks_take_photos_only_once_reconstructed(tmp_path, monkeypatch):
    """Ranks never run SfM side by side into one folder: under torchrun with several
    ranks, photos need the reconstruction that `--nproc` makes before it starts them."""
    from promptgs_engine import cli

    photos = tmp_path / "photos"
    photos.mkdir()
    (photos / "a.jpg").write_bytes(b"")
    args = cli.build_parser().parse_args(["train", str(photos), "--out", str(tmp_path / "run")])
    cfg = cli.train_config_from_args(args)
    with pytest.raises(PromptGSError, match=r"reconstructed before the ranks start: use `promptgs train --nproc N`"):
        cli._sfm_first(cfg, args, None, ranks=2)
    assert cfg.dataset == str(photos) and not (tmp_path / "run").exists()
    # A finished reconstruction in the run folder is what every rank trains on.
    monkeypatch.setattr("promptgs_engine.sfm.pipeline.finished_summary", lambda folder: {"status": "ok"})
    monkeypatch.setattr("promptgs_engine.sfm.chain.finished_summary", lambda folder: {"status": "ok"})
    cli._sfm_first(cfg, args, None, ranks=2)
    assert cfg.dataset == str(tmp_path / "run" / "sfm")


def test_failure_line_names_the_killed_rank():
    output = [
        "Root Cause (first observed failure):\n", "[0]:\n", "  rank      : 1 (local_rank: 1)\n",
        "  exitcode  : -9 (pid: 123)  (SIGKILL)\n",
    ]
    expected = (
        "distributed training failed: rank 1 was killed by SIGKILL, and the other ranks were stopped; "
        "the last checkpoint is kept in runs/x"
    )
    assert distributed.failure_line(output, 1, "runs/x") == expected
    # On a loaded machine torchrun can see the survivor's error first (rank 0 lost its peer
    # in an all-reduce) and name it the root cause; the killed rank, listed among the other
    # failures, is still the cause.
    output = [
        "Failures:\n", "[1]:\n", "  rank      : 1 (local_rank: 1)\n", "  exitcode  : -9 (pid: 124)  (SIGKILL)\n",
        "  traceback : Signal 9 (SIGKILL) received by PID 124\n", "-----\n",
        "Root Cause (first observed failure):\n", "[0]:\n", "  rank      : 0 (local_rank: 0)\n",
        "  exitcode  : 2 (pid: 123) \n", "  traceback : <N/A>\n",
        "promptgs: error: rank 0: lost the other ranks during the gradient all-reduce\n",
    ]
    assert distributed.failure_line(output, 2, "runs/x") == expected
    # Older torchruns (2.11 on an H100 machine) print the code without the signal's name.
    output[3] = "  exitcode  : -9 (pid: 124)\n"
    assert distributed.failure_line(output, 2, "runs/x") == expected
    # With no rank killed, the root cause's own report ends the run.
    assert distributed.describe_failure(output[:2] + output[6:]) == "rank 0 exited with code 2"
    # A rank that stops on bad input reports it; that line ends the run.
    assert distributed.failure_line(["promptgs: error: data: no images\n"], 1, None) == "data: no images"


def _assert_equal_up_to_atomics(a: torch.Tensor, b: torch.Tensor, name: str) -> None:
    """Two CUDA runs of the same steps: gsplat's backward adds with atomics, and Adam divides
    by the gradient's own running size, so an element whose gradient is near zero can move
    by a few learning-rate steps on rounding alone (seen on an H100: one of 6,000 quaternion
    entries 1.6e-4 apart after 8 steps). A wiring error (a gradient not reduced, a batch
    weighted twice, another view order) moves most elements instead."""
    diff = (a - b).abs()
    off = float((diff > 1e-4).float().mean())
    assert off <= 1e-3, f"{name}: {off:.2%} of the elements differ by more than 1e-4"
    assert float(diff.max()) <= 1e-2, f"{name}: largest difference {float(diff.max()):.3g}"


@pytest.mark.gpu
def test_world_size_one_with_nccl_is_the_single_process_trainer(toy, tmp_path, monkeypatch):
    if not torch.cuda.is_available() or not torch.distributed.is_nccl_available():
        pytest.skip("needs a CUDA GPU and NCCL")
    _torchrun_env_of_one(monkeypatch)
    # Eight steps, before the first refinement: gsplat's CUDA backward adds with atomics,
    # so two GPU runs agree to float rounding, not bit for bit, and a refinement could
    # turn a rounding difference into a different Gaussian.
    ctx = distributed.init_from_env("cuda", timeout_s=60)
    try:
        assert ctx.backend == "nccl"
        ranked = _train_in_process(_config(toy, tmp_path / "nccl", iterations=8, backend="cuda"), dist=ctx)
        # Two views a step on one GPU: the batched step, its NCCL collectives of one rank.
        batched = _train_in_process(_config(toy, tmp_path / "nccl2", iterations=8, backend="cuda", batch_size=2), dist=ctx)
    finally:
        ctx.close()
    plain = _train_in_process(_config(toy, tmp_path / "plain", iterations=8, backend="cuda"))
    assert not ranked.batched and batched.total_steps == 4
    for key, value in plain.params.items():
        _assert_equal_up_to_atomics(ranked.params[key], value, key)
