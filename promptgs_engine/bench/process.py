"""One trainer process, as the benchmark tools run it, and how it ended.

`bench` (one process per grid cell) and `stability` (one per case) both start
``python -m promptgs_engine train --job …`` and need the same things back: its output in
a log file, its wall time, its peak memory (``wait4`` of that process), a time limit,
and a verdict: a finished run with finite metrics, a clear one-line error, non-finite
metrics, or a crash.
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Sequence

# Outcomes of one process.
OK = "ok"  # finished, finite metrics
CLEAR_ERROR = "clear error"  # exit 2 with a one-line "promptgs: error: ..." message
NAN = "nan"  # finished, but a metric is not finite
CRASH = "crash"  # anything else: traceback, signal, timeout, missing metrics

ERROR_PREFIX = "promptgs: error:"
POLL_SECONDS = 0.2  # how often a process with a time limit is checked


@dataclass
class ProcessResult:
    returncode: int | None  # None: stopped at the time limit
    seconds: float  # wall clock, start to end
    peak_rss_mb: float | None  # peak resident memory of the process
    output: str  # stdout and stderr together (also in the log file, when one was given)


def run_logged(command: Sequence[str], log_path: Path | None = None, timeout: float | None = None) -> ProcessResult:
    """Run ``command`` in its own process group with stdout and stderr in ``log_path``
    (a temporary file when None). Past ``timeout`` seconds the whole group is killed.
    Ctrl-C stops the process and is raised again."""
    t0 = time.perf_counter()
    if log_path is None:
        with tempfile.TemporaryDirectory() as tmp:
            result = run_logged(command, Path(tmp) / "output.log", timeout)
        return result
    log_path = Path(log_path)
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with log_path.open("w") as log:
        proc = subprocess.Popen(list(command), stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
        code: int | None
        try:
            if timeout is None:
                _, status, usage = os.wait4(proc.pid, 0)
                code = os.waitstatus_to_exitcode(status)
            else:
                while True:
                    pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
                    if pid:
                        code = os.waitstatus_to_exitcode(status)
                        break
                    if time.perf_counter() - t0 > timeout:
                        os.killpg(proc.pid, signal.SIGKILL)  # the trainer and anything it started
                        _, status, usage = os.wait4(proc.pid, 0)
                        code = None
                        break
                    time.sleep(POLL_SECONDS)
        except KeyboardInterrupt:
            os.killpg(proc.pid, signal.SIGTERM)
            proc.wait()
            raise
    proc.returncode = os.waitstatus_to_exitcode(status)  # reaped above; keeps Popen from waiting again
    seconds = time.perf_counter() - t0
    output = log_path.read_text(errors="replace")
    return ProcessResult(code, seconds, usage.ru_maxrss / 1024.0, output)


def is_finite(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)


def last_line(text: str) -> str:
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[-1] if lines else ""


def error_message(output: str) -> str:
    """The message of the last ``promptgs: error: …`` line, else the last line."""
    for line in reversed(output.splitlines()):
        if line.startswith(ERROR_PREFIX):
            return line[len(ERROR_PREFIX) :].strip()
    return last_line(output) or "no output"


def classify(returncode: int | None, output: str, run_dir: Path | None, timeout: float | None = None) -> dict:
    """How one training process ended: ``outcome``, ``message`` and, for ``ok`` and
    ``nan``, ``metrics`` (``metrics.json`` of ``run_dir``). ``returncode`` None means the
    process was stopped at ``timeout`` seconds."""
    if returncode is None:
        return {"outcome": CRASH, "message": f"timed out after {timeout:g} s", "metrics": None}
    if returncode == 0:
        path = Path(run_dir) / "metrics.json" if run_dir is not None else None
        if path is None or not path.is_file():
            return {"outcome": CRASH, "message": "exit 0 but no metrics.json", "metrics": None}
        try:
            metrics = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError) as exc:
            return {"outcome": CRASH, "message": f"exit 0 but metrics.json is unreadable ({exc})", "metrics": None}
        bad = [k for k in ("psnr", "ssim") if not is_finite(metrics.get(k))]
        # The mean skips non-finite views; a NaN in any single view is a NaN too.
        bad += [
            f"{k} of {row.get('image')}"
            for row in metrics.get("per_image", [])
            for k in ("psnr", "ssim")
            if isinstance(row.get(k), float) and math.isnan(row[k])
        ]
        if bad:
            return {"outcome": NAN, "message": "not finite: " + ", ".join(bad), "metrics": metrics}
        return {"outcome": OK, "message": "", "metrics": metrics}
    line = last_line(output)
    if returncode == 2:
        errors = [ln.strip() for ln in output.splitlines() if "error:" in ln]
        if errors:
            return {"outcome": CLEAR_ERROR, "message": errors[-1], "metrics": None}
    if returncode < 0:
        return {"outcome": CRASH, "message": f"killed by signal {-returncode}" + (f" ({line})" if line else ""), "metrics": None}
    return {"outcome": CRASH, "message": line or f"exit {returncode}, no output", "metrics": None}
