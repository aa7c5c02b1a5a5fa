"""Structure from motion with pycolmap: photos or a video in, a trainer-ready dataset out.

    DATASET/
      images/             undistorted images (PINHOLE cameras)
      sparse/0/           the COLMAP model of the largest reconstruction, PINHOLE
      sfm_summary.json    images registered / given, points, reprojection error, times
      colmap/             working files, kept so that a re-run resumes:
        database.db       features and matches (a re-run skips what it already holds)
        options.json      the settings the features were made with
        frames/           the frames taken from a video
        models/N/         every model the incremental mapper built, before undistortion
        models-global/N/  the global mapper's models, when it ran
        colmap-*          pycolmap's own log, one file per run

Stages: frames (video only) → features (SIFT) → matching (exhaustive or sequential, then
geometric verification) → mapping (incremental, or global where incremental mapping leaves
images out) → undistortion. pycolmap is called in chunks so each stage shows how far it is.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import threading
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from PIL import Image

from ..data.images import image_size
from ..errors import DatasetError, PromptGSError
from ..events import EventWriter
from .inputs import input_kind, list_images
from .pairs import choose_matcher, exhaustive_pairs, sequential_pairs
from .progress import STAGES, Reporter
from .video import extract_frames, probe_video

WORK = "colmap"
SUMMARY = "sfm_summary.json"
CAMERA_MODELS = (
    "SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV",
    "SIMPLE_RADIAL_FISHEYE", "RADIAL_FISHEYE", "OPENCV_FISHEYE", "THIN_PRISM_FISHEYE",
)
# Thumbnails: images whose longer side (as features are found on them) is below
# SMALL_IMAGE_PX. COLMAP's defaults suit images of a thousand pixels or more, with
# thousands of features each; on a 200x150 thumbnail they are both too strict (a few
# hundred features, so 30 2D-3D inliers to register an image is a tenth of them) and too
# loose (a 4 px epipolar tolerance is 2% of the image), and they make few SfM points.
# Measured on tumbler's 200x150 photos (docs/sfm.md): COLMAP's defaults register 21 of
# 77; the lower peak threshold 38; all of the settings below 57 at the same camera
# accuracy, and the two-view tracks raise the points from about 1,100 to 1,800.
SMALL_IMAGE_PX = 400
SMALL_IMAGE_PEAK_THRESHOLD = 0.002  # SIFT peak threshold (COLMAP: 1/150)
SMALL_IMAGE_MAX_RATIO = 0.85  # Lowe's ratio test (COLMAP: 0.8)
SMALL_IMAGE_RANSAC_PX = 1.5  # two-view geometry's RANSAC tolerance in pixels (COLMAP: 4)
SMALL_IMAGE_MIN_POSE_INLIERS = 12  # 2D-3D inliers to register an image (COLMAP: 30)
SMALL_IMAGE_MIN_POSE_INLIER_RATIO = 0.1  # and their fraction (COLMAP: 0.25)
# `--mapper auto`: incremental mapping first (the more accurate cameras where it ties every
# image into one model); when it leaves more than this fraction of the images out, global
# mapping (GLOMAP, in pycolmap) runs on the same matches and its model is kept if it
# registers more. Incremental mapping grows one model image by image and stops at a weak
# link: on tumbler's 200x150 photos a jump to a top-down view splits the photos 57 / 18,
# which the global mapper, solving every rotation and position at once, ties into 75
# (docs/sfm.md).
AUTO_GLOBAL_BELOW = 0.9
MAPPERS = ("auto", "incremental", "global")


@dataclass
class SfmOptions:
    """Settings of one SfM run (the `promptgs sfm` options)."""

    max_image_size: int | None = 1600  # longer side of the images features are found on and written at
    camera_model: str = "SIMPLE_RADIAL"
    camera_mode: str = "auto"  # auto | single | per-image
    matcher: str = "auto"  # auto | exhaustive | sequential
    mapper: str = "auto"  # auto | incremental | global
    overlap: int = 10  # sequential: neighbours each image is matched with
    fps: float = 2.0  # video: frames kept per second
    max_frames: int | None = None  # video: stop after this many frames
    min_registered: float = 0.5  # fewer registered images than this fraction of the given ones is an error
    max_features: int = 8192
    seed: int = 0
    num_threads: int = -1  # -1: all cores

    def validate(self) -> None:
        if isinstance(self.num_threads, bool) or not isinstance(self.num_threads, int) or not (self.num_threads == -1 or self.num_threads >= 1):
            raise PromptGSError(f"--threads must be a positive whole number (or -1: every core), got {self.num_threads!r}")
        if self.camera_model not in CAMERA_MODELS:
            raise PromptGSError(f"camera model {self.camera_model!r} is not one of {', '.join(CAMERA_MODELS)}")
        if self.camera_mode not in ("auto", "single", "per-image"):
            raise PromptGSError(f"camera mode {self.camera_mode!r} is not one of auto, single, per-image")
        if self.matcher not in ("auto", "exhaustive", "sequential"):
            raise PromptGSError(f"matcher {self.matcher!r} is not one of auto, exhaustive, sequential")
        if self.mapper not in MAPPERS:
            raise PromptGSError(f"mapper {self.mapper!r} is not one of {', '.join(MAPPERS)}")
        if self.max_image_size is not None and self.max_image_size < 32:
            raise PromptGSError(f"--max-image-size must be at least 32 pixels, got {self.max_image_size}")
        if self.overlap < 1:
            raise PromptGSError(f"--overlap must be at least 1, got {self.overlap}")
        if not 0.0 <= self.min_registered <= 1.0:
            raise PromptGSError(f"--min-registered is a fraction in [0, 1], got {self.min_registered}")

    def feature_settings(self) -> dict:
        """The settings stored features depend on: a re-run with others starts over."""
        return {"max_image_size": self.max_image_size, "camera_model": self.camera_model, "camera_mode": self.camera_mode, "max_features": self.max_features}


def is_sfm_output(folder: Path) -> bool:
    return (folder / WORK / "options.json").is_file() or (folder / SUMMARY).is_file()


def finished_summary(folder: Path) -> dict | None:
    """The summary of a finished SfM output folder, or None."""
    try:
        summary = json.loads((folder / SUMMARY).read_text())
    except (OSError, json.JSONDecodeError):
        return None
    ok = summary.get("status") == "ok" and (folder / "sparse" / "0").is_dir() and (folder / "images").is_dir()
    return summary if ok else None


def _prepare_out(input_path: Path, out: Path, overwrite: bool) -> None:
    if out.resolve() == input_path.resolve() or input_path.resolve() in out.resolve().parents:
        raise PromptGSError(f"{out}: the output folder must lie outside the input {input_path}")
    if out.exists() and not out.is_dir():
        raise PromptGSError(f"{out}: exists and is not a folder")
    if out.is_dir() and any(out.iterdir()) and not is_sfm_output(out):
        raise PromptGSError(f"{out}: exists, is not empty and holds no earlier sfm output (give a new or empty folder)")
    if overwrite and out.is_dir():
        for name in (WORK, "images", "sparse", SUMMARY):
            p = out / name
            if p.is_dir():
                shutil.rmtree(p)
            elif p.exists():
                p.unlink()
    out.mkdir(parents=True, exist_ok=True)


def _check_feature_settings(work: Path, settings: dict) -> None:
    path = work / "options.json"
    if path.is_file():
        try:
            saved = json.loads(path.read_text())
        except (OSError, json.JSONDecodeError):
            saved = None
        if saved is not None and saved != settings:
            diff = ", ".join(f"{k} {saved.get(k)} (now {v})" for k, v in settings.items() if saved.get(k) != v)
            raise PromptGSError(
                f"{work.parent}: holds features made with other settings ({diff}); use --overwrite to start over, or the same settings to resume"
            )
    work.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(settings, indent=2))


def _exif_focal(path: Path) -> float | None:
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            value = exif.get_ifd(0x8769).get(0x920A) or exif.get(0x920A)
    except (OSError, ValueError):
        return None
    return float(value) if value else None


def _camera_mode(options: SfmOptions, kind: str, image_dir: Path, names: list[str]) -> str:
    """single or per-image. `auto`: one shared camera for a video, or for photos of one
    size and one EXIF focal length; one per image otherwise."""
    sizes = {image_size(image_dir / n) for n in names}
    if options.camera_mode == "single":
        if len(sizes) > 1:
            raise PromptGSError(f"{image_dir}: --single-camera needs images of one size, found {len(sizes)} sizes ({', '.join(f'{w}x{h}' for w, h in sorted(sizes)[:3])}…)")
        return "single"
    if options.camera_mode == "per-image":
        return "per-image"
    if kind == "video":
        return "single"
    focals = {_exif_focal(image_dir / n) for n in names}
    return "single" if len(sizes) == 1 and len(focals) == 1 else "per-image"


class _ColmapLog:
    """Sends pycolmap's log to a file for the run (the terminal keeps only its errors)."""

    def __init__(self, path: Path):
        self.path = path

    def __enter__(self):
        import pycolmap

        lg = pycolmap.logging
        self.saved = (lg.minloglevel, lg.stderrthreshold, lg.logtostderr, lg.alsologtostderr)
        lg.logtostderr = False
        lg.alsologtostderr = False
        lg.stderrthreshold = lg.ERROR
        lg.set_log_destination(lg.INFO, str(self.path))
        lg.minloglevel = lg.INFO
        return self

    def __exit__(self, *exc):
        import pycolmap

        lg = pycolmap.logging
        lg.minloglevel, lg.stderrthreshold, lg.logtostderr, lg.alsologtostderr = self.saved
        return False


class _Cancellable:
    """Ctrl-C (SIGINT, the add-on's Cancel) during a long pycolmap call: ask pycolmap to
    stop through its cancellation token, then raise KeyboardInterrupt when it returns.
    Python runs the handler when pycolmap calls back (each registered image)."""

    def __init__(self, pycolmap):
        self.token = pycolmap.CancellationToken()
        self.cancelled = False

    def _handler(self, signum, frame) -> None:
        self.cancelled = True
        self.token.cancel()

    def __enter__(self) -> "_Cancellable":
        self.previous = signal.signal(signal.SIGINT, self._handler) if threading.current_thread() is threading.main_thread() else None
        return self

    def __exit__(self, exc_type, exc, tb) -> bool:
        if self.previous is not None:
            signal.signal(signal.SIGINT, self.previous)
        if self.cancelled and (exc_type is None or issubclass(exc_type, InterruptedError)):
            raise KeyboardInterrupt from None  # pycolmap ends a cancelled call with InterruptedError
        return False


def _chunks(items: list, size: int) -> list[list]:
    return [items[i : i + size] for i in range(0, len(items), size)]


def _thumbnails(longest: int, options: SfmOptions) -> bool:
    """Whether features are found on images smaller than SMALL_IMAGE_PX (see above)."""
    cap = options.max_image_size
    return min(longest, cap or longest) < SMALL_IMAGE_PX


def _extract(pycolmap, db: Path, image_dir: Path, names: list[str], options: SfmOptions, camera: str, thumbnails: bool, reporter: Reporter) -> int:
    """SIFT features of every image not yet in the database; returns how many were already there."""
    existing = 0
    camera_id = -1
    if db.is_file():
        database = pycolmap.Database.open(str(db))
        try:
            have = {im.name: im for im in database.read_all_images()}
            existing = sum(1 for n in names if n in have and database.exists_keypoints(have[n].image_id))
            if camera == "single" and have:
                camera_id = next(iter(have.values())).camera_id
        finally:
            database.close()
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = options.camera_model
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = options.num_threads
    extraction.sift.max_num_features = options.max_features
    cap = options.max_image_size
    if thumbnails:
        extraction.sift.peak_threshold = SMALL_IMAGE_PEAK_THRESHOLD
    if cap is not None:
        extraction.max_image_size = cap
    mode = pycolmap.CameraMode.SINGLE if camera == "single" else pycolmap.CameraMode.PER_IMAGE
    chunk = max(4, -(-len(names) // 50))
    with reporter.stage("features", len(names), "img", detail=f"SIFT, camera {options.camera_model} {camera}") as stage:
        stage.set(0)
        for part in _chunks(names, chunk):
            if camera_id >= 0:
                reader.existing_camera_id = camera_id
            pycolmap.extract_features(str(db), str(image_dir), image_names=part, camera_mode=mode, reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu)
            if camera == "single" and camera_id < 0:
                database = pycolmap.Database.open(str(db))
                try:
                    cams = database.read_all_cameras()
                finally:
                    database.close()
                if cams:
                    camera_id = cams[0].camera_id
            stage.advance(len(part))
    return existing


def _match(pycolmap, db: Path, work: Path, names: list[str], matcher: str, options: SfmOptions, thumbnails: bool, reporter: Reporter) -> tuple[int, int]:
    """Match the chosen pairs (pairs already matched are skipped by pycolmap); returns the
    pair count and how many of them were already matched."""
    n = len(names)
    pairs = exhaustive_pairs(n) if matcher == "exhaustive" else sequential_pairs(n, options.overlap)
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = options.num_threads
    verification = pycolmap.TwoViewGeometryOptions()
    if thumbnails:
        matching.sift.max_ratio = SMALL_IMAGE_MAX_RATIO
        verification.ransac.max_error = SMALL_IMAGE_RANSAC_PX
    chunk = max(50, -(-len(pairs) // 50))
    pair_file = work / "pairs.txt"
    reused = _pairs_already_matched(pycolmap, db, names, pairs)
    with reporter.stage("matching", len(pairs), "pair", detail=f"{matcher}, {len(pairs)} pairs") as stage:
        stage.set(0)
        for part in _chunks(pairs, chunk):
            pair_file.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in part))
            pycolmap.match_image_pairs(
                str(db), matching_options=matching, pairing_options=pycolmap.ImportedPairingOptions(match_list_path=str(pair_file)),
                verification_options=verification, device=pycolmap.Device.cpu,
            )
            stage.advance(len(part))
    pair_file.unlink(missing_ok=True)
    return len(pairs), reused


def _pairs_already_matched(pycolmap, db: Path, names: list[str], pairs: list[tuple[int, int]]) -> int:
    """How many of `pairs` the database already holds matches for (a resumed run)."""
    database = pycolmap.Database.open(str(db))
    try:
        ids = {im.name: im.image_id for im in database.read_all_images()}
        return sum(1 for i, j in pairs if database.exists_matches(ids[names[i]], ids[names[j]]))
    finally:
        database.close()


def _empty_folder(folder: Path) -> None:
    """`folder`, emptied of an earlier run's models."""
    if folder.exists():
        shutil.rmtree(folder)
    folder.mkdir(parents=True)


def _largest(recs: dict):
    """(id, model) of the model with the most registered images, then the most points."""
    return max(recs.items(), key=lambda kv: (kv[1].num_reg_images(), kv[1].num_points3D()))


def _incremental_options(pycolmap, options: SfmOptions, thumbnails: bool):
    """COLMAP's incremental mapping and triangulation settings, with the thumbnail ones."""
    pipeline = pycolmap.IncrementalPipelineOptions()
    pipeline.num_threads = options.num_threads
    if thumbnails:
        pipeline.mapper.abs_pose_min_num_inliers = SMALL_IMAGE_MIN_POSE_INLIERS
        pipeline.mapper.abs_pose_min_inlier_ratio = SMALL_IMAGE_MIN_POSE_INLIER_RATIO
        pipeline.triangulation.ignore_two_view_tracks = False  # points seen by two images are kept too
    pipeline.random_seed = options.seed
    return pipeline


def _map(pycolmap, db: Path, image_dir: Path, models_dir: Path, n: int, options: SfmOptions, thumbnails: bool, reporter: Reporter):
    """Incremental mapping; returns the largest model (most registered images) and the model count."""
    _empty_folder(models_dir)
    pipeline = _incremental_options(pycolmap, options, thumbnails)
    pycolmap.set_random_seed(options.seed)
    models = [0]

    def new_model() -> None:
        # Each model starts from a pair of images; the bar counts the current model's images.
        models[0] += 1
        stage.note(f"model {models[0]}")
        stage.set(2)

    with reporter.stage("mapping", n, "img", detail="incremental") as stage, _Cancellable(pycolmap) as cancel:
        stage.set(0)
        recs = pycolmap.incremental_mapping(
            str(db), str(image_dir), str(models_dir), pipeline,
            initial_image_pair_callback=new_model,
            next_image_callback=lambda: stage.advance(1),
            cancellation_token=cancel.token,
        )
    if not recs:
        return None, 0, None
    best_id, best = _largest(recs)
    return best, len(recs), models_dir / str(best_id)


def _map_global(pycolmap, db: Path, image_dir: Path, models_dir: Path, n: int, options: SfmOptions, thumbnails: bool, reporter: Reporter, why: str = ""):
    """Global mapping (GLOMAP: rotation averaging, global positioning, bundle adjustment),
    then COLMAP's triangulation on the largest model's cameras; returns that model and the
    model count. pycolmap reports nothing until it returns (seconds for a hundred images),
    and Ctrl-C takes effect then.

    GLOMAP keeps the points of tracks it could use for positioning (three views or more);
    the triangulator, with the cameras fixed, adds the rest as the incremental mapper would:
    GLOMAP's points alone are too few to start training from (docs/sfm.md)."""
    _empty_folder(models_dir)
    pipeline = pycolmap.GlobalPipelineOptions()
    pipeline.num_threads = pipeline.mapper.num_threads = options.num_threads
    pipeline.random_seed = pipeline.mapper.random_seed = options.seed
    pipeline.mapper.global_positioning.use_gpu = False  # the pycolmap wheels are CPU builds
    pipeline.mapper.bundle_adjustment.ceres.use_gpu = False
    pycolmap.set_random_seed(options.seed)
    with reporter.stage("mapping", n, "img", detail="global" + (f" ({why})" if why else "")) as stage, _Cancellable(pycolmap):
        stage.set(0)
        recs = pycolmap.global_mapping(str(db), str(image_dir), str(models_dir), pipeline)
        if not recs:
            return None, 0, None
        best_id, best = _largest(recs)
        stage.set(best.num_reg_images())
        stage.note("triangulating")
        best_dir = models_dir / str(best_id)
        best = pycolmap.triangulate_points(best, str(db), str(image_dir), str(best_dir), clear_points=False,
                                           options=_incremental_options(pycolmap, options, thumbnails), refine_intrinsics=False)
    return best, len(recs), best_dir


def _map_chosen(pycolmap, db: Path, image_dir: Path, work: Path, n: int, options: SfmOptions, thumbnails: bool, reporter: Reporter):
    """The mapper(s) `options.mapper` asks for; returns (model, model count, its folder,
    the mapper whose model it is, images registered by each mapper that ran). The folder of
    a mapper that does not run is removed, so `colmap/` holds only this run's models."""
    tried: dict[str, int] = {}
    best, n_models, model_dir, used = None, 0, None, None
    if options.mapper == "global":
        shutil.rmtree(work / "models", ignore_errors=True)
    else:
        best, n_models, model_dir = _map(pycolmap, db, image_dir, work / "models", n, options, thumbnails, reporter)
        used = "incremental"
        tried["incremental"] = int(best.num_reg_images()) if best is not None else 0
    run_global = options.mapper == "global" or (options.mapper == "auto" and tried["incremental"] < AUTO_GLOBAL_BELOW * n)
    if not run_global:
        shutil.rmtree(work / "models-global", ignore_errors=True)
        return best, n_models, model_dir, used, tried
    why = f"incremental registered {tried['incremental']} of {n}" if tried else ""
    g_best, g_models, g_dir = _map_global(pycolmap, db, image_dir, work / "models-global", n, options, thumbnails, reporter, why)
    tried["global"] = int(g_best.num_reg_images()) if g_best is not None else 0
    if g_best is not None and tried["global"] > tried.get("incremental", 0):
        best, n_models, model_dir, used = g_best, g_models, g_dir, "global"
    return best, n_models, model_dir, used, tried


def _undistort(pycolmap, model_dir: Path, image_dir: Path, out: Path, n: int, options: SfmOptions, reporter: Reporter) -> None:
    """Undistort the model to PINHOLE cameras into `out/images` and `out/sparse/0`."""
    staging = out / WORK / "undistorted"
    if staging.exists():
        shutil.rmtree(staging)
    undistort = pycolmap.UndistortCameraOptions()
    if options.max_image_size is not None:
        undistort.max_image_size = options.max_image_size
    with reporter.stage("undistortion", n, "img", detail="PINHOLE") as stage:
        stage.set(0)
        pycolmap.undistort_images(str(staging), str(model_dir), str(image_dir), output_type="COLMAP", undistort_options=undistort, num_threads=options.num_threads)
        stage.set(n)
    for name in ("images", "sparse"):
        if (out / name).exists():
            shutil.rmtree(out / name)
    (staging / "images").rename(out / "images")
    (out / "sparse").mkdir()
    (staging / "sparse").rename(out / "sparse" / "0")
    shutil.rmtree(staging)


def _summary_of(rec, n_given: int) -> dict:
    cams = rec.cameras
    return {
        "images_given": n_given,
        "images_registered": int(rec.num_reg_images()),
        "registered_fraction": round(rec.num_reg_images() / max(1, n_given), 4),
        "points": int(rec.num_points3D()),
        "mean_reprojection_error_px": float(rec.compute_mean_reprojection_error()),
        "mean_track_length": float(rec.compute_mean_track_length()),
        "cameras": len(cams),
    }


def run_sfm(
    input_path: str | Path,
    out: str | Path,
    options: SfmOptions | None = None,
    overwrite: bool = False,
    events: EventWriter | None = None,
    quiet: bool = False,
) -> dict:
    """Reconstruct cameras and points from photos or a video into a dataset folder.

    Returns the summary (also written to ``out/sfm_summary.json``). Raises DatasetError
    or PromptGSError with one line for bad input or a failed reconstruction; the working
    files stay in ``out/colmap`` so a re-run resumes.
    """
    import pycolmap

    options = options or SfmOptions()
    options.validate()
    input_path, out = Path(input_path).expanduser(), Path(out).expanduser()
    events = events or EventWriter()
    reporter = Reporter(events, quiet=quiet)
    start = time.perf_counter()
    stage_name = "input"
    try:
        kind = input_kind(input_path)
        reporter.stages = STAGES if kind == "video" else STAGES[1:]
        if kind == "video":
            probe_video(input_path)
        _prepare_out(input_path, out, overwrite)
        work = out / WORK
        _check_feature_settings(work, options.feature_settings() | ({"fps": options.fps, "max_frames": options.max_frames} if kind == "video" else {}))
        events.emit("sfm_start", input=str(input_path), kind=kind, out=str(out), options=asdict(options))
        frames = None
        if kind == "video":
            stage_name = "frames"
            image_dir = work / "frames"
            with reporter.stage("frames", None, "frame", detail=f"{options.fps:g} per second, sharpest kept") as stage:
                frames = extract_frames(input_path, image_dir, fps=options.fps, max_frames=options.max_frames, max_size=options.max_image_size, progress=lambda d, t: stage.set(d, t))
            names = list_images(image_dir)
        else:
            image_dir = input_path
            names = _list_input_images(input_path)
        n = len(names)
        if n < 2:
            raise DatasetError(f"{image_dir}: SfM needs at least 2 images, found {n}")
        longest = max(max(image_size(image_dir / nm)) for nm in names[:: max(1, n // 20)])
        thumbnails = _thumbnails(longest, options)
        camera = _camera_mode(options, kind, image_dir, names)
        matcher = choose_matcher(options.matcher, n, kind)
        db = work / "database.db"
        with _ColmapLog(work / "colmap-"):
            stage_name = "features"
            reused = _extract(pycolmap, db, image_dir, names, options, camera, thumbnails, reporter)
            stage_name = "matching"
            n_pairs, pairs_reused = _match(pycolmap, db, work, names, matcher, options, thumbnails, reporter)
            stage_name = "mapping"
            best, n_models, model_dir, mapper, tried = _map_chosen(pycolmap, db, image_dir, work, n, options, thumbnails, reporter)
            summary = {
                "status": "failed",
                "input": str(input_path),
                "kind": kind,
                "out": str(out),
                "matcher": matcher,
                "pairs": n_pairs,
                "camera_mode": camera,
                "camera_model": options.camera_model,
                "max_image_size": options.max_image_size,
                "thumbnail_settings": thumbnails,
                "features_reused": reused,
                "pairs_reused": pairs_reused,
                "mapper": mapper,
                "mappers_tried": tried,
                "models": n_models,
                "frames": frames.to_json() if frames else None,
            }
            if best is None:
                summary |= {"images_given": n, "images_registered": 0}
                _write_summary(out, summary, start, reporter)
                raise PromptGSError(
                    f"{input_path}: no model could be built from {n} images (no pair had enough matches to start); {_advice(kind, matcher, options)}"
                )
            summary |= _summary_of(best, n)
            k = summary["images_registered"]
            needed = max(2, int(np.ceil(options.min_registered * n)))
            if k < needed:
                _write_summary(out, summary, start, reporter)
                raise PromptGSError(
                    f"{input_path}: only {k} of {n} images registered (at least {needed} needed; --min-registered {options.min_registered:g}); "
                    f"{_advice(kind, matcher, options)}; the partial models are in {model_dir.parent}"
                )
            stage_name = "undistortion"
            _undistort(pycolmap, model_dir, image_dir, out, k, options, reporter)
        summary["status"] = "ok"
        summary = _write_summary(out, summary, start, reporter)
        events.emit("sfm_done", out=str(out), summary=summary)
        return summary
    except (Exception, KeyboardInterrupt) as exc:
        if isinstance(exc, KeyboardInterrupt):
            message = "cancelled; the features and matches found so far are kept (run the same command to resume)"
        else:
            message = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        events.emit("error", message=message, stage=stage_name, step=None, log=_newest_log(out / WORK))
        raise


def _newest_log(work: Path) -> str | None:
    logs = sorted(work.glob("colmap-*"), key=lambda p: p.stat().st_mtime) if work.is_dir() else []
    return str(logs[-1]) if logs else None


def _list_input_images(folder: Path) -> list[str]:
    try:
        return list_images(folder)
    except DatasetError as e:
        if (folder / "images").is_dir() and "no images found" in str(e):
            raise DatasetError(f"{folder}: no images found directly in it (it has an images/ folder: give that folder)") from None
        raise


def _advice(kind: str, matcher: str, options: SfmOptions) -> str:
    tips = []
    if options.mapper == "incremental":
        tips.append("--mapper global")
    if matcher == "sequential":
        tips.append("--matcher exhaustive" if kind == "images" else f"a higher --overlap (now {options.overlap})")
    if options.max_image_size is not None:
        tips.append(f"a larger --max-image-size (now {options.max_image_size})")
    if kind == "video":
        tips.append(f"a higher --fps (now {options.fps:g})")
    else:
        tips.append("more photos with more overlap between neighbours")
    return "try " + ", ".join(tips)


def _write_summary(out: Path, summary: dict, start: float, reporter: Reporter) -> dict:
    summary["seconds"] = round(time.perf_counter() - start, 3)
    summary["stage_seconds"] = {k: round(v, 3) for k, v in reporter.stage_seconds.items()}
    tmp = out / (SUMMARY + ".tmp")
    tmp.write_text(json.dumps(summary, indent=2))
    os.replace(tmp, out / SUMMARY)
    return summary
