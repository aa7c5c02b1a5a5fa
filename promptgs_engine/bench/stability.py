"""The stability suite: inputs where 3DGS-style training is known to break.

Each case builds a variant of the embedded toy scene (``toy_scene.make_toy_scene``) and
its prompt files in a work folder, then trains it with ``promptgs train`` in a process of
its own (one per case and strategy, with a timeout). Every run must end either with a
sensible result or with a clear one-line error; never NaN, never a crash:

==========================  ======================================================  ===========
case                        what it builds                                          expected
==========================  ======================================================  ===========
no_sfm_points_on_objects    the toy scene as is (its SfM points miss the drones),   ok
                            the suggested prompt
prompt_in_empty_sky         one box high above everything, in front of the          ok
                            backdrop, seen whole by most cameras, holding nothing
prompt_seen_by_two_cameras  a small box near one camera that exactly 2 training     ok
                            cameras see (found from the frusta)
box_larger_than_scene       one box 10x the scene extent (it holds the cameras)     ok
overlapping_boxes           the suggested box and a copy shifted by half its width  ok
prompt_seen_by_no_camera    a box straight above the scene, outside every frustum   clear error
very_short_runs             1 and 5 iterations                                      ok
extent_outlier_camera       one more camera 50x the ring radius away, looking at    ok
                            the scene (inflates the scene extent ~40x)
constant_colour_images      every image one constant colour                         ok
==========================  ======================================================  ===========

The baseline (``3dgs``) runs too where the prompt is not what is tested, so the table
compares. Outcome of a run: exit 0 → ``ok`` (metrics from ``RUN/metrics.json``), or
``nan`` when PSNR/SSIM is not finite; exit 2 with a ``promptgs: error: …`` line → ``clear
error``; anything else (a traceback, a signal, the timeout) → ``crash``. A run passes when
its outcome is the expected one and its case's checks hold (PSNR floors, bounds on the
Gaussian count, measured and justified above ``CHECKS``).

    promptgs stability --out runs/stability [--iterations 200] [--cases a b ...]

writes ``stability.json`` and ``stability.md`` in ``--out``, prints the table and exits 1
when a run failed.
"""

from __future__ import annotations

import argparse
import json
import math
import shutil
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Sequence

import numpy as np

from ..errors import PromptGSError
from .process import CLEAR_ERROR, CRASH, NAN, OK, classify, is_finite, run_logged  # the outcomes are this suite's too
from .toy_scene import ToySceneConfig, look_at, make_toy_scene


SIZES: dict[str, ToySceneConfig] = {
    # focal keeps the field of view of the default 256 x 192 / 220 scene
    # views: not a multiple of 8, so the outlier camera (sorting last) stays a training view
    "small": ToySceneConfig(width=96, height=72, focal=82.5, n_views=14, ground_grid=50, n_sfm_points=1200),
    "tiny": ToySceneConfig(width=64, height=48, focal=55.0, n_views=12, ground_grid=36, n_sfm_points=600),
}

OUTLIER_DISTANCE = 50.0  # x the ring radius
OUTLIER_IMAGE = "zz_outlier_far.png"  # sorts last: the test split (every 8th name) is unchanged
CONSTANT_COLOUR = (0.55, 0.35, 0.7)
SHORT_ITERATIONS = (1, 5)


@dataclass(frozen=True)
class Case:
    name: str
    dataset: str  # "base" | "outlier" | "constant"
    prompts: str  # key of the prompt file built for the case
    expected: str  # OK or CLEAR_ERROR
    baseline: bool  # also run 3dgs (the prompt is not what is tested)
    iterations: tuple[int, ...] | None = None  # fixed iteration counts, else the suite's


CASES: dict[str, Case] = {
    c.name: c
    for c in (
        Case("no_sfm_points_on_objects", "base", "suggested", OK, True),
        Case("prompt_in_empty_sky", "base", "sky", OK, False),
        Case("prompt_seen_by_two_cameras", "base", "two_cameras", OK, False),
        Case("box_larger_than_scene", "base", "huge", OK, False),
        Case("overlapping_boxes", "base", "overlapping", OK, False),
        Case("prompt_seen_by_no_camera", "base", "unseen", CLEAR_ERROR, False),
        Case("very_short_runs", "base", "suggested", OK, True, SHORT_ITERATIONS),
        Case("extent_outlier_camera", "outlier", "suggested", OK, True),
        Case("constant_colour_images", "constant", "suggested", OK, True),
    )
}


# -------------------------------------------------------------------------------------
# outcome of one process
# -------------------------------------------------------------------------------------


def run_command(cmd: Sequence[str], run_dir: Path | None, timeout: float, log_path: Path | None = None) -> dict:
    """Run ``cmd`` (output in ``log_path``), classify how it ended; adds ``seconds`` (wall
    clock) and ``returncode``."""
    result = run_logged(cmd, log_path, timeout)
    outcome = classify(result.returncode, result.output, run_dir, timeout)
    outcome.update(seconds=result.seconds, returncode=result.returncode)
    return outcome


# -------------------------------------------------------------------------------------
# datasets and prompt files
# -------------------------------------------------------------------------------------


def _box(center, size) -> dict:
    return {"center": [float(v) for v in center], "size": [float(v) for v in size], "rotation_wxyz": [1.0, 0.0, 0.0, 0.0], "weight": 1.0}


def build_outlier_dataset(base: Path, out: Path, distance: float = OUTLIER_DISTANCE) -> Path:
    """``base`` with one more camera ``distance`` x the ring radius away, looking at the
    scene centre; its image is a copy of a ring image (as a stray frame would be)."""
    import pycolmap

    cfg = json.loads((base / "scene.json").read_text())["config"]
    if cfg["n_views"] % 8 == 0:  # it would be the next test view (every 8th name)
        raise ValueError(f"the outlier camera needs a view count that is not a multiple of 8, got {cfg['n_views']}")
    shutil.copytree(base, out, ignore=shutil.ignore_patterns(".promptgs_cache"))
    rec = pycolmap.Reconstruction(str(base / "sparse/0"))
    r = distance * cfg["ring_radius"]
    center = np.array([r * math.cos(0.3), r * math.sin(0.3), cfg["ring_height"] * distance / 4])
    viewmat = look_at(center, np.array([0.0, 0.0, 0.6]))
    image_id = max(int(i) for i in rec.images) + 1
    image = pycolmap.Image(name=OUTLIER_IMAGE, camera_id=1, image_id=image_id)
    pose = pycolmap.Rigid3d(pycolmap.Rotation3d(viewmat[:3, :3]), viewmat[:3, 3])
    rec.add_image_with_trivial_frame(image, pose)
    rec.write_binary(str(out / "sparse/0"))
    first = sorted((base / "images").iterdir())[1]
    shutil.copy(first, out / "images" / OUTLIER_IMAGE)
    return out


def build_constant_dataset(base: Path, out: Path, colour=CONSTANT_COLOUR) -> Path:
    """``base`` with every image replaced by one constant colour (no objects left, so no
    object masks either)."""
    from PIL import Image

    shutil.copytree(base, out, ignore=shutil.ignore_patterns(".promptgs_cache", "object_masks", "gt_nodrones"))
    rgb = tuple(int(round(c * 255)) for c in colour)
    for path in sorted((out / "images").iterdir()):
        with Image.open(path) as im:
            size = im.size
        Image.new("RGB", size, rgb).save(path)
    return out


def sky_box(cameras, objects_top: float, extent: float) -> dict:
    """A box above the scene centre, as high as most training cameras still see it whole
    (between the top of the objects and the top of the views: no geometry in it)."""
    from ..prompts import PromptBox, project_box

    centers = np.stack([c.center.numpy() for c in cameras])
    cx, cy = centers[:, 0].mean(), centers[:, 1].mean()
    size = 0.08 * extent
    top = objects_top
    best = None
    for z in np.arange(top + size, centers[:, 2].max() + 2 * extent, 0.02 * extent):
        box = PromptBox((cx, cy, z), (size,) * 3)
        whole = sum(project_box(box, c).in_image_fraction > 0.999 for c in cameras)
        if whole >= max(3, len(cameras) // 2):
            best = z
    if best is None:
        raise RuntimeError("no sky box position found that most cameras see")
    return _box((cx, cy, best), (size,) * 3)


def _corners_in_image(points: np.ndarray, half: float, cameras) -> tuple[np.ndarray, np.ndarray]:
    """For boxes of half edge ``half`` centred at ``points`` [N, 3]: whether some corner /
    every corner projects into each camera's image, both [C, N]."""
    signs = np.array([[(i >> b & 1) * 2 - 1 for b in range(3)] for i in range(8)], dtype=np.float64)
    corners = points[:, None, :] + half * signs[None]  # [N, 8, 3]
    some, every = [], []
    for cam in cameras:
        w2c = cam.world_to_camera.double().numpy()
        K = cam.K.double().numpy()
        x = corners @ w2c[:3, :3].T + w2c[:3, 3]
        z = x[..., 2]
        uv = x[..., :2] / np.maximum(z, 1e-9)[..., None] * np.diag(K)[:2] + K[:2, 2]
        inside = (z > 0.01) & (uv[..., 0] >= 0) & (uv[..., 0] <= cam.width) & (uv[..., 1] >= 0) & (uv[..., 1] <= cam.height)
        some.append(inside.any(1))
        every.append(inside.all(1))
    return np.array(some), np.array(every)


def two_camera_box(cameras, extent: float, seed: int = 0) -> dict:
    """A small box that exactly two training cameras see, both whole, as near one of
    them as the frusta allow (at least a tenth of the extent in front of it): random
    positions around the camera ring, filtered by corner projections, then checked with
    the exact silhouettes of `prompts.project_box`."""
    from ..prompts import PromptBox, project_box

    size = 0.03 * extent
    centers = np.stack([c.center.double().numpy() for c in cameras])
    lo, hi = centers.min(0) - 0.3 * extent, centers.max(0) + 0.3 * extent
    lo[2] = min(lo[2], 0.0)
    points = np.random.default_rng(seed).uniform(lo, hi, size=(40_000, 3))
    some, every = _corners_in_image(points, size / 2, cameras)
    good = np.where((some.sum(0) == 2) & (every.sum(0) == 2))[0]
    dist = np.linalg.norm(points[good, None, :] - centers[None], axis=-1)  # [G, C]
    dist = np.where(every[:, good].T, dist, np.inf).min(1)
    order = [i for i in np.argsort(dist) if dist[i] >= 0.1 * extent]
    for i in order[:200]:
        box = PromptBox(tuple(points[good[i]]), (size,) * 3)
        proj = [project_box(box, cam) for cam in cameras]
        seen = [k for k, pr in enumerate(proj) if pr.visible_area > 0]
        if len(seen) == 2 and all(proj[k].in_image_fraction > 0.999 for k in seen):
            return _box(points[good[i]], (size,) * 3)
    raise RuntimeError("no box position found that exactly two cameras see")


def build_prompts(base: Path, folder: Path) -> dict[str, Path]:
    """The prompt files of the cases, from the toy scene's cameras; name → path."""
    from ..data import load_colmap_scene
    from ..prompts import PromptBox, check_visible, contains_any, prompts_from_json

    scene = load_colmap_scene(base)
    cams = scene.train_cameras
    suggested = json.loads((base / "prompts_1.json").read_text())["prompts"][0]
    centers = np.stack([c.center.numpy() for c in cams])
    mid = centers.mean(0)
    half = dict(suggested)
    half["center"] = [suggested["center"][0] + suggested["size"][0] / 2, *suggested["center"][1:]]
    unseen = _box((mid[0], mid[1], centers[:, 2].max() + 3 * scene.extent), (0.1 * scene.extent,) * 3)
    boxes = {
        "suggested": [suggested],
        "sky": [sky_box(cams, suggested["center"][2] + suggested["size"][2] / 2, scene.extent)],
        "two_cameras": [two_camera_box(cams, scene.extent)],
        "huge": [_box(mid, (10 * scene.extent,) * 3)],
        "overlapping": [suggested, half],
        "unseen": [unseen],
    }
    # The geometry the cases rely on, checked here so a changed toy scene cannot make a
    # case silently test something else.
    from ..errors import PromptError

    try:
        check_visible([PromptBox(**unseen)], cams)
        raise RuntimeError("the 'unseen' box is seen by a camera")
    except PromptError:
        pass
    if contains_any(prompts_from_json({"prompts": boxes["sky"]}), scene.points).any():
        raise RuntimeError("the 'sky' box holds SfM points")
    if len(check_visible(prompts_from_json({"prompts": boxes["two_cameras"]}), cams)[0]) != 2:
        raise RuntimeError("the 'two_cameras' box is not seen by exactly two cameras")
    folder.mkdir(parents=True, exist_ok=True)
    paths = {}
    for name, entries in boxes.items():
        paths[name] = folder / f"{name}.json"
        paths[name].write_text(json.dumps({"prompts": entries}, indent=2) + "\n")
    return paths


def build_datasets(work: Path, size: str, needed: set[str]) -> dict[str, Path]:
    if size not in SIZES:
        raise PromptGSError(f"unknown size {size!r} (choose {', '.join(SIZES)})")
    data = work / "datasets"
    if data.exists():
        shutil.rmtree(data)
    base = make_toy_scene(data / "base", SIZES[size])
    out = {"base": base}
    if "outlier" in needed:
        out["outlier"] = build_outlier_dataset(base, data / "extent_outlier")
        from ..data import load_colmap_scene

        before, after = load_colmap_scene(base).extent, load_colmap_scene(out["outlier"]).extent
        if after < 10 * before:  # the case would not test what it says
            raise RuntimeError(f"the outlier camera inflates the extent only from {before:.2f} to {after:.2f}")
    if "constant" in needed:
        out["constant"] = build_constant_dataset(base, data / "constant_colour")
    return out


# -------------------------------------------------------------------------------------
# checks beyond the outcome
# -------------------------------------------------------------------------------------


def _find(rows: list[dict], case: str, strategy: str, iterations: int) -> dict | None:
    for r in rows:
        if (r["case"], r["strategy"], r["iterations"], r["outcome"]) == (case, strategy, iterations, OK):
            return r
    return None


def _reference(row: dict, rows: list[dict]) -> dict | None:
    """The same strategy and length on the unmodified scene with the suggested prompt."""
    return _find(rows, "no_sfm_points_on_objects", row["strategy"], row["iterations"])


# Bounds of the checks. Measured on the toy scene (tiny: 64x48, 30 steps; small, the
# default: 96x72, 200 steps; 3dgs / promptgs), with the margin each leaves:
#
# * extent_outlier_camera: PSNR vs the unmodified scene +2.7 / +2.7 dB (tiny), +4.2 /
#   +4.1 dB (small). The ~40x extent multiplies the position learning rate and the
#   split / prune size thresholds (which speeds up these short runs); it must not cost
#   more than OUTLIER_MAX_DROP_DB.
# * constant_colour_images: PSNR over the untrained start +2.6 dB (tiny), +7.7 / +8.4 dB
#   (small; the SH colour learning rate of 3DGS needs ~500 steps to move a colour by
#   0.35, so 200 steps do not reach the constant). Gaussians vs the textured scene:
#   1.02 / 0.87 (tiny); small, with the far background shell: 1.25 / 1.26 (3DGS's growth
#   rule in both). The SfM points keep the textured scene's colours, so every one must
#   be recoloured and its gradients drive growth; a runaway would be far beyond 1.5x.
# * prompt_in_empty_sky: Gaussians inside the empty box 13 % (tiny), 7 % (small) of all
#   (3dgs puts none there: resampling carves a few hundred points early, when the whole
#   render is wrong, and prompt-prioritised growth multiplies them); PSNR +0.3 / +0.9 dB
#   vs the suggested prompt: the box must not fill up nor spoil the views.
# * box_larger_than_scene: everything is inside the prompt, so growth runs at the
#   lowered prompt threshold everywhere: 1.12x (tiny), 2.9x (small) the Gaussians of
#   the suggested prompt (2.2x the 3dgs count), 2.1x its time. A runaway would be far
#   beyond 4x.
MIN_GAIN_DB = 1.0  # over the untrained start
OUTLIER_MAX_DROP_DB = 1.0
CONSTANT_MAX_COUNT_RATIO = 1.5
EMPTY_BOX_MAX_FRACTION = 0.25
EMPTY_BOX_MAX_DROP_DB = 1.0
HUGE_BOX_MAX_COUNT_RATIO = 4.0


def _check_outlier(row: dict, rows: list[dict], ctx: dict) -> str | None:
    ref = _reference(row, rows)
    if ref is not None and row["psnr"] < ref["psnr"] - OUTLIER_MAX_DROP_DB:
        return f"PSNR {row['psnr']:.2f} is more than {OUTLIER_MAX_DROP_DB:g} dB below the unmodified scene's {ref['psnr']:.2f}"
    return None


def _check_constant(row: dict, rows: list[dict], ctx: dict) -> str | None:
    start = ctx["start_psnr"]["constant"]
    if row["psnr"] < start + MIN_GAIN_DB:
        return f"PSNR {row['psnr']:.2f} is not {MIN_GAIN_DB:g} dB above the untrained start ({start:.2f})"
    ref = _reference(row, rows)
    if ref is not None and row["n_gaussians"] > CONSTANT_MAX_COUNT_RATIO * ref["n_gaussians"]:
        return f"{row['n_gaussians']} Gaussians on constant images, over {CONSTANT_MAX_COUNT_RATIO:g}x the textured scene's {ref['n_gaussians']}"
    return None


def _check_sky(row: dict, rows: list[dict], ctx: dict) -> str | None:
    inside, total = _gaussians_inside(Path(row["run_dir"]), ctx["prompts"]["sky"])
    row["inside_prompt"] = inside
    if inside > EMPTY_BOX_MAX_FRACTION * total:
        return f"{inside} of {total} Gaussians inside the empty prompt"
    ref = _reference(row, rows)
    if ref is not None and row["psnr"] < ref["psnr"] - EMPTY_BOX_MAX_DROP_DB:
        return f"PSNR {row['psnr']:.2f} is more than {EMPTY_BOX_MAX_DROP_DB:g} dB below the suggested prompt's {ref['psnr']:.2f}"
    return None


def _check_huge(row: dict, rows: list[dict], ctx: dict) -> str | None:
    ref = _reference(row, rows)
    if ref is not None and row["n_gaussians"] > HUGE_BOX_MAX_COUNT_RATIO * ref["n_gaussians"]:
        return f"{row['n_gaussians']} Gaussians, over {HUGE_BOX_MAX_COUNT_RATIO:g}x the {ref['n_gaussians']} with the suggested prompt"
    return None


def _gaussians_inside(run_dir: Path, prompt_file: Path) -> tuple[int, int]:
    from ..gaussians import load_ply
    from ..prompts import contains_any, load_prompts

    means = load_ply(run_dir / "point_cloud.ply")["means"].detach()
    return int(contains_any(load_prompts(prompt_file), means).sum()), int(means.shape[0])


def start_psnr(dataset: Path) -> float:
    """Test-view PSNR of the untrained Gaussians (the trainer's initialisation from the
    SfM points, default settings)."""
    from ..config import TrainConfig
    from ..data import load_colmap_scene
    from ..evaluation import evaluate
    from ..gaussians import init_from_points

    cfg = TrainConfig(dataset=str(dataset), out="")
    scene = load_colmap_scene(dataset)
    params = init_from_points(scene.points, scene.point_colors, sh_degree=cfg.sh_degree, init_opacity=cfg.init_opacity)
    return float(evaluate(params, scene.test_cameras, backend="cpu", quiet=True)["psnr"])


CHECKS: dict[str, Callable[[dict, list[dict], dict], str | None]] = {
    "extent_outlier_camera": _check_outlier,
    "constant_colour_images": _check_constant,
    "prompt_in_empty_sky": _check_sky,
    "box_larger_than_scene": _check_huge,
}


# -------------------------------------------------------------------------------------
# the suite
# -------------------------------------------------------------------------------------


def _select(cases: list[str] | None) -> list[Case]:
    if not cases:
        return list(CASES.values())
    names = [n for item in cases for n in item.split(",") if n]
    unknown = [n for n in names if n not in CASES]
    if unknown:
        raise PromptGSError(f"unknown stability case(s) {', '.join(unknown)} (available: {', '.join(CASES)})")
    return [CASES[n] for n in CASES if n in names]


def run_stability(
    out: Path,
    iterations: int = 200,
    cases: list[str] | None = None,
    strategies: Sequence[str] = ("3dgs", "promptgs"),
    size: str = "small",
    timeout: float | None = None,
    progress: Callable[[dict], None] | None = None,
) -> list[dict]:
    """Run the cases (all by default) and write ``out/stability.json`` and
    ``out/stability.md``; returns one row per (case, strategy, iterations)."""
    out = Path(out).resolve()
    selected = _select(cases)
    if iterations < 1:
        raise PromptGSError(f"--iterations must be at least 1, got {iterations}")
    from ..strategies import STRATEGY_NAMES

    unknown = [s for s in strategies if s not in STRATEGY_NAMES]
    if unknown:
        raise PromptGSError(f"unknown strategy {', '.join(unknown)} (use {', '.join(STRATEGY_NAMES)})")
    out.mkdir(parents=True, exist_ok=True)
    datasets = build_datasets(out, size, {c.dataset for c in selected})
    prompts = build_prompts(datasets["base"], out / "prompts")
    ctx = {"prompts": prompts, "start_psnr": {name: start_psnr(path) for name, path in datasets.items()}}
    for sub in ("jobs", "logs", "runs"):
        (out / sub).mkdir(exist_ok=True)
    rows: list[dict] = []
    for case in selected:
        for strategy in strategies:
            if strategy != "promptgs" and not case.baseline:
                continue
            for iters in case.iterations or (iterations,):
                tag = f"{case.name}-{strategy}-i{iters}"
                run_dir = out / "runs" / tag
                job = {
                    "dataset": str(datasets[case.dataset]),
                    "out": str(run_dir),
                    "iterations": iters,
                    "strategy": strategy,
                    "checkpoint_every": 0,
                    "seed": 0,
                }
                if strategy == "promptgs":
                    job["prompts"] = str(prompts[case.prompts])
                job_path = out / "jobs" / f"{tag}.json"
                job_path.write_text(json.dumps(job, indent=2))
                cmd = [sys.executable, "-m", "promptgs_engine", "train", "--job", str(job_path), "--quiet", "--overwrite"]
                limit = timeout if timeout is not None else 120.0 + 3.0 * iters
                result = run_command(cmd, run_dir, limit, out / "logs" / f"{tag}.log")
                row = _row(case, strategy, iters, run_dir, result)
                row["start_psnr"] = ctx["start_psnr"][case.dataset]
                row["expected"] = case.expected
                problem = None
                if row["outcome"] == OK and case.name in CHECKS:
                    try:
                        problem = CHECKS[case.name](row, rows, ctx)
                    except Exception as exc:  # an unreadable result fails the run, not the suite
                        problem = f"check raised {type(exc).__name__}: {exc}"
                row["check"] = problem
                row["passed"] = row["outcome"] == case.expected and problem is None
                rows.append(row)
                # written after every run, so an interrupted suite keeps what it measured
                (out / "stability.json").write_text(json.dumps(rows, indent=2))
                (out / "stability.md").write_text(table(rows) + "\n")
                if progress is not None:
                    progress(row)
    return rows


def _row(case: Case, strategy: str, iters: int, run_dir: Path, result: dict) -> dict:
    m = result.get("metrics") or {}
    return {
        "case": case.name,
        "strategy": strategy,
        "iterations": iters,
        "outcome": result["outcome"],
        "psnr": m.get("psnr"),
        "ssim": m.get("ssim"),
        "n_gaussians": m.get("n_gaussians"),
        "sky_points": m.get("sky_points"),
        "seconds": round(result["seconds"], 2),
        "message": result["message"],
        "returncode": result["returncode"],
        "run_dir": str(run_dir),
    }


def table(rows: list[dict]) -> str:
    lines = [
        "| case | strategy | iterations | outcome | PSNR | Gaussians | seconds | message | passed |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        psnr = f"{r['psnr']:.2f}" if is_finite(r.get("psnr")) else "-"
        n = str(r["n_gaussians"]) if r.get("n_gaussians") is not None else "-"
        message = r["message"]
        if r.get("check"):
            message = (message + "; " if message else "") + "check failed: " + r["check"]
        message = message.replace("|", "\\|")
        lines.append(
            f"| {r['case']} | {r['strategy']} | {r['iterations']} | {r['outcome']} | {psnr} | {n} "
            f"| {r['seconds']:.1f} | {message} | {'yes' if r['passed'] else 'no'} |"
        )
    return "\n".join(lines)


# -------------------------------------------------------------------------------------
# command line
# -------------------------------------------------------------------------------------


def add_parser(subparsers: Any) -> None:
    """Register the ``stability`` subcommand on an argparse subparsers object."""
    p = subparsers.add_parser(
        "stability",
        help="run the stability suite (inputs where 3DGS training breaks) on the toy scene",
        description="Train variants of the embedded toy scene that are known to break 3DGS-style training "
        "(no SfM points on the objects, odd prompts, very short runs, an outlier camera, constant images), "
        "each in its own process; every run must end with a sensible result or a one-line error.",
    )
    p.add_argument("--out", type=Path, default=Path("runs/stability"), help="work folder (default runs/stability)")
    p.add_argument("--iterations", type=int, default=200, help="training steps per run (default 200)")
    p.add_argument("--cases", nargs="+", help=f"cases to run (default all): {', '.join(CASES)}")
    p.add_argument("--size", default="small", choices=list(SIZES), help="toy scene size (default small)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run ``promptgs stability``; 0 when every run passed, 1 when one failed, 2 for bad input."""

    def show(row: dict) -> None:
        psnr = f"{row['psnr']:.2f}" if is_finite(row.get("psnr")) else "-"
        flag = "" if row["passed"] else "  FAILED"
        print(f"{row['case']} {row['strategy']} i{row['iterations']}: {row['outcome']} psnr={psnr} ({row['seconds']:.1f} s){flag}", flush=True)

    try:
        rows = run_stability(args.out, iterations=args.iterations, cases=args.cases, size=args.size, progress=show)
    except PromptGSError as exc:
        print(f"promptgs: error: {exc}", file=sys.stderr)
        return 2
    print(table(rows))
    failed = [r for r in rows if not r["passed"]]
    print(f"{len(rows) - len(failed)} of {len(rows)} runs passed; results: {Path(args.out) / 'stability.json'}")
    return 1 if failed else 0


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="promptgs")
    add_parser(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
