"""Generate a synthetic mountain dataset end to end: Blender renders, then the COLMAP model.

The dataset is written into a hidden sibling folder ``.<name>.partial`` and renamed to
``out`` only when complete, so ``out`` is never half-written and an existing dataset is
never touched.
"""

from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from ..errors import DatasetError
from . import scene_record
from .blender import BlenderFailed, run_generator
from .presets import GROUND_DETAIL

FORMAT = "promptgs-synthetic-mountain/1"


def _normalised(params: dict[str, Any]) -> str:
    return json.dumps(params, sort_keys=True)


def check_output_folder(out: Path, params: dict[str, Any]) -> bool:
    """True when ``out`` already holds exactly this dataset; raises if it holds anything else."""
    if out.exists() and not out.is_dir():
        raise DatasetError(f"{out}: exists and is not a folder")
    scene_json = out / "scene.json"
    if scene_json.is_file():
        try:
            stored = json.loads(scene_json.read_text())
        except (OSError, ValueError) as exc:
            raise DatasetError(f"{scene_json}: unreadable ({exc}); choose another --out") from exc
        # A dataset from before the ground-detail settings has their defaults.
        if _normalised({**GROUND_DETAIL, **stored.get("parameters", {})}) == _normalised(params):
            return True
        raise DatasetError(
            f"{out}: already holds a different dataset (preset {stored.get('parameters', {}).get('preset')}, "
            f"seed {stored.get('seed')}); choose another --out or delete it"
        )
    if out.is_dir() and any(out.iterdir()):
        raise DatasetError(f"{out}: folder is not empty and holds no PromptGS dataset; choose an empty or new folder")
    return False


def _record(params: dict[str, Any], gen: dict[str, Any]) -> dict[str, Any]:
    layout = gen["layout"]
    return {
        "format": FORMAT,
        "complete": False,
        "seed": params["seed"],
        "preset": params.get("preset"),
        "parameters": params,
        "coordinates": "dataset (COLMAP) world = Blender world (identity); metres; +z up",
        "size_rule": {
            "drone_max_px_1080": params["drone_max_px_1080"],
            "max_drone_px": layout["limits"]["max_drone_px"],
            "min_visible_px": layout["limits"]["min_visible_px"],
            "min_views": layout["limits"]["min_views"],
            "definition": "size = larger side of the bounding rectangle of the projected 3D bounding box; "
            "size <= max_drone_px = drone_max_px_1080 * height / 1080 in every image the box touches; "
            "a view sees a drone when its centre is in the frame, unoccluded by terrain, and size >= min_visible_px; "
            "each drone is seen by >= min_views training views",
        },
        "test_split": "every 8th image in name order (index % test_every == 0), listed in test.txt",
        "test_images": scene_record.test_names(layout),
        "cameras": layout["cameras"],
        "sun": layout["sun"],
        "terrain": layout["terrain"],
        "flames": layout["flames"],
        "drones": layout["drones"],
        "prompts": scene_record.prompt_boxes(layout["drones"]),
        "blender": gen.get("blender"),
        "timings": dict(gen.get("timings", {})),
    }


def dry_run(params: dict[str, Any], blender: str | None) -> dict[str, Any]:
    """The layout part of ``scene.json`` (cameras, flames, drones, prompts) without rendering."""
    with tempfile.TemporaryDirectory(prefix="promptgs-layout-") as tmp:
        tmp_path = Path(tmp)
        (tmp_path / "params.json").write_text(json.dumps(params))
        run_generator(["--params", str(tmp_path / "params.json"), "--out", str(tmp_path / "out"), "--dry-run"],
                      blender, tmp_path / "blender.log", need_bpy=False)
        gen = json.loads((tmp_path / "out" / "layout.json").read_text())
    record = _record(params, gen)
    record["dry_run"] = True
    return record


def generate(params: dict[str, Any], out: Path, blender: str | None, show_progress: bool = True) -> dict[str, Any] | None:
    """Render and reconstruct a dataset into ``out``; returns its scene record, or None when
    ``out`` already holds this very dataset."""
    import pycolmap  # noqa: F401  (fail before rendering when pycolmap is missing)

    from .sfm import build_sparse_model

    out = Path(out).resolve()
    if check_output_folder(out, params):
        return None
    partial = out.parent / f".{out.name}.partial"
    if partial.exists():
        shutil.rmtree(partial)
    work = partial / ".work"
    work.mkdir(parents=True)
    (work / "params.json").write_text(json.dumps(params, indent=1))
    t_start = time.perf_counter()

    n_views = sum(int(r["count"]) for r in params["camera_rings"])
    n_test = sum(1 for i in range(n_views) if int(params["test_every"]) > 0 and i % int(params["test_every"]) == 0)
    bars: list = []  # the progress bar, opened at the first render so parameter errors print alone
    last: dict[str, int] = {}

    def progress(stage: str, done: int, total: int) -> None:
        if show_progress and not bars:
            from tqdm import tqdm

            bars.append(tqdm(total=2 * n_views + n_test, unit="render", desc="rendering", dynamic_ncols=True))
        if bars:
            bars[0].set_postfix_str(f"{stage} {done}/{total}")
            bars[0].update(done - last.get(stage, 0))
        last[stage] = done

    try:
        try:
            run_generator(["--params", str(work / "params.json"), "--out", str(partial)], blender, work / "blender.log", progress)
        finally:
            for bar in bars:
                bar.close()
    except BlenderFailed:
        raise  # keep the partial folder with .work/blender.log
    except DatasetError:
        shutil.rmtree(partial, ignore_errors=True)  # a parameter problem: nothing worth keeping
        raise
    gen = json.loads((partial / "layout.json").read_text())
    layout = gen["layout"]
    record = _record(params, gen)

    scene_record.mask_statistics(partial, layout)
    t0 = time.perf_counter()
    rec = build_sparse_model(partial, layout["cameras"], work)
    record["timings"]["sfm_s"] = time.perf_counter() - t0
    points = np.array([p.xyz for p in rec.points3D.values()]).reshape(-1, 3)
    heights = np.load(partial / "terrain_heights.npy").astype(np.float64)
    record["sfm"] = scene_record.sfm_statistics(points, layout, heights)
    record["sfm"]["n_registered_images"] = int(rec.num_reg_images())
    record["drones"] = layout["drones"]
    record["pycolmap"] = pycolmap.__version__
    (partial / "test.txt").write_text("".join(f"{n}\n" for n in record["test_images"]))
    record["timings"]["total_s"] = time.perf_counter() - t_start
    record["complete"] = True
    (partial / "scene.json").write_text(json.dumps(record, indent=1))
    (partial / "layout.json").unlink()
    shutil.rmtree(work)
    if out.exists():
        out.rmdir()  # empty, checked above
    partial.rename(out)
    return record
