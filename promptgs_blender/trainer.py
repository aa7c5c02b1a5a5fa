"""Running the trainer (and other engine commands) out of process.

No bpy here: a :class:`TrainerRun` starts a subprocess, a reader thread parses its
JSON-lines event stream (docs/interfaces.md, "Trainer events") into a queue, and the
add-on drains that queue from a timer (or tests drain it directly). Non-JSON lines on
stdout arrive as ``{"event": "output", "line": ...}``; when the process ends an
``{"event": "exit", "returncode": ..., "stderr_tail": [...]}`` follows.
"""

from __future__ import annotations

import json
import os
import queue
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

# Printed by the "Test" button: engine version and the backends the trainer can use.
PROBE_SCRIPT = r"""
import json
info = {}
try:
    import promptgs_engine
    info["version"] = getattr(promptgs_engine, "__version__", "?")
except Exception as exc:
    print(json.dumps({"error": "promptgs_engine is not importable: %s" % exc}))
    raise SystemExit(0)
backends = []
try:
    import torch
    info["torch"] = torch.__version__
    try:
        import promptgs_engine._C
        backends.append("cpu")
    except Exception as exc:
        info["cpu_error"] = (str(exc).splitlines() or [type(exc).__name__])[0]
    if torch.cuda.is_available():
        backends.append("cuda")
        info["gpu"] = torch.cuda.get_device_name(0)
except Exception as exc:
    info["torch_error"] = (str(exc).splitlines() or [type(exc).__name__])[0]
info["backends"] = backends
print(json.dumps(info))
"""


class TrainerError(RuntimeError):
    """The trainer command cannot be started; the message says what to fix."""


def engine_command(python: str, *args: str) -> list[str]:
    """argv running ``promptgs ARGS`` with the given interpreter."""
    return [python, "-m", "promptgs_engine", *args]


def check_python(python: str) -> str:
    """A clear one-line problem with a trainer interpreter path, or '' when it looks usable."""
    if not python:
        return "No trainer command set: choose a Python with promptgs_engine in the add-on preferences"
    resolved = shutil.which(python) if os.path.sep not in python else python
    if not resolved or not Path(resolved).exists():
        return f"Trainer command not found: {python} (set it in Preferences > Add-ons > PromptGS)"
    if Path(resolved).is_dir() or not os.access(resolved, os.X_OK):
        return f"Trainer command is not an executable file: {python}"
    return ""


def probe(python: str, timeout: float = 120.0) -> dict:
    """Run :data:`PROBE_SCRIPT` with ``python``; returns its JSON or ``{"error": ...}``."""
    problem = check_python(python)
    if problem:
        return {"error": problem}
    try:
        done = subprocess.run([python, "-c", PROBE_SCRIPT], capture_output=True, text=True,
                              timeout=timeout, stdin=subprocess.DEVNULL)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return {"error": f"{python}: {exc}"}
    for line in reversed(done.stdout.splitlines()):
        if line.startswith("{"):
            return json.loads(line)
    tail = (done.stderr.strip().splitlines() or ["no output"])[-1]
    return {"error": f"{python} exited with {done.returncode}: {tail}"}


def find_python(candidates: list[str] | None = None) -> str:
    """The first interpreter that can import promptgs_engine, or ''.

    Looks at ``$PROMPTGS_PYTHON``, the interpreter of a ``promptgs`` script on PATH, this
    process's interpreter, then ``python3`` and ``python`` on PATH.
    """
    found = list(candidates or [])
    if os.environ.get("PROMPTGS_PYTHON"):
        found.append(os.environ["PROMPTGS_PYTHON"])
    script = shutil.which("promptgs")
    if script:
        try:
            first = Path(script).read_bytes()[:256].split(b"\n", 1)[0].decode()
            if first.startswith("#!"):
                found.append(first[2:].strip().split()[0])
        except OSError:
            pass
    found.append(sys.executable)
    found += [p for p in (shutil.which("python3"), shutil.which("python")) if p]
    seen = set()
    for python in found:
        if not python or python in seen or check_python(python):
            continue
        seen.add(python)
        try:
            ok = subprocess.run([python, "-c", "import promptgs_engine"], capture_output=True,
                                timeout=30, stdin=subprocess.DEVNULL).returncode == 0
        except (OSError, subprocess.TimeoutExpired):
            ok = False
        if ok:
            return python
    return ""


class TrainerRun:
    """One engine subprocess whose stdout is read into :attr:`events` by a thread."""

    def __init__(self, argv: list[str], log_path: Path, out: Path | None = None):
        self.argv = list(argv)
        self.log_path = Path(log_path)
        self.out = out  # the folder the job writes (informational)
        self.events: queue.Queue[dict] = queue.Queue()
        self.process: subprocess.Popen | None = None
        self.cancel_requested = False
        self._thread: threading.Thread | None = None
        self._stderr = None

    def start(self) -> None:
        """Start the process; raises :class:`TrainerError` with a clear message."""
        problem = check_python(self.argv[0])
        if problem:
            raise TrainerError(problem)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._stderr = open(self.log_path, "wb")
        env = dict(os.environ, PYTHONUNBUFFERED="1")
        kwargs = {}
        if os.name == "posix":
            kwargs["start_new_session"] = True  # Ctrl-C in Blender's terminal is ours to forward
        try:
            self.process = subprocess.Popen(self.argv, stdout=subprocess.PIPE, stderr=self._stderr,
                                            stdin=subprocess.DEVNULL, env=env, **kwargs)
        except OSError as exc:
            self._stderr.close()
            raise TrainerError(f"Cannot start the trainer {self.argv[0]}: {exc.strerror or exc}") from None
        self._thread = threading.Thread(target=self._read, name="promptgs-trainer-reader", daemon=True)
        self._thread.start()

    def _read(self) -> None:
        assert self.process is not None and self.process.stdout is not None
        for raw in self.process.stdout:
            line = raw.decode("utf-8", "replace").strip()
            if not line:
                continue
            try:
                event = json.loads(line)
                if not isinstance(event, dict) or "event" not in event:
                    raise ValueError
            except ValueError:
                event = {"event": "output", "line": line}
            self.events.put(event)
        returncode = self.process.wait()
        if self._stderr:
            self._stderr.close()
        self.events.put({"event": "exit", "returncode": returncode, "time": time.time(),
                         "stderr_tail": self.stderr_tail()})

    def stderr_tail(self, lines: int = 8) -> list[str]:
        """The last non-empty lines the process wrote to stderr."""
        try:
            text = self.log_path.read_bytes()[-16384:].decode("utf-8", "replace")
        except OSError:
            return []
        return [ln for ln in text.splitlines() if ln.strip()][-lines:]

    @property
    def running(self) -> bool:
        return self.process is not None and self.process.poll() is None

    @property
    def finished(self) -> bool:
        """True once the reader has seen the end of the stream (all events are queued)."""
        return self._thread is not None and not self._thread.is_alive()

    @property
    def done(self) -> bool:
        """True once the stream has ended and every event was taken: the job can be forgotten."""
        return self.finished and self.events.empty()

    def drain(self, limit: int = 10000) -> list[dict]:
        """Events queued since the last call, oldest first (never blocks)."""
        out = []
        while len(out) < limit:
            try:
                out.append(self.events.get_nowait())
            except queue.Empty:
                break
        return out

    def exit_event(self) -> dict | None:
        """For a job whose only news is its end: the ``exit`` event if it came (the other
        queued events are dropped), else None. Never blocks."""
        ends = [event for event in self.drain() if event.get("event") == "exit"]
        return ends[-1] if ends else None

    def cancel(self, timeout: float = 20.0, block: bool = True) -> None:
        """Ask the process to stop (SIGINT: the trainer keeps its last snapshot), then force it.

        With ``block=False`` the escalation (terminate, kill after ``timeout``) runs in a
        thread so the UI does not wait.
        """
        self.cancel_requested = True
        proc = self.process
        if proc is None or proc.poll() is not None:
            return
        if not block:
            threading.Thread(target=self.cancel, args=(timeout, True), daemon=True).start()
            return
        try:
            if os.name == "posix":
                proc.send_signal(signal.SIGINT)
            else:
                proc.terminate()
            proc.wait(timeout)
        except subprocess.TimeoutExpired:
            proc.terminate()
            try:
                proc.wait(5)
            except subprocess.TimeoutExpired:
                proc.kill()
        except OSError:
            pass

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the stream has ended; True when it did."""
        if self._thread is not None:
            self._thread.join(timeout)
        return self.finished


def start_run(argv: list[str], log_path: Path, out: Path, error: type[Exception]) -> TrainerRun:
    """Start a background engine command (render, propose, sfm); a problem starting it is
    raised as ``error``, the job's own error class, with the same message."""
    run = TrainerRun(argv, log_path, out=out)
    try:
        run.start()
    except TrainerError as exc:
        raise error(str(exc)) from None
    return run


def exit_line(event: dict, what: str) -> str:
    """The line to show for a failed job's ``exit`` event: its last stderr line, else its exit code."""
    tail = event.get("stderr_tail") or []
    return (tail[-1] if tail else f"{what} exited with code {event.get('returncode')}")[:300]


def metrics_summary(metrics: dict) -> str:
    """'PSNR 24.10 dB, SSIM 0.812, 1,234 Gaussians, 95 s' from a metrics.json object."""
    parts = []
    if isinstance(metrics.get("psnr"), (int, float)):
        parts.append(f"PSNR {metrics['psnr']:.2f} dB")
    if isinstance(metrics.get("ssim"), (int, float)):
        parts.append(f"SSIM {metrics['ssim']:.3f}")
    if isinstance(metrics.get("n_gaussians"), (int, float)):
        parts.append(f"{int(metrics['n_gaussians']):,} Gaussians")
    if isinstance(metrics.get("train_seconds"), (int, float)):
        parts.append(f"{metrics['train_seconds']:.0f} s")
    return ", ".join(parts)


def reduce_event(state, event: dict) -> None:
    """Apply one event to a progress state (any object with the RunState attributes).

    The add-on's ``RunState`` property group and the tests' plain namespaces both work.
    Snapshot files are not loaded here; the caller does that.
    """
    kind = event.get("event")
    if kind == "start":
        state.status = "RUNNING"
        state.iterations = int(event.get("iterations") or 0)
        state.n_gaussians = int(event.get("n_gaussians") or 0)
        state.backend = str(event.get("backend") or "")
        state.message = f"Training on {event.get('backend', '?')} ({event.get('strategy', '?')})"
    elif kind == "progress":
        state.step = int(event.get("step") or 0)
        state.iterations = int(event.get("iterations") or state.iterations)
        state.loss = float(event.get("loss") or 0.0)
        state.psnr = float(event.get("psnr") or 0.0)
        state.n_gaussians = int(event.get("n_gaussians") or state.n_gaussians)
        state.elapsed_s = float(event.get("elapsed_s") or 0.0)
        state.eta_s = float(event.get("eta_s") or 0.0)
        state.progress = state.step / state.iterations if state.iterations else 0.0
    elif kind == "snapshot":
        state.last_snapshot = str(event.get("path") or "")
        state.snapshot_step = int(event.get("step") or 0)
        state.n_gaussians = int(event.get("n_gaussians") or state.n_gaussians)
    elif kind == "done":
        state.status = "DONE"
        state.progress = 1.0
        state.result_ply = str(event.get("ply") or "")
        state.message = "Done" + (f": {summary}" if (summary := metrics_summary(event.get("metrics") or {})) else "")
    elif kind == "error":
        if state.cancel_requested or state.status == "CANCELLING":
            state.last_output = str(event.get("message") or "")[:400]  # the trainer saw our SIGINT
            return
        state.status = "ERROR"
        state.message = str(event.get("message") or "the trainer reported an error").splitlines()[0]
        state.log_path = str(event.get("log") or state.log_path)
    elif kind == "output":
        state.last_output = str(event.get("line", ""))[:400]
    elif kind == "exit":
        code = event.get("returncode")
        if state.status in ("RUNNING", "STARTING", "CANCELLING"):
            if state.status == "CANCELLING" or state.cancel_requested:
                state.status = "CANCELLED"
                state.message = "Cancelled" + (f" (kept the snapshot of step {state.snapshot_step})"
                                               if state.last_snapshot else "")
            elif code == 0:
                state.status = "DONE"
                state.message = state.message or "Finished"
            else:
                state.status = "ERROR"
                tail = event.get("stderr_tail") or []
                state.message = (tail[-1] if tail else f"The trainer exited with code {code}")[:300]
        tail = event.get("stderr_tail") or []
        if state.status == "ERROR" and tail:
            state.error_lines = "\n".join(line[:200] for line in tail)
