"""The engine's lifeline (promptgs_engine/lifeline.py): a process started with
PROMPTGS_LIFELINE=stdin stops when the pipe on its stdin closes (its client is gone)."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def _watch_script(tmp_path: Path, ignore_interrupt: bool) -> Path:
    """A process that starts the engine's lifeline and reports how it ended."""
    script = tmp_path / "watched.py"
    script.write_text(textwrap.dedent(f"""
        import sys, time
        sys.path.insert(0, {str(REPO)!r})
        from promptgs_engine.lifeline import watch_from_env
        assert watch_from_env()
        print("watching", flush=True)
        while True:
            try:
                time.sleep(0.05)
            except KeyboardInterrupt:
                print("interrupted", flush=True)
                if not {ignore_interrupt}:
                    sys.exit(130)
    """))
    return script


@pytest.mark.parametrize("ignore_interrupt", [False, True], ids=["stops-cleanly", "stuck-main-thread"])
def test_the_lifeline_stops_a_process_whose_client_is_gone(tmp_path, ignore_interrupt):
    """PROMPTGS_LIFELINE=stdin: the end of stdin is a KeyboardInterrupt; a main thread that
    does not end on it is ended GRACE_S seconds later."""
    from promptgs_engine import lifeline

    proc = subprocess.Popen([sys.executable, str(_watch_script(tmp_path, ignore_interrupt))], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True, env=dict(os.environ, PROMPTGS_LIFELINE="stdin"))
    assert proc.stdout.readline().strip() == "watching"
    start = time.time()
    proc.stdin.close()  # what the client's death does
    code = proc.wait(timeout=lifeline.GRACE_S + 10)
    seconds = time.time() - start
    assert "interrupted" in proc.stdout.read()
    assert code == 130
    assert seconds < (lifeline.GRACE_S + 2 if ignore_interrupt else 2), seconds
    assert not lifeline.watch_from_env({})  # off unless asked for


@pytest.mark.slow
def test_a_training_whose_client_is_gone_stops_within_seconds(toy, tmp_path):
    """``promptgs train --events`` with the lifeline: the pipe closes mid-run, the run ends
    as a cancel does (an error event, exit code 130) within the grace time."""
    from promptgs_engine import lifeline

    out, log = tmp_path / "run", tmp_path / "stderr.log"
    proc = subprocess.Popen([sys.executable, "-m", "promptgs_engine", "train", str(toy), "--out", str(out), "--events",
                             "--iterations", "100000", "--backend", "cpu"],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=open(log, "w"), text=True,
                            env=dict(os.environ, PROMPTGS_LIFELINE="stdin", OMP_NUM_THREADS="1"))
    events = []
    for line in proc.stdout:
        events.append(json.loads(line))
        if events[-1]["event"] == "progress":
            break
    start = time.time()
    proc.stdin.close()
    code = proc.wait(timeout=60)
    seconds = time.time() - start
    events += [json.loads(line) for line in proc.stdout.read().splitlines() if line.startswith("{")]
    assert code == 130 and seconds < lifeline.GRACE_S + 1, (code, seconds)
    assert events[-1]["event"] == "error", events[-1]
    assert "the program that started this run is gone" in log.read_text()
