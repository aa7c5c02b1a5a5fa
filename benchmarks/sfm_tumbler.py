"""Time and peak memory of `promptgs sfm` on the tumbler photos at two sizes.

Each run is a fresh process (``python -m promptgs_engine.cli sfm``, no resume) whose peak
resident memory and CPU seconds are read from ``wait4`` on the finished child; the sizes are run
alternately, ``--repeats`` times each, and medians are reported. Each run's cameras are
also compared with the given model (Umeyama similarity on the camera centres, errors as
fractions of the scene's extent, ``promptgs_engine.sfm.compare``).

    python benchmarks/sfm_tumbler.py --scene ../shared/data/tumbler --out out/sfm --repeats 3

Writes ``sfm_tumbler.json`` and ``sfm_tumbler.png`` (per-stage seconds, median run) into --out.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt

from promptgs_engine.sfm.compare import camera_centres, compare_centres

SIZES = {"images_4": "200x150", "images": "800x600"}


def run_once(images: Path, out: Path) -> dict:
    """One `promptgs sfm` process; its summary, wall seconds and peak RSS (MiB)."""
    if out.exists():
        shutil.rmtree(out)
    # Accept a partial model here: the benchmark reports how many photos register.
    cmd = [sys.executable, "-m", "promptgs_engine.cli", "sfm", str(images), "--out", str(out), "--quiet", "--min-registered", "0.3"]
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _, _, ru = os.wait4(proc.pid, 0)
    wall = time.perf_counter() - start
    stderr = proc.stderr.read()
    summary = json.loads((out / "sfm_summary.json").read_text()) if (out / "sfm_summary.json").is_file() else {"status": "error", "error": stderr.strip().splitlines()[-1:]}
    # CPU seconds (user + system, all threads) tell the work done even on a shared machine.
    return {"wall_s": wall, "cpu_s": ru.ru_utime + ru.ru_stime, "peak_rss_mib": ru.ru_maxrss / 1024.0, "summary": summary}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", type=Path, default=Path(__file__).resolve().parents[2] / "shared" / "data" / "tumbler")
    ap.add_argument("--out", type=Path, default=Path("out/sfm"))
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    args = ap.parse_args()
    reference = camera_centres(args.scene / "sparse" / "0")
    work = Path(tempfile.mkdtemp(prefix="sfm_bench_"))
    runs: dict[str, list[dict]] = {s: [] for s in args.sizes}
    load_before = os.getloadavg()[0]
    try:
        for r in range(args.repeats):
            for size in args.sizes:  # alternate the sizes so load changes hit both
                res = run_once(args.scene / size, work / size)
                s = res["summary"]
                if s.get("status") == "ok":
                    cmp = compare_centres(camera_centres(work / size / "sparse" / "0"), reference)
                    res["alignment"] = {k: cmp[k] for k in ("common", "max_error", "median_error")}
                runs[size].append(res)
                write_results(args, runs, load_before)  # after every run: an interrupted benchmark keeps what it measured
                print(f"{size} run {r + 1}: {res['wall_s']:.1f} s ({res['cpu_s']:.1f} CPU s), {res['peak_rss_mib']:.0f} MiB, "
                      f"{s.get('images_registered')}/{s.get('images_given')} registered, alignment {res.get('alignment')}", flush=True)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    result = write_results(args, runs, load_before)
    plot(args, result)
    print(json.dumps({s: {k: v for k, v in d.items() if k != "runs"} for s, d in result["sizes"].items()}, indent=2))


def write_results(args: argparse.Namespace, runs: dict[str, list[dict]], load_before: float) -> dict:
    """Medians over the runs so far, written to sfm_tumbler.json."""
    result = {
        "scene": str(args.scene),
        "repeats": args.repeats,
        "cpu_count": os.cpu_count(),
        "load_avg_before": load_before,
        "load_avg_after": os.getloadavg()[0],
        "sizes": {},
    }
    for size, rs in runs.items():
        if not rs:
            continue
        ok = [x for x in rs if x["summary"].get("status") == "ok"] or rs
        med = sorted(ok, key=lambda x: x["wall_s"])[len(ok) // 2]
        result["sizes"][size] = {
            "resolution": SIZES[size],
            "median_wall_s": statistics.median(x["wall_s"] for x in rs),
            "median_cpu_s": statistics.median(x["cpu_s"] for x in rs),
            "median_peak_rss_mib": statistics.median(x["peak_rss_mib"] for x in rs),
            "registered": [x["summary"].get("images_registered") for x in rs],
            "mapper": [x["summary"].get("mapper") for x in rs],
            "mappers_tried": [x["summary"].get("mappers_tried") for x in rs],
            "given": rs[0]["summary"].get("images_given"),
            "points": [x["summary"].get("points") for x in rs],
            "mean_reprojection_error_px": [x["summary"].get("mean_reprojection_error_px") for x in rs],
            "alignment_median_error": [x.get("alignment", {}).get("median_error") for x in rs],
            "alignment_max_error": [x.get("alignment", {}).get("max_error") for x in rs],
            "median_run_stage_seconds": med["summary"].get("stage_seconds"),
            "runs": rs,
        }
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "sfm_tumbler.json").write_text(json.dumps(result, indent=2))
    return result


def plot(args: argparse.Namespace, result: dict) -> None:
    runs = result["sizes"]
    load_before = result["load_avg_before"]
    fig, ax = plt.subplots(figsize=(6, 3))
    stages = ["features", "matching", "mapping", "undistortion"]
    left = [0.0] * len(runs)
    labels = [f"{s} ({SIZES[s]})" for s in runs]
    for stage in stages:
        vals = [(result["sizes"][s]["median_run_stage_seconds"] or {}).get(stage, 0.0) for s in runs]
        ax.barh(labels, vals, left=left, label=stage)
        left = [a + b for a, b in zip(left, vals)]
    ax.set_xlabel("seconds (median run)")
    ax.set_title(f"promptgs sfm on tumbler, {os.cpu_count()} cores (load {load_before:.1f})")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(args.out / "sfm_tumbler.png", dpi=120)


if __name__ == "__main__":
    main()
