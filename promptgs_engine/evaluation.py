"""Evaluate and render a finished run folder (``promptgs eval`` and ``promptgs render``)."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator

import numpy as np
import torch
from PIL import Image
from tqdm import tqdm

from .config import BASELINE_SCREEN_FILTER, TrainConfig
from .data import Camera, Scene, load_camera_file, load_colmap_scene
from .data.images import load_image_tensor
from .errors import PromptGSError
from .gaussians import sh_degree_of
from .metrics import masked_psnr, object_recall, object_region_psnr, psnr, resize_mask, ssim
from .render import on_backend_device, render
from .run_folder import METRICS, RENDERS, SUMMARY, load_run

NO_OBJECTS = "gt_nodrones"  # object-free ground truth beside object_masks/ (recall)


def render_view(
    params: torch.nn.ParameterDict,
    camera: Camera,
    backend: str = "auto",
    screen_filter: float = BASELINE_SCREEN_FILTER,
    rasterize_mode: str = "classic",
) -> torch.Tensor:
    """Render one camera with the Gaussians in ``params``; [H, W, 3] in [0, 1]. A run's
    Gaussians render with the filter they were trained with (``cfg.effective_screen_filter``
    and ``cfg.rasterize_mode``)."""
    with torch.no_grad():
        device = params["means"].device
        img, _, _ = render(
            params["means"],
            params["quats"],
            torch.exp(params["scales"]),
            torch.sigmoid(params["opacities"]),
            torch.cat([params["sh0"], params["shN"]], dim=1),
            camera.world_to_camera[None].to(device),
            camera.K[None].to(device),
            camera.width,
            camera.height,
            sh_degree=sh_degree_of(params),
            backend=backend,
            eps2d=screen_filter,
            rasterize_mode=rasterize_mode,
        )
    return img[0].clamp(0, 1).cpu()


def find_mask(mask_dir: Path, image_name: str) -> Path | None:
    """The mask of an image: the same file name, or the same stem with any extension."""
    exact = mask_dir / image_name
    if exact.is_file():
        return exact
    matches = sorted(mask_dir.glob(Path(image_name).stem + ".*"))
    return matches[0] if matches else None


def read_mask(path: Path) -> torch.Tensor:
    """An object-id mask [H, W] int64: 0 = background; a white/black mask is one object."""
    arr = np.asarray(Image.open(path))
    if arr.ndim == 3:
        arr = arr[..., :3].max(axis=-1)
    return torch.from_numpy(arr.astype(np.int64))


@dataclass
class ObjectView:
    """A test view at a run's training size with its per-object ground truth."""

    name: str
    camera: Camera
    gt: torch.Tensor  # [H, W, 3]
    ids: torch.Tensor  # [H, W] object ids, 0 = background
    without_objects: torch.Tensor  # [H, W, 3] the object-free ground truth


def object_views(cfg: TrainConfig, scene: Scene) -> Iterator[ObjectView]:
    """The test views of a run's dataset that have both an object mask
    (``object_masks/``) and object-free ground truth (``gt_nodrones/``)."""
    dataset = Path(cfg.dataset)
    for camera in scene.test_cameras:
        cam = camera.downscaled(cfg.downscale)
        mask_path = find_mask(dataset / "object_masks", camera.name)
        free_path = find_mask(dataset / NO_OBJECTS, camera.name)
        if mask_path is None or free_path is None:
            continue
        ids = resize_mask(read_mask(mask_path), cam.height, cam.width)
        free = load_image_tensor(free_path, cam.downscale, (cam.width, cam.height))
        yield ObjectView(camera.name, cam, cam.load_image(), ids, free)


def _mean(values: list[float | None]) -> float | None:
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(np.mean(finite)) if finite else None


def evaluate(
    params: torch.nn.ParameterDict,
    cameras: list[Camera],
    downscale: int = 1,
    mask_dir: Path | None = None,
    backend: str = "auto",
    quiet: bool = False,
    no_objects_dir: Path | None = None,
    render_dir: Path | None = None,
    screen_filter: float = BASELINE_SCREEN_FILTER,
    rasterize_mode: str = "classic",
) -> dict:
    """PSNR/SSIM on ``cameras``; with ``mask_dir``, object-pixel and object-region PSNR;
    with ``no_objects_dir`` as well (object-free ground truth, same names), per-object
    recall (`metrics.object_recall`). ``render_dir`` keeps each render as a PNG.
    ``screen_filter`` (px²) and ``rasterize_mode`` are the ones the Gaussians were trained with."""
    if not cameras:
        raise PromptGSError("no test views to evaluate (the dataset has no test split)")
    if mask_dir is not None and not Path(mask_dir).is_dir():
        raise PromptGSError(f"{mask_dir}: mask folder not found")
    params = on_backend_device(params, backend)
    per_image = []
    for camera in tqdm(cameras, desc="eval", disable=quiet, unit="view"):
        cam = camera.downscaled(downscale)
        gt = cam.load_image()
        img = render_view(params, cam, backend, screen_filter, rasterize_mode)
        row = {"image": camera.name, "psnr": psnr(img, gt), "ssim": ssim(img, gt)}
        if mask_dir is not None:
            mask_path = find_mask(Path(mask_dir), camera.name)
            if mask_path is not None:
                ids = resize_mask(read_mask(mask_path), cam.height, cam.width)
                row["masked_psnr"] = masked_psnr(img, gt, ids > 0)
                row["object_region_psnr"] = object_region_psnr(img, gt, ids)
                free_path = find_mask(Path(no_objects_dir), camera.name) if no_objects_dir is not None else None
                if free_path is not None:
                    free = load_image_tensor(free_path, cam.downscale, (cam.width, cam.height))
                    row["objects"] = {str(k): v for k, v in object_recall(img, gt, free, ids).items()}
        if render_dir is not None:
            save_png(img, Path(render_dir) / (Path(camera.name).stem + ".png"))
        per_image.append(row)
    metrics = {
        "psnr": _mean([r["psnr"] for r in per_image]),
        "ssim": _mean([r["ssim"] for r in per_image]),
        "n_test_views": len(per_image),
        "resolution": [cameras[0].downscaled(downscale).width, cameras[0].downscaled(downscale).height],
    }
    if mask_dir is not None:
        metrics["masked_psnr"] = _mean([r.get("masked_psnr") for r in per_image])
        metrics["object_region_psnr"] = _mean([r.get("object_region_psnr") for r in per_image])
        metrics["n_masked_views"] = sum(r.get("masked_psnr") is not None for r in per_image)
    if any("objects" in r for r in per_image):
        metrics.update(summarize_recall(per_image))
    metrics["per_image"] = per_image
    return metrics


def summarize_recall(per_image: list[dict]) -> dict:
    """Recall over all (object, view) pairs, and per object (keys are object ids)."""
    pairs: dict[str, list[bool]] = {}
    for row in per_image:
        for obj, ok in row.get("objects", {}).items():
            pairs.setdefault(obj, []).append(bool(ok))
    flat = [ok for oks in pairs.values() for ok in oks]
    return {
        "recall": float(np.mean(flat)) if flat else None,
        "n_recall_pairs": len(flat),
        "recall_per_object": {obj: float(np.mean(oks)) for obj, oks in sorted(pairs.items(), key=lambda kv: int(kv[0]))},
    }


def save_png(img: torch.Tensor, path: Path) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray((img.clamp(0, 1).numpy() * 255).round().astype(np.uint8)).save(path)


def evaluate_run(
    run_dir: Path,
    mask_dir: Path | None = None,
    scene: Scene | None = None,
    quiet: bool = False,
    save_renders: bool = False,
    gaussians: Path | None = None,
) -> dict:
    """Evaluate a run folder on its test views; writes and returns ``metrics.json``.
    With ``gaussians`` (a PLY, SPZ or glTF file), those Gaussians are evaluated with the
    run's dataset and settings instead, and only returned.

    A dataset with ``object_masks/`` is evaluated on them by default, and with
    ``gt_nodrones/`` beside them also for per-object recall. ``save_renders`` keeps the
    test-view renders in ``RUN/renders/``.
    """
    run_dir = Path(run_dir)
    cfg, params = load_run(run_dir, gaussians=gaussians)
    if scene is None:
        scene = load_colmap_scene(cfg.dataset, images=cfg.images, test_every=cfg.test_every)
    if mask_dir is None and (Path(cfg.dataset) / "object_masks").is_dir():
        mask_dir = Path(cfg.dataset) / "object_masks"
    no_objects = Path(cfg.dataset) / NO_OBJECTS
    metrics = evaluate(
        params, scene.test_cameras, cfg.downscale, mask_dir, backend=cfg.backend, quiet=quiet,
        no_objects_dir=no_objects if no_objects.is_dir() else None,
        render_dir=run_dir / RENDERS if save_renders else None, screen_filter=cfg.effective_screen_filter,
        rasterize_mode=cfg.rasterize_mode,
    )
    if gaussians is not None:
        return {**metrics, "gaussians": str(gaussians), "n_gaussians": int(params["means"].shape[0])}
    summary_path = run_dir / SUMMARY
    if summary_path.is_file():
        metrics = {**json.loads(summary_path.read_text()), **metrics}
    metrics["n_gaussians"] = int(params["means"].shape[0])
    tmp = run_dir / (METRICS + ".tmp")
    tmp.write_text(json.dumps(metrics, indent=2))
    tmp.replace(run_dir / METRICS)
    return metrics


def render_run(
    run_dir: Path,
    out_dir: Path,
    camera_names: list[str] | None = None,
    quiet: bool = False,
    camera_file: Path | None = None,
    snapshot: Path | None = None,
) -> list[Path]:
    """Render cameras of a run to PNG files: the named dataset cameras (all when None) at
    the run's resolution, or the cameras of a camera file at their own size.

    The Gaussians are the run's ``point_cloud.ply``, or a snapshot of a run that is still
    training (``snapshot``; DC colour only). The run's screen filter and rasterize mode apply.
    """
    cfg, params = load_run(run_dir, snapshot)
    if camera_file is not None:
        views = load_camera_file(camera_file)
    else:
        scene = load_colmap_scene(cfg.dataset, images=cfg.images, test_every=cfg.test_every)
        cameras = {c.name: c for c in scene.train_cameras + scene.test_cameras}
        if camera_names is None:
            camera_names = sorted(cameras)
        unknown = [n for n in camera_names if n not in cameras]
        if unknown:
            raise PromptGSError(f"no camera named {unknown[0]!r} in {cfg.dataset}")
        views = [cameras[name].downscaled(cfg.downscale) for name in camera_names]
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    params = on_backend_device(params, cfg.backend)
    written = []
    for camera in tqdm(views, desc="render", disable=quiet, unit="view"):
        img = render_view(params, camera, cfg.backend, cfg.effective_screen_filter, cfg.rasterize_mode)
        path = out_dir / (Path(camera.name).stem + ".png")
        save_png(img, path)
        written.append(path)
    return written
