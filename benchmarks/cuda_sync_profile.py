"""Where our training step waits on a GPU: the host's reads of the device, by call site.

Runs the CLI's ``train`` in this process with ``Trainer.train_step`` wrapped:

- steps 200-299 and 400-499 are timed with the device drained at each end (ms per step);
- steps 300-399 run under torch's sync debug mode; every operation that makes the host
  wait for the GPU (a read of a value, a copy from ordinary host memory, a boolean-mask
  index) is counted by its call site in the engine or gsplat;
- steps 500-599 run under ``torch.profiler`` (CPU and CUDA); its tables by self CPU time
  and by CUDA time are printed. ``PROFILE_TABLES=0`` leaves the debug mode and the
  profiler off (timing only).

The run needs at least 600 steps. Writes ``OUT_JSON`` with the two timings and the counts.

    python benchmarks/cuda_sync_profile.py out.json -- train DATASET --backend cuda --iterations 700 --out RUN

Without a GPU it runs as a smoke test (no drains, no debug mode; the counts stay empty).
"""

from __future__ import annotations

import collections
import json
import os
import sys
import time
import traceback
import warnings

import torch

from promptgs_engine import train as train_module
from promptgs_engine.cli import main

TIMED = (200, 300, 400, 500, 600)
SYNC_STEPS = (300, 400)
PROFILED_STEPS = (500, 600)


def _drain() -> None:
    if torch.cuda.is_available():
        torch.cuda.synchronize()


def run(out_json: str, argv: list[str]) -> dict:
    tables = os.environ.get("PROFILE_TABLES", "1") == "1" and torch.cuda.is_available()
    sites: collections.Counter = collections.Counter()
    marks: dict[int, float] = {}
    profiler: list = []
    original = train_module.Trainer.train_step

    def count_sync_site(message, category, filename, lineno, file=None, line=None):
        if "synchroniz" not in str(message):
            return
        ours = [f for f in traceback.extract_stack()[:-1] if "promptgs_engine" in f.filename or "gsplat" in f.filename]
        sites[" <- ".join(f"{f.filename.split('/')[-1]}:{f.lineno}:{f.name}" for f in reversed(ours[-4:]))] += 1

    def step(self):
        s = self.step
        if s in TIMED:
            _drain()
            marks[s] = time.perf_counter()
        if tables and s == SYNC_STEPS[0]:
            torch.cuda.set_sync_debug_mode(1)
        if tables and s == SYNC_STEPS[1]:
            torch.cuda.set_sync_debug_mode(0)
        if tables and s == PROFILED_STEPS[0]:
            acts = [torch.profiler.ProfilerActivity.CPU, torch.profiler.ProfilerActivity.CUDA]
            profiler.append(torch.profiler.profile(activities=acts))
            profiler[0].__enter__()
        result = original(self)
        if tables and s == PROFILED_STEPS[1] - 1:
            _drain()
            profiler[0].__exit__(None, None, None)
            averages = profiler[0].key_averages()
            print(f"== by self CPU time (steps {PROFILED_STEPS[0]}-{PROFILED_STEPS[1] - 1})")
            print(averages.table(sort_by="self_cpu_time_total", row_limit=40))
            print("== by CUDA time")
            print(averages.table(sort_by="self_device_time_total", row_limit=30))
        return result

    warnings.showwarning = count_sync_site
    warnings.simplefilter("always")
    train_module.Trainer.train_step = step
    try:
        main(argv)
    finally:
        train_module.Trainer.train_step = original
        per_step = lambda a, b: (marks[b] - marks[a]) * 1000 / (b - a) if a in marks and b in marks else None  # noqa: E731
        result = {
            "ms_per_step_200_300": per_step(200, 300),
            "ms_per_step_400_500_plain": per_step(400, 500),
            "sync_sites_steps_300_399": dict(sites.most_common()),
        }
        print(json.dumps(result, indent=1))
        with open(out_json, "w") as f:
            json.dump(result, f, indent=1)
    return result


if __name__ == "__main__":
    if "--" not in sys.argv or len(sys.argv) < 4:
        sys.exit(__doc__)
    run(sys.argv[1], sys.argv[sys.argv.index("--") + 1 :])
