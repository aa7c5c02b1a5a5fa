"""Proposed boxes against the true objects: precision and recall of the boxes themselves.

For proposal files (``promptgs propose RUN`` output, or the ``proposals.json`` that
``promptgs train --propose-prompts`` writes into its run folder) on a dataset whose
``scene.json`` lists its objects (the mountain generator's ``drones`` with ``centre`` and
``radius``, the toy scene's with ``center`` and ``size``):

* a proposal is **correct** when some object's centre lies inside its box grown by that
  object's radius (the box holds part of the object);
* **precision** at a confidence threshold: correct proposals / proposals at or above it;
* **recall**: objects that some proposal at or above the threshold holds / all objects
  (also over the objects that at least ``min_views`` training views show, from
  ``scene.json``'s ``n_train_views_in_mask`` where it exists);
* **localisation**: distance from a correct proposal's triangulated point to the object's
  centre (metres and in object radii), and the boxes' largest edge in object radii.

    python benchmarks/diagnostics/proposal_quality.py runs/x/proposals.json [more files] --out DIR [--labels A B]

Writes ``DIR/proposal_quality.json`` and ``DIR/proposal_quality.png`` (precision and
recall against the confidence threshold per file; a top view of the objects and the
first file's boxes), and ``DIR/proposal_crops.png``: for the first file's boxes, the
image around the candidate pixel of their three strongest views (what a user is shown
as the reason for a box).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from promptgs_engine.prompts import PromptBox
from promptgs_engine.propose import TRAIN_MIN_CONFIDENCE

THRESHOLDS = [round(t, 2) for t in np.arange(0.0, 0.96, 0.05)]
TRAIN_THRESHOLD = TRAIN_MIN_CONFIDENCE
MIN_VIEWS = 8


def truth(dataset: Path) -> list[dict]:
    """Objects of a dataset: id, centre, radius, training views that show them (or None)."""
    record = json.loads((dataset / "scene.json").read_text())
    out = []
    for d in record.get("drones", []):
        centre = d.get("centre", d.get("center"))
        radius = d.get("radius", 0.75 * d.get("size", 0.0))  # toy: the arms reach ~0.7 size from the centre
        out.append({"id": d["id"], "centre": np.asarray(centre, float), "radius": float(radius),
                    "train_views": d.get("n_train_views_in_mask")})
    return out


def holds(box: PromptBox, centre: np.ndarray, radius: float) -> bool:
    local = box.rotation_matrix().T @ (centre - np.asarray(box.center))
    return bool(np.all(np.abs(local) <= np.asarray(box.size) / 2 + radius))


def evaluate(path: Path, dataset: Path | None) -> dict:
    data = json.loads(path.read_text())
    if dataset is None:
        dataset = Path(data["dataset"])
    objects = truth(dataset)
    entries = data["prompts"]
    boxes = [PromptBox(e["center"], e["size"], e["rotation_wxyz"], e.get("weight", 1.0)) for e in entries]
    conf = np.array([e.get("confidence", 1.0) for e in entries])
    match = np.array([[holds(b, o["centre"], o["radius"]) for o in objects] for b in boxes]).reshape(len(boxes), len(objects))
    seen = np.array([o["train_views"] is None or o["train_views"] >= MIN_VIEWS for o in objects])
    curve = []
    for t in THRESHOLDS:
        sel = conf >= t
        n = int(sel.sum())
        correct = int(match[sel].any(axis=1).sum()) if n else 0
        found = match[sel].any(axis=0) if n else np.zeros(len(objects), bool)
        curve.append({"threshold": t, "n_proposals": n, "precision": correct / n if n else None,
                      "recall": float(found.mean()) if len(objects) else None,
                      "recall_seen": float(found[seen].mean()) if seen.any() else None})
    sel = conf >= TRAIN_THRESHOLD
    errors, size_ratio = [], []
    for i in np.nonzero(sel)[0]:
        hit = np.nonzero(match[i])[0]
        if len(hit):
            point = np.asarray(entries[i].get("evidence", {}).get("point", entries[i]["center"]))
            j = hit[np.argmin([np.linalg.norm(point - objects[k]["centre"]) for k in hit])]
            d = float(np.linalg.norm(point - objects[j]["centre"]))
            errors.append((d, d / max(objects[j]["radius"], 1e-9)))
            size_ratio.append(max(boxes[i].size) / max(objects[j]["radius"], 1e-9))
    found = match[sel].any(axis=0) if sel.any() else np.zeros(len(objects), bool)
    at = next(c for c in curve if c["threshold"] == TRAIN_THRESHOLD)
    reasons: dict[str, int] = {}
    for r in data.get("rejected", []):
        reasons[r["reason"]] = reasons.get(r["reason"], 0) + 1
    return {
        "file": str(path),
        "dataset": str(dataset),
        "step": data.get("step"),
        "n_objects": len(objects),
        "n_objects_seen": int(seen.sum()),
        "n_proposals": len(entries),
        "at_training_threshold": {**at, "missed": [{"id": o["id"], "train_views": o["train_views"]} for o, f in zip(objects, found) if not f]},
        "median_error_m": float(np.median([e[0] for e in errors])) if errors else None,
        "median_error_radii": float(np.median([e[1] for e in errors])) if errors else None,
        "median_box_edge_radii": float(np.median(size_ratio)) if size_ratio else None,
        "rejected": reasons,
        "n_unmatched": sum(len(v) for v in data.get("unmatched", {}).values()),
        "candidates_per_view_median": float(np.median(list(data.get("n_candidates", {0: 0}).values()))),
        "curve": curve,
        "_objects": objects,
        "_boxes": boxes,
        "_conf": conf,
    }


def plot(results: list[dict], labels: list[str], path: Path) -> None:
    fig, (ax, top) = plt.subplots(1, 2, figsize=(11, 4.4))
    for r, label, colour in zip(results, labels, plt.cm.tab10.colors):
        t = [c["threshold"] for c in r["curve"]]
        ax.plot(t, [np.nan if c["precision"] is None else c["precision"] for c in r["curve"]], "-", color=colour, label=f"{label}: precision")
        ax.plot(t, [c["recall"] for c in r["curve"]], "--", color=colour, label=f"{label}: recall")
    ax.axvline(TRAIN_THRESHOLD, color="0.6", lw=0.8)
    ax.set_xlabel("confidence threshold")
    ax.set_ylim(-0.02, 1.02)
    ax.set_title("proposed boxes against the true objects")
    ax.legend(fontsize=7)
    r = results[0]
    centres = np.array([o["centre"] for o in r["_objects"]]).reshape(-1, 3)
    top.scatter(centres[:, 0], centres[:, 1], s=40, facecolors="none", edgecolors="k", label="objects")
    for b, c in zip(r["_boxes"], r["_conf"]):
        corners = b.corners().numpy()
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        colour = plt.cm.viridis(float(c))
        top.add_patch(plt.Rectangle((lo[0], lo[1]), hi[0] - lo[0], hi[1] - lo[1], fill=False, edgecolor=colour, lw=1.5 if c >= TRAIN_THRESHOLD else 0.6))
    if len(centres):
        span = max(np.ptp(centres[:, 0]), np.ptp(centres[:, 1]), 1e-3)
        mid = centres[:, :2].mean(axis=0)
        top.set_xlim(mid[0] - span, mid[0] + span)
        top.set_ylim(mid[1] - span, mid[1] + span)
    top.set_aspect("equal")
    top.set_title(f"{labels[0]}: top view (boxes coloured by confidence; thick: ≥ {TRAIN_THRESHOLD})", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def crops(path: Path, dataset: Path, out: Path, n_boxes: int = 12, half: int = 10) -> None:
    """The image around each box's three strongest observations, the candidate pixel marked."""
    from promptgs_engine.data import load_colmap_scene

    data = json.loads(path.read_text())
    entries = data["prompts"][:n_boxes]
    if not entries:
        return
    scene = load_colmap_scene(dataset)
    cams = {c.name: c for c in scene.train_cameras}
    width = data.get("resolution", [None])[0]
    fig, axes = plt.subplots(len(entries), 3, figsize=(4.2, 1.45 * len(entries)), squeeze=False)
    for i, e in enumerate(entries):
        obs = sorted(e.get("evidence", {}).get("observations", []), key=lambda o: -o["strength"])[:3]
        for j in range(3):
            ax = axes[i, j]
            ax.set_xticks([])
            ax.set_yticks([])
            if j >= len(obs):
                ax.axis("off")
                continue
            cam = cams[obs[j]["view"]]
            cam = cam.downscaled(max(1, round(cam.width / width))) if width else cam
            img = cam.load_image().numpy()
            u, v = obs[j]["uv"]
            x0, y0 = int(u) - half, int(v) - half
            patch = np.zeros((2 * half + 1, 2 * half + 1, 3))
            ys, xs = slice(max(y0, 0), min(y0 + 2 * half + 1, img.shape[0])), slice(max(x0, 0), min(x0 + 2 * half + 1, img.shape[1]))
            patch[ys.start - y0 : ys.stop - y0, xs.start - x0 : xs.stop - x0] = img[ys, xs]
            ax.imshow(patch, interpolation="nearest", extent=(x0, x0 + 2 * half + 1, y0 + 2 * half + 1, y0))
            ax.plot([u], [v], "o", ms=9, mfc="none", mec="#ff00ff", mew=0.8)
            ax.set_title(f"{Path(obs[j]['view']).stem} s={obs[j]['strength']:.1f}", fontsize=6)
        axes[i, 0].set_ylabel(f"#{i} c={e.get('confidence', 1.0):.2f}", fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("files", type=Path, nargs="+", help="proposal files")
    parser.add_argument("--dataset", type=Path, help="dataset folder (default: the file's 'dataset')")
    parser.add_argument("--labels", nargs="+")
    parser.add_argument("--out", type=Path, required=True)
    args = parser.parse_args()
    labels = args.labels or [f.parent.name for f in args.files]
    results = [evaluate(f, args.dataset) for f in args.files]
    args.out.mkdir(parents=True, exist_ok=True)
    clean = [{k: v for k, v in r.items() if not k.startswith("_")} | {"label": lab} for r, lab in zip(results, labels)]
    (args.out / "proposal_quality.json").write_text(json.dumps(clean, indent=1))
    plot(results, labels, args.out / "proposal_quality.png")
    crops(args.files[0], Path(results[0]["dataset"]), args.out / "proposal_crops.png")
    for r, lab in zip(clean, labels):
        a = r["at_training_threshold"]
        print(f"{lab}: {r['n_proposals']} proposals; at confidence >= {TRAIN_THRESHOLD}: {a['n_proposals']} boxes, "
              f"precision {a['precision']}, recall {a['recall']} (seen {a['recall_seen']}), "
              f"median error {r['median_error_m']} m ({r['median_error_radii']} radii)")
    print(f"wrote {args.out / 'proposal_quality.json'} and {args.out / 'proposal_quality.png'}")


if __name__ == "__main__":
    main()
