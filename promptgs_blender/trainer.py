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


LIFELINE_ENV = "PROMPTGS_LIFELINE"  # promptgs_engine/lifeline.py: stop when our end of stdin closes


class TrainerRun:
    """One engine subprocess whose stdout is read into :attr:`events` by a thread.

    Its standard input is a pipe this process holds and never writes (the engine's
    lifeline, ``PROMPTGS_LIFELINE=stdin``): when this process exits, however it ends,
    the pipe closes and every process of the run stops within seconds. On POSIX the
    trainer leads a new process group (``train --nproc``'s launcher and torchrun are in
    it; torchrun's ranks make their own): :meth:`cancel` ends all of them.
    """

    def __init__(self, argv: list[str], log_path: Path, out: Path | None = None, append_log: bool = False):
        self.argv = list(argv)
        self.log_path = Path(log_path)
        self.out = out  # the folder the job writes (informational)
        self.append_log = append_log  # a resumed run adds to its log
        self.events: queue.Queue[dict] = queue.Queue()
        self.process: subprocess.Popen | None = None
        self.cancel_requested = False
        self.started = 0.0
        self._thread: threading.Thread | None = None
        self._stderr = None

    def start(self) -> None:
        """Start the process; raises :class:`TrainerError` with a clear message."""
        problem = check_python(self.argv[0])
        if problem:
            raise TrainerError(problem)
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._stderr = open(self.log_path, "ab" if self.append_log else "wb")
        env = dict(os.environ, PYTHONUNBUFFERED="1", **{LIFELINE_ENV: "stdin"})
        kwargs = {}
        if os.name == "posix":
            kwargs["start_new_session"] = True  # its own process group, which cancel ends
        try:
            self.process = subprocess.Popen(self.argv, stdout=subprocess.PIPE, stderr=self._stderr,
                                            stdin=subprocess.PIPE, env=env, **kwargs)
        except OSError as exc:
            self._stderr.close()
            raise TrainerError(f"Cannot start the trainer {self.argv[0]}: {exc.strerror or exc}") from None
        self.started = time.time()
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
        self._release_lifeline()
        if self._stderr:
            self._stderr.close()
        self.events.put({"event": "exit", "returncode": returncode, "time": time.time(),
                         "stderr_tail": self.stderr_tail()})

    def _release_lifeline(self) -> None:
        """Close our end of the trainer's stdin: every process of the run sees end-of-file."""
        pipe = self.process.stdin if self.process is not None else None
        if pipe is not None and not pipe.closed:
            try:
                pipe.close()
            except OSError:
                pass

    def stderr_tail(self, lines: int = 8) -> list[str]:
        """The last non-empty lines the process wrote to stderr."""
        try:
            text = self.log_path.read_bytes()[-16384:].decode("utf-8", "replace")
        except OSError:
            return []
        return [ln for ln in text.replace("\r", "\n").splitlines() if ln.strip()][-lines:]

    def last_line(self) -> str:
        """The newest line of its log (stderr), for the panel."""
        tail = self.stderr_tail(1)
        return tail[-1].strip()[:300] if tail else ""

    @property
    def pid(self) -> int | None:
        return self.process.pid if self.process is not None else None

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

    def processes(self) -> list[tuple[int, str]]:
        """The trainer and every process below it (launcher, torchrun, ranks), as
        (pid, start time) pairs (the start time tells a reused pid apart)."""
        if not self.running:
            return []
        return [(self.process.pid, process_start(self.process.pid))] + descendants(self.process.pid)

    def cancel(self, timeout: float = 20.0, block: bool = True) -> None:
        """Stop every process of the run: SIGINT to its process group and the end of its
        lifeline (the trainer keeps its last checkpoint and snapshot), then, after
        ``timeout`` seconds, SIGTERM and 5 s later SIGKILL to whatever is left.

        With ``block=False`` the waiting runs in a thread so the UI does not wait.
        """
        self.cancel_requested = True
        proc = self.process
        if proc is None or proc.poll() is not None:
            return
        tree = self.processes()  # before anyone exits: ranks are re-parented when torchrun goes
        if not block:
            threading.Thread(target=self._stop, args=(tree, timeout), daemon=True).start()
            return
        self._stop(tree, timeout)

    def _stop(self, tree: list[tuple[int, str]], timeout: float) -> None:
        proc = self.process
        assert proc is not None
        self._release_lifeline()
        if os.name == "posix":
            _signal_group(proc.pid, signal.SIGINT)
        else:
            proc.terminate()
        for sig, wait in ((None, timeout), (signal.SIGTERM, 5.0), (getattr(signal, "SIGKILL", None), 5.0)):
            if sig is not None:
                if os.name == "posix":
                    _signal_group(proc.pid, sig)
                elif proc.poll() is None:
                    proc.kill()
                for pid, start in tree:
                    if alive(pid, start):
                        _signal(pid, sig)
            if _wait_all(proc, tree, wait):
                return

    def wait(self, timeout: float | None = None) -> bool:
        """Wait until the stream has ended; True when it did."""
        if self._thread is not None:
            self._thread.join(timeout)
        return self.finished


# --- the processes of a run ------------------------------------------------------------

def _proc_stat(pid: int) -> list[str] | None:
    """Fields of /proc/PID/stat after the command name (field 3, the state, first), or None."""
    try:
        text = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    return text[text.rindex(")") + 2:].split()


def process_start(pid: int) -> str:
    """The process's start time (Linux: clock ticks since boot), '' where unknown."""
    fields = _proc_stat(pid)
    return fields[19] if fields and len(fields) > 19 else ""


def _parents() -> dict[int, int]:
    """pid → parent pid of every process: /proc, else ``ps`` (macOS)."""
    found: dict[int, int] = {}
    if Path("/proc/self/stat").exists():
        for entry in Path("/proc").iterdir():
            if entry.name.isdigit():
                fields = _proc_stat(int(entry.name))
                if fields and len(fields) > 1:
                    found[int(entry.name)] = int(fields[1])
        return found
    try:
        out = subprocess.run(["ps", "-A", "-o", "pid=", "-o", "ppid="], capture_output=True, text=True,
                             timeout=10, stdin=subprocess.DEVNULL).stdout
    except (OSError, subprocess.TimeoutExpired):
        return found
    for line in out.splitlines():
        parts = line.split()
        if len(parts) == 2 and parts[0].isdigit() and parts[1].isdigit():
            found[int(parts[0])] = int(parts[1])
    return found


def descendants(pid: int) -> list[tuple[int, str]]:
    """Every process below ``pid`` (children, their children, ...) as (pid, start time)."""
    children: dict[int, list[int]] = {}
    for child, parent in _parents().items():
        children.setdefault(parent, []).append(child)
    out, todo = [], list(children.get(pid, []))
    while todo:
        child = todo.pop()
        out.append((child, process_start(child)))
        todo += children.get(child, [])
    return out


def alive(pid: int, start: str = "") -> bool:
    """Whether the process runs (a zombie does not; a pid reused since ``start`` does not count)."""
    fields = _proc_stat(pid)
    if fields is not None:
        return fields[0] != "Z" and (not start or len(fields) <= 19 or fields[19] == start)
    if Path("/proc/self/stat").exists():
        return False
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:
        return True
    return True


def _signal(pid: int, sig) -> None:
    try:
        os.kill(pid, sig)
    except OSError:
        pass


def _signal_group(pgid: int, sig) -> None:
    try:
        os.killpg(pgid, sig)
    except OSError:
        pass


def _wait_all(proc: subprocess.Popen, tree: list[tuple[int, str]], timeout: float) -> bool:
    """Wait up to ``timeout`` s for the trainer and the processes of ``tree`` to end."""
    deadline = time.time() + timeout
    while True:
        if proc.poll() is not None and not any(alive(pid, start) for pid, start in tree):
            return True
        if time.time() >= deadline:
            return False
        time.sleep(0.05)


class BackgroundCall:
    """``fn(*args)`` in a daemon thread, so the UI does not wait for it (*Find*, *Test*);
    the main thread looks at :attr:`done` and takes :attr:`result` or :attr:`error`."""

    def __init__(self, fn, *args):
        self.result = None
        self.error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, args=(fn, args), name="promptgs-background", daemon=True)
        self._thread.start()

    def _run(self, fn, args) -> None:
        try:
            self.result = fn(*args)
        except Exception as exc:  # handed to the main thread
            self.error = exc

    @property
    def done(self) -> bool:
        return not self._thread.is_alive()

    def wait(self, timeout: float | None = None) -> bool:
        self._thread.join(timeout)
        return self.done


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


def probe_summary(info: dict) -> str:
    """'promptgs_engine 0.1.0 (torch 2.13.0+cpu), backends: cpu' from :func:`probe`'s answer."""
    backends = ", ".join(info.get("backends") or []) or "none"
    return (f"promptgs_engine {info.get('version')} (torch {info.get('torch', '?')}), backends: {backends}"
            + (f" ({info['gpu']})" if info.get("gpu") else ""))


def folder_state(folder: Path) -> dict:
    """What a run folder says of its run when no trainer follows it (a file reopened after
    Blender quit): its result, or a checkpoint to resume from, and its newest snapshot."""
    if not folder.is_dir():
        return {"status": "MISSING", "message": f"{folder}: run folder not found"}
    snapshots = sorted((folder / "snapshots").glob("step_*.npz"))
    state: dict = {"last_snapshot": str(snapshots[-1]) if snapshots else "", "error_lines": ""}
    if snapshots:
        digits = snapshots[-1].stem.split("_")[-1]
        state["snapshot_step"] = int(digits) if digits.isdigit() else 0
    if (folder / "point_cloud.ply").is_file():
        try:
            metrics = json.loads((folder / "metrics.json").read_text())
        except (OSError, ValueError):
            metrics = {}
        summary = metrics_summary(metrics) if isinstance(metrics, dict) else ""
        state.update(status="DONE", result_ply=str(folder / "point_cloud.ply"), progress=1.0,
                     message="Done" + (f": {summary}" if summary else ""))
    elif (folder / "ckpt.pt").is_file():
        state.update(status="INTERRUPTED", message="Stopped before its end: Resume continues from its last checkpoint")
    else:
        state.update(status="ERROR", message="Stopped before its first checkpoint: train it again")
    return state


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


# --- Set Up Trainer: a virtual environment with torch and the engine ---------------------
#
# Blender runs ``BASE_PYTHON trainer.py setup --venv DIR --source SRC ...`` (this file as
# a script: it needs nothing but the standard library) as a background job. It prints the
# same kind of JSON-lines events as the engine (``setup_stage``, ``setup_done``, ``error``)
# and passes pip's output on as plain lines, which the job reader turns into ``output``
# events for the panel.

TORCH = "torch==2.13.0"
CPU_INDEX = "https://download.pytorch.org/whl/cpu"
COMPILERS = ("c++", "g++", "clang++")
NO_COMPILER = ("No C++ compiler found (looked for $CXX, then {names} on PATH): the engine compiles its CPU "
               "rasterizer when it installs. Install one (Debian/Ubuntu: sudo apt install build-essential; "
               "Fedora: sudo dnf install gcc-c++; macOS: xcode-select --install and brew install libomp), "
               "then press Set Up Trainer again")


def venv_python(venv: Path) -> Path:
    """The interpreter of a virtual environment."""
    return venv / ("Scripts/python.exe" if os.name == "nt" else "bin/python")


def find_compiler(environ=os.environ) -> str | None:
    """The C++ compiler a source build would use: ``$CXX``, else c++ / g++ / clang++ on PATH."""
    named = environ.get("CXX", "").split()
    for name in ([named[0]] if named else []) + list(COMPILERS):
        found = shutil.which(name, path=environ.get("PATH"))
        if found:
            return found
    return None


def check_source(source: str) -> str:
    """A problem with the engine source (a checkout with pyproject.toml, or a promptgs wheel), or ''."""
    if not source:
        return "Choose the engine source: a PromptGS checkout (the folder with pyproject.toml) or a promptgs wheel"
    path = Path(source)
    if path.is_dir():
        return "" if (path / "pyproject.toml").is_file() else f"{path}: no pyproject.toml (not a PromptGS checkout)"
    if path.is_file():
        return "" if path.suffix == ".whl" and path.name.startswith("promptgs-") else f"{path}: not a promptgs wheel"
    return f"{source}: not found"


def setup_stages(venv: Path, source: str, torch_index: str = "") -> list[tuple[str, list[str]]]:
    """(name, argv) of each step that makes the trainer environment, run in order."""
    python = str(venv_python(venv))
    pip = [python, "-m", "pip", "install", "--progress-bar", "off"]
    torch_extra = ["--extra-index-url", torch_index] if torch_index else []
    return [
        ("virtual environment", [sys.executable, "-m", "venv", str(venv)]),
        ("build tools", pip + ["setuptools>=64", "wheel"]),
        ("torch", pip + [TORCH] + torch_extra),
        # Compiled against the torch just installed, so without build isolation.
        ("PromptGS engine (compiles the CPU rasterizer)", pip + ["--no-build-isolation", source]),
    ]


def _emit(**event) -> None:
    event["time"] = time.time()
    print(json.dumps(event), flush=True)


def run_setup(venv: Path, source: str, torch_index: str = "", environ=os.environ) -> int:
    """Make the environment (the ``setup`` command of this file); 0 when it works."""
    problem = check_source(source)
    if not problem and Path(source).is_dir() and not find_compiler(environ):
        problem = NO_COMPILER.format(names=", ".join(COMPILERS))
    if not problem and sys.version_info < (3, 10):
        problem = f"{sys.executable} is Python {sys.version.split()[0]}: the engine needs 3.10 or newer"
    if not problem and Path(source).is_dir():
        import sysconfig

        headers = Path(sysconfig.get_paths()["include"]) / "Python.h"
        if not headers.is_file():
            problem = (f"{sys.executable} has no C headers ({headers} is missing), which the build needs "
                       "(Debian/Ubuntu: sudo apt install python3-dev); or choose another base Python")
    if problem:
        _emit(event="error", message=problem)
        return 2
    stages = setup_stages(venv, source, torch_index)
    for index, (name, argv) in enumerate(stages, 1):
        _emit(event="setup_stage", index=index, n_stages=len(stages) + 1, stage=name, command=" ".join(argv))
        proc = subprocess.Popen(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                env=dict(environ, PYTHONUNBUFFERED="1"))
        assert proc.stdout is not None
        last = ""
        for raw in proc.stdout:
            line = raw.decode("utf-8", "replace").rstrip()
            if line.strip():
                last = line.strip()
                print(line, flush=True)
                print(line, file=sys.stderr, flush=True)  # the job's log
        if proc.wait() != 0:
            _emit(event="error", message=f"{name} failed (exit code {proc.returncode}): {last or ' '.join(argv)}"[:400])
            return 2
    python = str(venv_python(venv))
    _emit(event="setup_stage", index=len(stages) + 1, n_stages=len(stages) + 1, stage="check", command=python)
    info = probe(python)
    if "error" in info or "cpu" not in (info.get("backends") or []):
        detail = info.get("error") or info.get("cpu_error") or info.get("torch_error") or "no usable backend"
        _emit(event="error", message=f"installed, but {python} cannot train: {detail}"[:400])
        return 2
    _emit(event="setup_done", python=python, probe=info)
    return 0


def setup_command(base_python: str, venv: Path, source: str, torch_index: str = "") -> list[str]:
    """argv of the set-up job: this file run by ``base_python`` (it makes the environment from it)."""
    argv = [base_python, str(Path(__file__).resolve()), "setup", "--venv", str(venv), "--source", source]
    return argv + (["--torch-index", torch_index] if torch_index else [])


def base_python_candidates() -> list[str]:
    """Interpreters to make the trainer environment from: python3 / python on PATH, then this one."""
    found = [shutil.which(name) for name in ("python3", "python")] + [sys.executable]
    return [p for p in dict.fromkeys(found) if p]


def _main(argv: list[str]) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="trainer.py", description="Make a PromptGS trainer environment")
    sub = parser.add_subparsers(dest="command", required=True)
    setup = sub.add_parser("setup")
    setup.add_argument("--venv", type=Path, required=True)
    setup.add_argument("--source", required=True)
    setup.add_argument("--torch-index", default="")
    args = parser.parse_args(argv)
    return run_setup(args.venv, args.source, args.torch_index)


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
