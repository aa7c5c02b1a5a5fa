"""How well a run fits each drone in the views it trained on, against the views it did not.

Per-object recall (`metrics.object_recall`) is measured on the test views only, where a
drone is reconstructed when the render's error over its pixels is under half its contrast
(the drone-free ground truth's difference there). A miss there is either a drone the model
fits in its training views but places or shades wrongly from a new one (generalisation),
or one it never fits (the fit). The generated datasets have drone-free images of the test
views only, so for every view this script measures contrast against a stand-in: a
BASELINE run without the drones (3DGS, recall about 0). Its error over a drone's pixels
is the drone's contrast plus the baseline's own background error, so the stand-in ratio
is a little lower than recall's; the same stand-in on both sides makes the two comparable.

With ``--noise-dataset`` (the same dataset rendered at another sample count,
``promptgs dataset mountain ... --samples N``) it also reports the ground truth's
sampling noise: the mean |difference| between the two renders over the drones' pixels
and over all pixels of every view, and the recall the other render gets on the test views
as if a model had drawn it (the ceiling that the ground truth's noise leaves).

    python benchmarks/diagnostics/drone_fit.py runs/sparse/runs/sparse_3dgs_none_i1500_s0 \\
        runs/sparse/runs/sparse_promptgs-1_none_i1500_s0 --out runs/drone_fit

Each training view is also marked ``cropped`` when it is one of the views whose crops
the first run trained for a box drawn in its job (the box's `views.related_views`, as
the trainer picks them), and the summary splits the training views' recall into those
and the others, by the drone's contrast in the view (``by_contrast``): whether a drone
is missed where the crops never train it, or wherever it is faint.

Each row also holds each run's mean error over the drone's background ring (the pixels
within RING_PX of the drone that no object covers, ``ring``): how much of a drone's error
the terrain behind it would explain; the summary gives its median over contrast
(``ring_over_contrast``) over all pairs, the fitted ones and the missed ones.

On the test views, whose drone-free ground truth exists, each run's misses are split
into the drones' part and the background's (``test_split``, for runs on a generated
dataset): the run's Gaussians within
DRONE_GAUSSIANS_WITHIN of a drone's centre (the dataset's ``scene.json``) are its drones;
the render without them is its background. Recall is taken again with a perfect
background (the drone-free truth plus what the drones' Gaussians change) and with perfect
drones (the run's background plus what the true drones change), and per pair the drones'
change is compared with the true one over the drone's neighbourhood: ``energy``, the
least-squares factor from the true change to the rendered one (1: as strong as the truth,
2: twice), with the drone's distance from the camera and the camera's elevation above the
drone (degrees), and their median by band of each (``by_distance``, ``by_elevation``);
``true_change`` and ``drawn_change`` are the length of the true and the drawn change
summed over the neighbourhood (an RGB vector: the ground truth's noise mostly cancels in
the sum), the drone's strength in that view; ``strength_slope`` says how much of its
change from view to view the drawn drones follow.
One more recall, ``true_energy``, takes the perfect background's again with
each pair's drawn change divided by its ``energy``: what the drones' placement and shape
would give if each pair were drawn exactly as strong as the truth.

Writes ``drone_fit.json`` and ``drone_fit.png`` (per drone: stand-in recall in the
training and the test views) into ``--out``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from collections import defaultdict
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import torch

from promptgs_engine.config import TrainConfig
from promptgs_engine.data import load_colmap_scene
from promptgs_engine.data.images import read_image_uint8
from promptgs_engine.evaluation import find_mask, read_mask, render_view
from promptgs_engine.run_folder import load_run
from promptgs_engine.focus import RELATED_VIEWS, load_prompt_setting
from promptgs_engine.metrics import object_recall, resize_mask, visible_objects
from promptgs_engine.views import related_views

RECALL_RATIO = 0.5  # as metrics.object_recall: reconstructed below half the contrast
CONTRAST_EDGES = (0.04, 0.07, 0.15)  # the drones' contrast bands of the summary
RING_PX = 3  # the background ring: pixels this close to a drone (Chebyshev distance)
NEAR_PX = 2  # a drone's neighbourhood for its energy: pixels this close to it
DRONE_GAUSSIANS_WITHIN = 0.5  # a drone's Gaussians: this close to its centre (scene units; drones are 0.1-0.2 across)
# Bands for the test pairs' energy: distance from the camera (scene units; the sparse
# scene's cropped views see the box's drones from a median 33), and the camera's elevation
# above the drone (degrees; the sparse scene's low ring sees its drones from 6-15, the high
# ring from 21-39).
DISTANCE_BANDS = (0.0, 36.0, 42.0, 48.0, 1000.0)
ELEVATION_BANDS = (-90.0, 18.0, 90.0)

Run = tuple[TrainConfig, torch.nn.ParameterDict]  # a run's settings and Gaussians (`run_folder.load_run`)


def cropped_views(cfg: TrainConfig, scene) -> set[str]:
    """Names of the training views whose crops the run of ``cfg`` trained for the boxes
    drawn in its job (not the centre box, whose crops rotate over every view; not
    proposals, which come during the run): each box's RELATED_VIEWS most relevant views."""
    if cfg.prompts is None:
        return set()
    cameras = [c.downscaled(cfg.downscale) for c in scene.train_cameras]
    boxes = load_prompt_setting(dataclasses.replace(cfg, center_prompt=False))
    return {cameras[i].name for views in related_views(boxes, cameras, RELATED_VIEWS) for i in views}


def fit_pairs(baseline: Run, models: list[Run], scene) -> list[dict]:
    """One row per (view, drone) of every view with an object mask: split, stand-in
    contrast, and each run's error / contrast and signed mean error (+: brighter)."""
    base_cfg, base = baseline
    cropped = cropped_views(models[0][0], scene) if models else set()
    masks = Path(base_cfg.dataset) / "object_masks"
    rows = []
    for split, cameras in (("train", scene.train_cameras), ("test", scene.test_cameras)):
        for camera in cameras:
            mask_path = find_mask(masks, camera.name)
            if mask_path is None:
                continue
            cam = camera.downscaled(base_cfg.downscale)
            ids = resize_mask(read_mask(mask_path), cam.height, cam.width)
            gt = cam.load_image()
            stand_in = render_view(base, cam, base_cfg.backend, base_cfg.effective_screen_filter, base_cfg.rasterize_mode)
            renders = [render_view(m, cam, c.backend, c.effective_screen_filter, c.rasterize_mode) for c, m in models]
            for obj, pixels, contrast in visible_objects(ids, (stand_in - gt).abs().mean(dim=-1)):
                ring = background_ring(pixels, ids)
                rows.append({
                    "split": split, "view": camera.name, "object": obj, "pixels": int(pixels.sum()),
                    "contrast": contrast, "cropped": split == "train" and camera.name in cropped,
                    "ratios": [float((r - gt).abs().mean(dim=-1)[pixels].mean()) / contrast for r in renders],
                    "signed": [float((r - gt)[pixels].mean()) for r in renders],
                    "ring": [float((r - gt).abs().mean(dim=-1)[ring].mean()) for r in renders],
                })
    return rows


def dilate(pixels: torch.Tensor, by: int) -> torch.Tensor:
    """[H, W] bool: the pixels within ``by`` of ``pixels`` (Chebyshev distance)."""
    return torch.nn.functional.max_pool2d(pixels[None, None].float(), 2 * by + 1, stride=1, padding=by)[0, 0] > 0


def background_ring(pixels: torch.Tensor, ids: torch.Tensor) -> torch.Tensor:
    """[H, W] bool: the pixels within RING_PX of ``pixels`` that no object of ``ids`` covers."""
    return dilate(pixels, RING_PX) & (ids == 0)


def split_test_misses(run: Run, scene) -> dict:
    """Recall on the test views as rendered, with a perfect background and with perfect
    drones, and per (drone, view) pair the drones' rendered change against the true one
    (see the module docstring)."""
    cfg, params = run
    dataset = Path(cfg.dataset)
    drones = {d["id"]: d["centre"] for d in json.loads((dataset / "scene.json").read_text())["drones"]}
    centres = torch.tensor(list(drones.values()), dtype=params["means"].dtype)
    far = torch.cdist(params["means"].detach(), centres).min(dim=1).values > DRONE_GAUSSIANS_WITHIN
    background = torch.nn.ParameterDict({k: torch.nn.Parameter(v.detach()[far], requires_grad=False) for k, v in params.items()})
    recalls: dict[str, list[bool]] = {"as_rendered": [], "perfect_background": [], "perfect_drones": [], "true_energy": []}
    pairs = []
    for camera in scene.test_cameras:
        mask_path, free_path = find_mask(dataset / "object_masks", camera.name), find_mask(dataset / "gt_nodrones", camera.name)
        if mask_path is None or free_path is None:
            continue
        cam = camera.downscaled(cfg.downscale)
        ids = resize_mask(read_mask(mask_path), cam.height, cam.width)
        gt, free = cam.load_image(), _read_rgb(free_path)
        full = render_view(params, cam, cfg.backend, cfg.effective_screen_filter, cfg.rasterize_mode)
        bare = render_view(background, cam, cfg.backend, cfg.effective_screen_filter, cfg.rasterize_mode)
        drawn, true = full - bare, gt - free
        with_true_background = object_recall(free + drawn, gt, free, ids)
        recalls["as_rendered"] += object_recall(full, gt, free, ids).values()
        recalls["perfect_background"] += with_true_background.values()
        recalls["perfect_drones"] += object_recall(bare + true, gt, free, ids).values()
        rescaled = drawn.clone()
        for obj, fitted in with_true_background.items():
            near = dilate(ids == obj, NEAR_PX)
            d, t = drawn[near].flatten(), true[near].flatten()
            energy = float((d * t).sum() / (t * t).sum())
            rescaled[near] = drawn[near] / max(energy, 1e-3)
            centre = torch.tensor(drones[obj], dtype=cam.world_to_camera.dtype)
            to_eye = cam.center - centre
            pairs.append({"view": camera.name, "object": obj, "distance": float(cam.project(centre[None])[2][0]),
                          "elevation": float(torch.rad2deg(torch.asin(to_eye[2] / to_eye.norm()))),
                          "energy": energy, "true_change": float(true[near].sum(dim=0).norm()),
                          "drawn_change": float(drawn[near].sum(dim=0).norm()), "fitted_with_true_background": fitted})
        recalls["true_energy"] += object_recall(free + rescaled, gt, free, ids).values()
    return {"pairs": len(recalls["as_rendered"]), **{k: float(np.mean(v)) for k, v in recalls.items()},
            "by_distance": by_band(pairs, "distance", DISTANCE_BANDS), "by_elevation": by_band(pairs, "elevation", ELEVATION_BANDS),
            "strength_slope": strength_slope(pairs), "rows": pairs}


def strength_slope(pairs: list[dict]) -> float:
    """How much of the true strength's change from view to view the drawn drones follow:
    the least-squares slope of log ``drawn_change`` on log ``true_change`` over the pairs,
    each drone's views centred on their mean (1: they follow it, 0: the drawn strength is
    the same in every view)."""
    xs, ys = [], []
    for obj in {p["object"] for p in pairs}:
        own = [p for p in pairs if p["object"] == obj and p["drawn_change"] > 0 and p["true_change"] > 0]
        true = np.log([p["true_change"] for p in own])
        drawn = np.log([p["drawn_change"] for p in own])
        xs += list(true - true.mean())
        ys += list(drawn - drawn.mean())
    x, y = np.array(xs), np.array(ys)
    return float(x @ y / (x @ x)) if x.size else float("nan")


def by_band(pairs: list[dict], key: str, edges: tuple[float, ...]) -> dict:
    """Per band of ``key`` (from each edge to the next): the pairs, their median
    ``energy`` and the share fitted over the true background."""
    bands = {}
    for lo, hi in zip(edges[:-1], edges[1:]):
        sel = [p for p in pairs if lo <= p[key] < hi]
        if sel:
            bands[f"{lo:g}-{hi:g}"] = {"pairs": len(sel), "energy": float(np.median([p["energy"] for p in sel])),
                                       "fitted_with_true_background": float(np.mean([p["fitted_with_true_background"] for p in sel]))}
    return bands


def summarise(rows: list[dict], runs: list[Path]) -> dict:
    out: dict = {}
    for i, run in enumerate(runs):
        per_run: dict = {}
        for split in ("train", "test"):
            split_rows = [r for r in rows if r["split"] == split]
            if not split_rows:
                continue
            ratios = np.array([r["ratios"][i] for r in split_rows])
            by_object = defaultdict(list)
            for r, ratio in zip(split_rows, ratios):
                by_object[r["object"]].append(ratio < RECALL_RATIO)
            per_run[split] = {
                "pairs": int(ratios.size),
                "stand_in_recall": float((ratios < RECALL_RATIO).mean()),
                "ratio_median": float(np.median(ratios)),
                "per_object": {str(k): round(float(np.mean(v)), 3) for k, v in sorted(by_object.items())},
                "ring_over_contrast": ring_over_contrast(split_rows, i),
            }
        train_rows = [r for r in rows if r["split"] == "train"]
        if any(r["cropped"] for r in train_rows):
            per_run["train_by_crops"] = {
                name: recall_by_contrast([r for r in train_rows if r["cropped"] == flag], i)
                for name, flag in (("cropped", True), ("other", False))
            }
        out[run.name] = per_run
    return out


def recall_by_contrast(rows: list[dict], run: int) -> dict:
    """Stand-in recall of run ``run`` over ``rows``, in all and per contrast band, and
    the background ring's error over contrast."""
    def recall(sel: list[dict]) -> dict:
        return {"pairs": len(sel), "stand_in_recall": round(float(np.mean([r["ratios"][run] < RECALL_RATIO for r in sel])), 3) if sel else None}
    edges = (0.0, *CONTRAST_EDGES, float("inf"))
    bands = {f"{lo:g}-{hi:g}": recall([r for r in rows if lo <= r["contrast"] < hi]) for lo, hi in zip(edges[:-1], edges[1:])}
    return {**recall(rows), "by_contrast": bands, "ring_over_contrast": ring_over_contrast(rows, run)}


def ring_over_contrast(rows: list[dict], run: int) -> dict:
    """Median of run ``run``'s background-ring error over the drone's contrast, over all
    of ``rows`` and over the fitted and the missed pairs apart."""
    def median(sel: list[dict]) -> float | None:
        return round(float(np.median([r["ring"][run] / r["contrast"] for r in sel])), 3) if sel else None
    fitted = [r for r in rows if r["ratios"][run] < RECALL_RATIO]
    missed = [r for r in rows if r["ratios"][run] >= RECALL_RATIO]
    return {"all": median(rows), "fitted": median(fitted), "missed": median(missed)}


def _read_rgb(path: Path) -> torch.Tensor:
    """[H, W, 3] float32 in [0, 1], decoded as the trainer decodes its images."""
    return torch.from_numpy(read_image_uint8(path).astype(np.float32) / 255.0)


def sampling_noise(dataset: Path, other: Path) -> dict:
    """Mean |a − b| between two renders of one dataset (its images/), over the drones'
    pixels (object_masks/) and over every pixel; and, on the views with a drone-free
    ground truth (the test views' gt_nodrones/), the recall that the other render gets as
    if a model had drawn it (`metrics.object_recall`): what the ground truth's own noise
    leaves of the metric."""
    drone, whole, pairs = [], [], []
    for path in sorted((dataset / "images").iterdir()):
        twin = other / "images" / path.name
        mask_path = find_mask(dataset / "object_masks", path.name)
        if not twin.is_file():
            continue
        a, b = _read_rgb(path), _read_rgb(twin)
        diff = (a - b).abs().mean(dim=-1)
        whole.append(float(diff.mean()))
        if mask_path is None:
            continue
        ids = resize_mask(read_mask(mask_path), diff.shape[0], diff.shape[1])
        if bool((ids > 0).any()):
            drone.append(float(diff[ids > 0].mean()))
        free = find_mask(dataset / "gt_nodrones", path.name)
        if free is not None:
            pairs += list(object_recall(b, a, _read_rgb(free), ids).values())
    return {
        "views": len(whole),
        "drone_pixels_median": float(np.median(drone)) if drone else None,
        "all_pixels_median": float(np.median(whole)) if whole else None,
        "other_as_render_recall": float(np.mean(pairs)) if pairs else None,
        "other_as_render_pairs": len(pairs),
    }


def plot(summary: dict, path: Path) -> None:
    fig, ax = plt.subplots(figsize=(7, 4))
    width = 0.8 / max(2 * len(summary), 1)
    for i, (name, per_run) in enumerate(summary.items()):
        for j, split in enumerate(("train", "test")):
            if split not in per_run:
                continue
            objs = per_run[split]["per_object"]
            x = np.array([int(k) for k in objs]) + (2 * i + j - (2 * len(summary) - 1) / 2) * width
            ax.bar(x, list(objs.values()), width=width, label=f"{name} ({split})")
    ax.set_xlabel("drone")
    ax.set_ylabel("stand-in recall (error < contrast / 2)")
    ax.set_ylim(0, 1.05)
    ax.set_title("Drone fit: training views against test views")
    ax.legend(fontsize=6)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("baseline", type=Path, help="a run folder of a model without the drones (3DGS): the stand-in background")
    ap.add_argument("runs", type=Path, nargs="+", help="run folders to measure")
    ap.add_argument("--noise-dataset", type=Path, help="the run's dataset rendered at another sample count")
    ap.add_argument("--out", type=Path, default=Path("runs/drone_fit"))
    args = ap.parse_args()
    baseline = load_run(args.baseline)
    models = [load_run(r) for r in args.runs]
    base_cfg = baseline[0]
    scene = load_colmap_scene(base_cfg.dataset, images=base_cfg.images, test_every=base_cfg.test_every)
    rows = fit_pairs(baseline, models, scene)
    if not rows:
        raise SystemExit(f"{args.baseline}: its dataset has no object_masks/ for its views")
    result: dict = {"baseline": str(args.baseline), "runs": [str(r) for r in args.runs], "summary": summarise(rows, args.runs)}
    if args.noise_dataset is not None:
        dataset = Path(base_cfg.dataset)
        result["sampling_noise"] = {"dataset": str(dataset), "other": str(args.noise_dataset),
                                    **sampling_noise(dataset, args.noise_dataset)}
    result["test_split"] = {path.name: split_test_misses(run, scene) for path, run in zip(args.runs, models)
                            if (Path(run[0].dataset) / "scene.json").is_file()}
    result["rows"] = rows
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "drone_fit.json").write_text(json.dumps(result, indent=2))
    plot(result["summary"], args.out / "drone_fit.png")
    print(json.dumps({k: v for k, v in result.items() if k != "rows"}, indent=2))


if __name__ == "__main__":
    main()
