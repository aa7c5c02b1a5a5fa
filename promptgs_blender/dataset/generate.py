"""Entry point run inside Blender: layout, scene, renders, ``layout.json``.

    generate.main(["--params", "params.json", "--out", "DIR", ["--dry-run"]])

writes ``DIR/layout.json`` ({"params", "layout", "blender", "timings"}),
``DIR/terrain_heights.npy`` (the terrain grid, row = y, column = x) and, unless
``--dry-run``, ``DIR/images``, ``DIR/gt_nodrones`` and ``DIR/object_masks``. The dry run
needs only numpy. Progress goes to stdout as ``PROMPTGS_PROGRESS {json}`` lines; a
parameter problem ends with one ``PROMPTGS_ERROR <message>`` line and exit status 2.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

from .layout import LayoutError, make_layout


def main(argv: list[str]) -> int:
    parser = argparse.ArgumentParser(prog="promptgs_blender.dataset.generate")
    parser.add_argument("--params", type=Path, required=True, help="JSON file with the full parameter set")
    parser.add_argument("--out", type=Path, required=True, help="folder to write into")
    parser.add_argument("--dry-run", action="store_true", help="layout only, no Blender scene or renders")
    args = parser.parse_args(argv)

    params = json.loads(args.params.read_text())
    timings: dict[str, float] = {}
    t0 = time.perf_counter()
    try:
        terrain, layout = make_layout(params)
    except LayoutError as exc:
        print(f"PROMPTGS_ERROR {exc}", flush=True)
        return 2
    timings["layout_s"] = time.perf_counter() - t0
    args.out.mkdir(parents=True, exist_ok=True)
    np.save(args.out / "terrain_heights.npy", terrain.heights.astype(np.float32))
    blender = None
    if not args.dry_run:
        import bpy

        from .build import build_scene
        from .render import progress_printer, render_all

        blender = bpy.app.version_string
        t0 = time.perf_counter()
        built = build_scene(terrain, layout, params)
        timings["build_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        render_all(built, layout, params, args.out, progress_printer)
        timings["render_s"] = time.perf_counter() - t0
    record = {"params": params, "layout": layout, "blender": blender, "timings": timings}
    (args.out / "layout.json").write_text(json.dumps(record, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
