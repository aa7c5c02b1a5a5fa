"""How long the Blender add-on takes to show a snapshot of 100k and 1M Gaussians, per Blender line.

For each line of tests/blender_lines.py a worker process (that line's ``bpy``) installs
the extension zip built from this checkout into a fresh profile and times, on random
snapshot arrays (the trainer's ``.npz`` form):

- ``update``: ``results.apply_snapshot`` of an ``.npz`` file, what the add-on runs on the
  main thread for each snapshot: reading the file, the point count changes (a point cloud
  gets a new datablock), every attribute set, the display mode applied and, where
  Blender does not draw the splats itself, the colours; split into ``attributes``
  (``splat_attributes.write``) and ``rest`` (reading, conversion, display mode, colours);
- ``evaluate``: the depsgraph update after it (the display modifier: instanced splats,
  points, or nothing for Blender's own splats);

in the default display (*Draw As* Auto) and, for 1M on 4.2–5.2, with *Draw As* Splats
forced (the instancing the Auto fallback avoids). Medians of ``--repeat`` updates, each
with a different count so that every one is a full update. The machine's load average
is recorded beside them.

    python benchmarks/blender_display.py --out runs/bench/blender_display.json [--lines blender-5.3 ...]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ADDON = "bl_ext.user_default.promptgs"


def snapshot(n: int, seed: int):
    import numpy as np

    rng = np.random.default_rng(seed)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    return {"means": rng.normal(size=(n, 3)).astype(np.float32), "opacity": rng.uniform(size=n).astype(np.float32),
            "scale": rng.uniform(0.001, 0.05, size=(n, 3)).astype(np.float32),
            "rotation": q / np.linalg.norm(q, axis=1, keepdims=True),
            "color": rng.uniform(size=(n, 3)).astype(np.float32),
            "score": rng.uniform(size=n).astype(np.float32), "error": rng.uniform(size=n).astype(np.float32)}


def worker(zip_path: str, sizes: list[int], repeat: int) -> dict:
    import statistics

    import bpy
    import numpy as np

    bpy.ops.extensions.package_install_files(filepath=zip_path, repo="user_default", enable_on_install=True)
    results, splat_attributes = sys.modules[f"{ADDON}.results"], sys.modules[f"{ADDON}.splat_attributes"]
    settings = bpy.context.scene.promptgs
    out = {"blender": bpy.app.version_string, "cases": []}

    def timed(n: int, style: str) -> dict:
        settings.display_style = style
        samples = {"update": [], "attributes": [], "evaluate": []}
        for i in range(repeat):
            path = Path(tempfile.gettempdir()) / f"promptgs-bench-{os.getpid()}.npz"
            np.savez(path, **snapshot(n - i, i))  # a new count every time: a full update
            written = []
            write = splat_attributes.write

            def timed_write(*args, **kwargs):
                start = time.perf_counter()
                write(*args, **kwargs)
                written.append(time.perf_counter() - start)

            splat_attributes.write = timed_write
            try:
                start = time.perf_counter()
                obj = results.apply_snapshot(bpy.context, path)
                samples["update"].append(time.perf_counter() - start)
            finally:
                splat_attributes.write = write
                path.unlink()
            samples["attributes"].append(written[0])
            start = time.perf_counter()
            depsgraph = bpy.context.evaluated_depsgraph_get()
            depsgraph.update()
            obj.evaluated_get(depsgraph)
            samples["evaluate"].append(time.perf_counter() - start)
        medians = {key: round(statistics.median(values), 4) for key, values in samples.items()}
        medians["rest"] = round(medians["update"] - medians["attributes"], 4)
        return {"n": n, "draw_as": style, "mode": obj["promptgs_mode"], **medians,
                "samples": {key: [round(v, 4) for v in values] for key, values in samples.items()}}

    for n in sizes:
        out["cases"].append(timed(n, "AUTO"))
    if not sys.modules[f"{ADDON}.display"].native_splats_supported():
        out["cases"].append(timed(max(sizes), "SPLATS"))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("runs/bench/blender_display.json"))
    parser.add_argument("--lines", nargs="*", help="line ids (blender-4.2 ...); default: all")
    parser.add_argument("--sizes", type=int, nargs="*", default=[100_000, 1_000_000])
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--worker", nargs=2, metavar=("ZIP", "RESULT"), help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        result = worker(args.worker[0], args.sizes, args.repeat)
        Path(args.worker[1]).write_text(json.dumps(result))
        return
    sys.path[:0] = [str(REPO / "tests"), str(REPO / "tools")]
    import build_extension
    from blender_lines import LINES, line_python

    tmp = Path(tempfile.mkdtemp(prefix="blender-display-"))
    zip_path = build_extension.build(tmp / "zip")
    report = {"load_average_before": os.getloadavg(), "sizes": args.sizes, "repeat": args.repeat, "lines": {}}
    for line in LINES:
        if args.lines and line.id not in args.lines:
            continue
        home = tmp / line.id
        home.mkdir()
        result = home / "result.json"
        argv = [line_python(line), __file__, "--worker", str(zip_path), str(result), "--repeat", str(args.repeat),
                "--sizes", *map(str, args.sizes)]
        done = subprocess.run(argv, env=dict(os.environ, HOME=str(home)), capture_output=True, text=True)
        if done.returncode != 0 or not result.is_file():
            raise SystemExit(f"{line.id}: the worker failed:\n{done.stderr[-3000:]}")
        report["lines"][line.id] = json.loads(result.read_text())
        for case in report["lines"][line.id]["cases"]:
            print(f"{line.id:12} {case['n']:>9,} {case['draw_as']:6} {case['mode']:6} update {case['update']:.3f} s "
                  f"(attributes {case['attributes']:.3f}, rest {case['rest']:.3f}), evaluate {case['evaluate']:.3f} s")
    report["load_average_after"] = os.getloadavg()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=1))
    print(args.out)


if __name__ == "__main__":
    main()
