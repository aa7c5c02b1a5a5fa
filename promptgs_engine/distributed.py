"""Data-parallel training across processes with torch.distributed (docs/distributed.md).

Every rank holds all Gaussians and trains on its share of each step's views
(`batch.py`); this module is the communication around that:

* `init_from_env` joins the process group that ``torchrun`` (or
  ``promptgs train --nproc N``, which starts torchrun) describes in the ``RANK``,
  ``WORLD_SIZE``, ``LOCAL_RANK``, ``LOCAL_WORLD_SIZE``, ``MASTER_ADDR`` and
  ``MASTER_PORT`` environment variables: ``gloo`` for the CPU backend, ``nccl`` for CUDA.
  Without them the run is one process (`Dist()`, world size 1) and nothing here
  communicates.
* `Dist.all_reduce_sum` sums a list of tensors across ranks in one flat all-reduce
  (gradients and densification statistics of a step); `Dist.all_reduce_max`,
  `Dist.all_gather_object` and `Dist.barrier` do the rest.
* `Dist.check_agreement` compares the Gaussian count and an exact checksum of every
  parameter's bits across ranks, and stops the run with a clear error when they differ.
* Every collective waits at most ``timeout_s``; a rank that died or stopped makes the
  others fail with a one-line `DistributedError` instead of hanging.
* `launch` is ``promptgs train --nproc N``: the same command under
  ``python -m torch.distributed.run --standalone`` on this machine, ending with one clear
  line when a rank fails.
"""

from __future__ import annotations

import datetime
import logging
import os
import re
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Callable, NamedTuple, Sequence

import torch

from .errors import PromptGSError

log = logging.getLogger("promptgs.distributed")

# How long a collective waits for the other ranks (seconds). Rank 0 alone writes
# checkpoints and snapshots while the others wait at the next step's all-reduce, so this
# must cover the slowest of those writes.
DEFAULT_TIMEOUT_S = 300.0
# Environment variables torchrun sets in every rank.
TORCHRUN_ENV = ("RANK", "WORLD_SIZE", "MASTER_ADDR", "MASTER_PORT")
# A debugging aid: with this variable set to a folder, every rank writes its final
# Gaussians there as rank<R>.pt (docs/distributed.md, "Checking reproducibility").
RANK_PARAMS_ENV = "PROMPTGS_RANK_PARAMS"
CHECKSUM_CHUNK = 1 << 22


class DistributedError(PromptGSError, RuntimeError):
    """The ranks of a distributed run lost each other or disagree; the run stops."""


def launched_by_torchrun() -> bool:
    """Whether this process is a rank that torchrun (or an equivalent launcher) started."""
    return all(name in os.environ for name in TORCHRUN_ENV)


def usable_cores() -> int:
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # macOS, Windows
        return os.cpu_count() or 1


def threads_per_rank(local_world_size: int) -> int:
    """OpenMP threads of one rank when ``local_world_size`` ranks share this machine."""
    return max(1, usable_cores() // max(1, local_world_size))


@dataclass
class Dist:
    """This process's place in the run: rank, world size, and the collectives.

    The default (``Dist()``) is a single process: every collective returns its input."""

    rank: int = 0
    world_size: int = 1
    local_rank: int = 0
    local_world_size: int = 1
    backend: str | None = None  # "gloo" | "nccl" once a process group exists
    timeout_s: float = DEFAULT_TIMEOUT_S
    bytes_reduced: int = 0  # payload of all_reduce_sum so far (this rank's buffer)
    seconds_reduced: float = 0.0  # wall time in all_reduce_sum so far (gloo: transfer and waiting for slower ranks; NCCL: the launch only)
    _previous_sigterm: Any = field(default=None, repr=False)

    @property
    def is_writer(self) -> bool:
        """Rank 0 writes events, snapshots, checkpoints, the PLY and the metrics."""
        return self.rank == 0

    @property
    def distributed(self) -> bool:
        return self.world_size > 1

    # -- collectives --------------------------------------------------------------------

    def _call(self, what: str, fn: Callable, *args, **kwargs):
        import torch.distributed as dist

        try:
            return fn(*args, **kwargs)
        except (RuntimeError, dist.DistError) as exc:  # gloo/nccl errors, timeouts
            if isinstance(exc, PromptGSError):
                raise
            detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            detail = re.sub(r"^\[[^\]]*\]\s*", "", detail)[:200]  # drop gloo's source location
            raise DistributedError(
                f"rank {self.rank}: lost the other ranks during {what} (a rank stopped, or did not answer "
                f"within {self.timeout_s:g} s): {detail}"
            ) from exc

    def all_reduce_sum(self, tensors: Sequence[torch.Tensor], what: str = "the gradient all-reduce") -> list[torch.Tensor]:
        """Element-wise sums over ranks of ``tensors`` (same shapes and dtype on every
        rank), in one flat all-reduce; returned as views into one buffer."""
        tensors = list(tensors)
        if not self.distributed or not tensors:
            return tensors
        import torch.distributed as dist

        flat = torch.cat([t.reshape(-1) for t in tensors])
        self.bytes_reduced += flat.numel() * flat.element_size()
        t0 = time.perf_counter()
        self._call(what, dist.all_reduce, flat, op=dist.ReduceOp.SUM)
        self.seconds_reduced += time.perf_counter() - t0
        out, offset = [], 0
        for t in tensors:
            out.append(flat[offset : offset + t.numel()].view(t.shape))
            offset += t.numel()
        return out

    def all_reduce_max(self, tensor: torch.Tensor, what: str = "a statistics all-reduce") -> torch.Tensor:
        if not self.distributed:
            return tensor
        import torch.distributed as dist

        self._call(what, dist.all_reduce, tensor, op=dist.ReduceOp.MAX)
        return tensor

    def all_gather_object(self, obj: Any, what: str = "an all-gather") -> list[Any]:
        """Every rank's ``obj``, in rank order."""
        if not self.distributed:
            return [obj]
        import torch.distributed as dist

        out: list[Any] = [None] * self.world_size
        self._call(what, dist.all_gather_object, out, obj)
        return out

    def barrier(self, what: str = "a barrier") -> None:
        if not self.distributed:
            return
        import torch.distributed as dist

        # gloo's barrier is an all-reduce and honours the process group's timeout.
        self._call(what, dist.barrier)

    # -- agreement ----------------------------------------------------------------------

    def check_agreement(self, step: int, params: dict[str, torch.Tensor]) -> None:
        """Stop with a clear error unless every rank holds the same Gaussians, bit for bit
        (count and `parameter_checksum`)."""
        if not self.distributed:
            return
        mine = parameter_checksum(params)
        everyone = self.all_gather_object(mine, what=f"the agreement check at step {step}")
        for rank, theirs in enumerate(everyone):
            if theirs != mine:
                n_mine, n_theirs = mine[0], theirs[0]
                detail = (
                    f"{n_theirs} Gaussians on rank {rank} against {n_mine} on rank {self.rank}"
                    if n_theirs != n_mine
                    else f"parameters differ between rank {rank} and rank {self.rank}"
                )
                raise DistributedError(
                    f"step {step}: the ranks diverged ({detail}); refinement or the view schedule is not "
                    "deterministic here (docs/distributed.md, 'What is bit-reproducible')"
                )

    # -- set-up and shutdown ------------------------------------------------------------

    def install_stop_handler(self) -> None:
        """Turn the launcher's SIGTERM (sent when another rank failed) into a one-line
        error, so this rank reports it, sends its error event and exits."""

        def on_sigterm(signum, frame):
            signal.signal(signal.SIGTERM, signal.SIG_IGN)  # report once
            raise DistributedError(f"rank {self.rank}: stopped by the launcher (another rank failed, or the run was cancelled)")

        if threading.current_thread() is threading.main_thread():
            self._previous_sigterm = signal.signal(signal.SIGTERM, on_sigterm)

    def close(self) -> None:
        if self._previous_sigterm is not None:
            signal.signal(signal.SIGTERM, self._previous_sigterm)
            self._previous_sigterm = None
        if self.backend is None:
            return
        import torch.distributed as dist

        if dist.is_initialized():
            try:
                dist.destroy_process_group()
            except Exception:  # the peers may be gone already
                pass
        self.backend = None


def parameter_checksum(params: dict[str, torch.Tensor]) -> list[int]:
    """[Gaussian count, one checksum per parameter]: the parameter's bits as 32-bit
    integers, weighted by position and summed with 64-bit wrap-around. Exact (equal
    parameters give equal sums on any machine) and sensitive to order."""
    out = [int(params["means"].shape[0])]
    for key in sorted(params):
        bits = params[key].detach().float().contiguous().reshape(-1).view(torch.int32)
        total = torch.zeros((), dtype=torch.int64, device=bits.device)
        for start in range(0, bits.numel(), CHECKSUM_CHUNK):  # bounded int64 temporaries
            chunk = bits[start : start + CHECKSUM_CHUNK].to(torch.int64)
            weights = torch.arange(start + 1, start + 1 + chunk.numel(), dtype=torch.int64, device=bits.device)
            total += (chunk * weights).sum() + chunk.sum()
        out.append(int(total))
    return out


def backend_for(device: str) -> str:
    """The process-group backend for the trainer's device: NCCL on CUDA, gloo on CPUs."""
    return "nccl" if device == "cuda" else "gloo"


def init_from_env(device: str, timeout_s: float = DEFAULT_TIMEOUT_S) -> Dist:
    """Join the process group described by torchrun's environment variables (see the
    module docstring), or return a single-process `Dist` when there are none.

    ``device`` is the trainer's backend ("cpu" or "cuda"); with CUDA each rank uses the
    GPU of its local rank."""
    if not launched_by_torchrun():
        return Dist(timeout_s=timeout_s)
    import torch.distributed as dist

    try:
        rank, world = int(os.environ["RANK"]), int(os.environ["WORLD_SIZE"])
        local_rank = int(os.environ.get("LOCAL_RANK", rank))
        local_world = int(os.environ.get("LOCAL_WORLD_SIZE", world))
    except ValueError as exc:
        raise DistributedError(f"torchrun environment: {exc}") from None
    if not 0 <= rank < world:
        raise DistributedError(f"torchrun environment: RANK {rank} is outside WORLD_SIZE {world}")
    backend = backend_for(device)
    if backend == "gloo" and not dist.is_gloo_available():
        raise DistributedError("this torch build has no gloo backend for distributed CPU training")
    kwargs: dict[str, Any] = {}
    if backend == "nccl":
        if not dist.is_nccl_available():
            raise DistributedError("this torch build has no NCCL backend for distributed GPU training")
        if local_rank >= torch.cuda.device_count():
            raise DistributedError(
                f"local rank {local_rank} has no GPU (this machine shows {torch.cuda.device_count()}); "
                "start at most one rank per GPU"
            )
        torch.cuda.set_device(local_rank)
        kwargs["device_id"] = torch.device("cuda", local_rank)
        # NCCL reports a timed-out collective from its watchdog, which then ends the process.
        os.environ.setdefault("TORCH_NCCL_ASYNC_ERROR_HANDLING", "1")
    ctx = Dist(rank=rank, world_size=world, local_rank=local_rank, local_world_size=local_world, timeout_s=timeout_s)
    try:
        dist.init_process_group(backend=backend, timeout=datetime.timedelta(seconds=timeout_s), **kwargs)
    except (RuntimeError, ValueError) as exc:
        detail = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DistributedError(f"rank {rank}: cannot join the process group ({backend}): {detail}") from exc
    ctx.backend = backend
    ctx.install_stop_handler()
    log.info("rank %d of %d (local %d of %d), backend %s", rank, world, local_rank, local_world, backend)
    return ctx


def set_threads(ctx: Dist, device: str, threads: int | None) -> int:
    """OpenMP/intra-op threads of this process: ``threads`` when given; on the CPU backend
    with several ranks on this machine, cores / local ranks (torchrun's default of one
    thread per rank is overridden); else torch's default. Returns the count in use."""
    if threads is not None:
        if threads < 1:
            raise PromptGSError(f"--threads must be at least 1, got {threads}")
        torch.set_num_threads(threads)
    elif device == "cpu" and ctx.local_world_size > 1:
        torch.set_num_threads(threads_per_rank(ctx.local_world_size))
    return torch.get_num_threads()


# -- `promptgs train --nproc N` -------------------------------------------------------------


def strip_option(argv: Sequence[str], name: str) -> list[str]:
    """``argv`` without ``name VALUE`` / ``name=VALUE``."""
    out, skip = [], False
    for arg in argv:
        if skip:
            skip = False
            continue
        if arg == name:
            skip = True
            continue
        if arg.startswith(name + "="):
            continue
        out.append(arg)
    return out


_FAILURE_RANK = re.compile(r"^\s*rank\s*:\s*(\d+)")
_FAILURE_EXIT = re.compile(r"^\s*exitcode\s*:\s*(-?\d+)(?:.*\((SIG\w+)\))?")


class _RankFailure(NamedTuple):
    """One block of torchrun's failure report."""

    rank: int
    exit_code: int
    signal: str | None  # 'SIGKILL', or None for a normal exit code
    root_cause: bool


def _signal_name(exit_code: int) -> str | None:
    """'SIGKILL' for a process's exit code -9; None for a normal exit code."""
    if exit_code >= 0:
        return None
    try:
        return signal.Signals(-exit_code).name
    except ValueError:
        return f"signal {-exit_code}"


def describe_failure(torchrun_output: Sequence[str]) -> str | None:
    """'rank R was killed by SIG…' for a rank killed by a signal, else 'rank R exited with
    code C' for the root cause, from the failure report torchrun prints when a rank fails.
    A killed rank comes first even when listed among the other failures: on a loaded
    machine torchrun may see the survivor's error (a lost peer) before the kill."""
    failures: list[_RankFailure] = []
    rank: int | None = None
    in_report = in_root = False  # past the report's "Failures:" / "Root Cause" headers
    for line in torchrun_output:
        if line.strip() == "Failures:":
            in_report = True
            continue
        if "Root Cause" in line:
            in_report = in_root = True
            continue
        if not in_report:
            continue
        m = _FAILURE_RANK.match(line)
        if m:
            rank = int(m.group(1))
            continue
        m = _FAILURE_EXIT.match(line)
        if m and rank is not None:
            code = int(m.group(1))
            # Older torchruns print no signal name beside the code: -N is signal N.
            failures.append(_RankFailure(rank, code, m.group(2) or _signal_name(code), in_root))
            rank = None
    killed = sorted((f for f in failures if f.signal), key=lambda f: not f.root_cause)  # the root cause first
    chosen = (killed or [f for f in failures if f.root_cause] or [None])[0]
    if chosen is None:
        return None
    rank, code, sig = chosen.rank, chosen.exit_code, chosen.signal
    how = f"was killed by {sig}" if sig else f"exited with code {code}"
    return f"rank {rank} {how}"


def launch(nproc: int, train_argv: Sequence[str], out: str | None, threads: int | None = None) -> int:
    """Run ``promptgs train`` with ``train_argv`` as ``nproc`` ranks on this machine
    (``python -m torch.distributed.run --standalone``) and return the exit code. Each
    rank gets cores / nproc OpenMP threads unless ``threads`` is given. Standard output
    (the event stream) passes through untouched; standard error too, and when a rank
    failed it ends with one ``promptgs: error:`` line naming it."""
    if nproc < 1:
        raise PromptGSError(f"--nproc must be at least 1, got {nproc}")
    env = dict(os.environ)
    env["OMP_NUM_THREADS"] = str(threads or threads_per_rank(nproc))
    command = [
        sys.executable, "-m", "torch.distributed.run", "--standalone", f"--nproc-per-node={nproc}",
        "-m", "promptgs_engine", "train", *train_argv,
    ]
    proc = subprocess.Popen(command, env=env, stderr=subprocess.PIPE, text=True, errors="replace")
    # Cancel (SIGINT, from the add-on or Ctrl-C) and SIGTERM go on to torchrun, which
    # passes them to the ranks; rank 0 then keeps its last checkpoint and reports.
    previous_term = signal.signal(signal.SIGTERM, lambda signum, frame: proc.send_signal(signal.SIGTERM))
    lines: list[str] = []
    assert proc.stderr is not None
    try:
        for line in proc.stderr:
            sys.stderr.write(line)
            lines.append(line)
            del lines[:-200]
        code = proc.wait()
    except KeyboardInterrupt:
        proc.send_signal(signal.SIGINT)
        proc.wait()
        raise
    finally:
        signal.signal(signal.SIGTERM, previous_term)
    if code == 0:
        return 0
    print(f"promptgs: error: {failure_line(lines, code, out)}", file=sys.stderr, flush=True)
    return 2


def failure_line(torchrun_output: Sequence[str], code: int, out: str | None) -> str:
    """The one line that ends a failed distributed run: the rank killed by a signal, else
    the first error a rank reported (bad input gives the same one on every rank), else
    torchrun's exit code."""
    kept = f"; the last checkpoint is kept in {out}" if out else ""
    cause = describe_failure(torchrun_output)
    if cause and "killed" in cause:
        return f"distributed training failed: {cause}, and the other ranks were stopped{kept}"
    prefix = "promptgs: error:"
    reported = [line.strip()[len(prefix) :].strip() for line in torchrun_output if line.strip().startswith(prefix)]
    if reported:
        return reported[0]
    reason = cause or f"torch.distributed.run exited with code {code}"
    return f"distributed training failed: {reason}{kept}"
