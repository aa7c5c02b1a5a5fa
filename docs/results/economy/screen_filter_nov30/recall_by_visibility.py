"""Recall split by the dataset's own visibility rule: a (drone, test view) pair is *seen*
when the drone is at least `min_visible_px` across there (`scene.json`'s per-view `seen`,
docs/dataset.md, "Visible"). The recall metric counts every pair whose contrast is at
least 0.02, seen or not. One line per run folder: fitted / pairs for each part.

    python docs/results/economy/screen_filter_nov30/recall_by_visibility.py RUN [RUN ...]
"""
from __future__ import annotations

import json
import sys
from pathlib import Path


def split(run: Path) -> dict[str, list[int]]:
    metrics = json.loads((run / "metrics.json").read_text())
    dataset = Path(json.loads((run / "cfg.json").read_text())["dataset"])
    scene = json.loads((dataset / "scene.json").read_text())
    seen = {(d["id"], v["name"]): v["seen"] for d in scene["drones"] for v in d["views"]}
    out = {"seen": [0, 0], "unseen": [0, 0]}
    for image in metrics["per_image"]:
        for obj, fitted in image.get("objects", {}).items():
            part = out["seen" if seen[(int(obj), image["image"])] else "unseen"]
            part[0] += bool(fitted)
            part[1] += 1
    return out


if __name__ == "__main__":
    for arg in sys.argv[1:]:
        parts = split(Path(arg))
        print(json.dumps({"run": arg, **{k: {"fitted": f, "pairs": n} for k, (f, n) in parts.items()}}))
