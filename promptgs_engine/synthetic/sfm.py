"""COLMAP model of a rendered dataset: known poses, SIFT points triangulated with pycolmap.

The cameras and poses are the true ones (PINHOLE, shared intrinsics); only the 3D points
come from images, the way a real capture gets them: SIFT features, matching with
geometric verification, then triangulation with the poses held fixed. Tiny objects yield
few or no features, so they get few or no points.
"""

from __future__ import annotations

import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pycolmap

from ..errors import DatasetError

EXHAUSTIVE_MAX_IMAGES = 60  # above this, match each image only with its nearest cameras
NEIGHBOURS = 20


def _rigid(world_to_camera: list[list[float]]) -> pycolmap.Rigid3d:
    m = np.asarray(world_to_camera, dtype=np.float64)
    return pycolmap.Rigid3d(pycolmap.Rotation3d(m[:3, :3]), m[:3, 3])


def _pairs_by_distance(cameras: list[dict[str, Any]], k: int) -> list[tuple[str, str]]:
    """Each camera with its k nearest cameras (by centre), each pair once."""
    centres = np.array([c["centre"] for c in cameras])
    d = np.linalg.norm(centres[:, None] - centres[None], axis=-1)
    pairs: set[tuple[int, int]] = set()
    for i in range(len(cameras)):
        for j in np.argsort(d[i])[1 : k + 1]:
            pairs.add((min(i, int(j)), max(i, int(j))))
    return [(cameras[i]["name"], cameras[j]["name"]) for i, j in sorted(pairs)]


def build_sparse_model(root: Path, cameras: list[dict[str, Any]], work: Path, num_threads: int = -1) -> pycolmap.Reconstruction:
    """Write ``root/sparse/0`` for the images in ``root/images`` with the given true cameras.

    ``cameras`` are layout cameras (name, width, height, fx, fy, cx, cy, world_to_camera,
    centre); all share one set of intrinsics. ``work`` holds the feature database.
    """
    level = pycolmap.logging.minloglevel
    pycolmap.logging.minloglevel = 2  # errors only: COLMAP's info lines would bury the progress bar
    try:
        return _build(root, cameras, work, num_threads)
    finally:
        pycolmap.logging.minloglevel = level


def _build(root: Path, cameras: list[dict[str, Any]], work: Path, num_threads: int) -> pycolmap.Reconstruction:
    images = root / "images"
    work.mkdir(parents=True, exist_ok=True)
    database = work / "database.db"
    database.unlink(missing_ok=True)
    cam0 = cameras[0]
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE"
    reader.camera_params = ",".join(str(float(cam0[k])) for k in ("fx", "fy", "cx", "cy"))
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.num_threads = num_threads
    extraction.use_gpu = False
    names = sorted(c["name"] for c in cameras)
    pycolmap.extract_features(
        database, images, image_names=names, camera_mode=pycolmap.CameraMode.SINGLE,
        reader_options=reader, extraction_options=extraction, device=pycolmap.Device.cpu,
    )
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = num_threads
    matching.use_gpu = False
    if len(cameras) <= EXHAUSTIVE_MAX_IMAGES:
        pycolmap.match_exhaustive(database, matching_options=matching, device=pycolmap.Device.cpu)
    else:
        pair_file = work / "pairs.txt"
        pair_file.write_text("".join(f"{a} {b}\n" for a, b in _pairs_by_distance(cameras, NEIGHBOURS)))
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pair_file)
        pycolmap.match_image_pairs(database, matching_options=matching, pairing_options=pairing, device=pycolmap.Device.cpu)

    by_name = {c["name"]: c for c in cameras}
    rec = pycolmap.Reconstruction()
    db = pycolmap.Database.open(database)
    try:
        db_cameras = db.read_all_cameras()
        db_rigs = db.read_all_rigs()
        db_frames = db.read_all_frames()
        db_images = db.read_all_images()
    finally:
        db.close()
    if len(db_cameras) != 1 or len(db_images) != len(cameras):
        raise DatasetError(f"{database}: expected 1 camera and {len(cameras)} images, found {len(db_cameras)} and {len(db_images)}")
    for cam in db_cameras:
        rec.add_camera(cam)
    for rig in db_rigs:
        rec.add_rig(rig)
    image_of_frame = {}
    for image in db_images:
        image_of_frame[image.frame_id] = image
    for frame in db_frames:
        image = image_of_frame[frame.frame_id]
        frame.rig_from_world = _rigid(by_name[image.name]["world_to_camera"])
        rec.add_frame(frame)
    for image in db_images:
        rec.add_image(image)
    for frame in db_frames:
        rec.register_frame(frame.frame_id)

    sparse = root / "sparse" / "0"
    if sparse.exists():
        shutil.rmtree(sparse)
    sparse.mkdir(parents=True)
    options = pycolmap.IncrementalPipelineOptions()
    options.num_threads = num_threads
    rec = pycolmap.triangulate_points(rec, database, images, sparse, clear_points=True, options=options)
    rec.write(sparse)
    return rec
