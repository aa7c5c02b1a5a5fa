"""The synthetic mountain dataset generator, end to end on the ``tiny`` preset.

One dataset is generated per test session (about a minute on 2 cores): Blender renders
in a subprocess, pycolmap triangulates in this process.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from promptgs_engine.synthetic import cli

pytestmark = pytest.mark.blender

REPO = Path(__file__).resolve().parents[1]


def _bpy_importable() -> bool:
    try:
        return subprocess.run([sys.executable, "-c", "import bpy"], capture_output=True, timeout=300).returncode == 0
    except (OSError, subprocess.TimeoutExpired):
        return False


@pytest.fixture(scope="module", autouse=True)
def _needs_bpy() -> None:
    if not _bpy_importable():
        pytest.skip("bpy cannot be imported in a subprocess")


def _cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "promptgs_engine.synthetic", "dataset", "mountain", *args],
        capture_output=True, text=True, cwd=REPO, timeout=600,
    )


@pytest.fixture(scope="module")
def tiny(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("synthetic") / "tiny"
    assert cli.main(["dataset", "mountain", "--preset", "tiny", "--seed", "0", "--out", str(out), "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def scene(tiny: Path) -> dict:
    return json.loads((tiny / "scene.json").read_text())


def _dry_run(seed: int) -> dict:
    result = _cli("--preset", "tiny", "--seed", str(seed), "--dry-run")
    assert result.returncode == 0, result.stderr
    return json.loads(result.stdout)


def _project(cam: dict, points: np.ndarray) -> np.ndarray:
    w2c = np.asarray(cam["world_to_camera"])
    pc = points @ w2c[:3, :3].T + w2c[:3, 3]
    assert np.all(pc[:, 2] > 0)
    return np.stack([cam["fx"] * pc[:, 0] / pc[:, 2] + cam["cx"], cam["fy"] * pc[:, 1] / pc[:, 2] + cam["cy"]], axis=1)


def test_layout_of_the_folder(tiny: Path, scene: dict) -> None:
    names = sorted(c["name"] for c in scene["cameras"])
    assert scene["complete"] and scene["seed"] == 0 and scene["parameters"]["preset"] == "tiny"
    assert sorted(p.name for p in (tiny / "images").iterdir()) == names
    assert sorted(p.name for p in (tiny / "object_masks").iterdir()) == names
    test = (tiny / "test.txt").read_text().split()
    assert test == names[::8]  # every 8th image in name order, like the trainer's default split
    assert sorted(p.name for p in (tiny / "gt_nodrones").iterdir()) == test
    assert not list(tiny.parent.glob(".*partial*"))
    for prompt in scene["prompts"]["prompts"]:
        assert set(prompt) == {"center", "size", "rotation_wxyz", "weight"}
        assert len(prompt["center"]) == 3 and min(prompt["size"]) > 0


def test_colmap_model_has_every_pose(tiny: Path, scene: dict) -> None:
    import pycolmap

    rec = pycolmap.Reconstruction(tiny / "sparse" / "0")
    assert rec.num_reg_images() == rec.num_images() == len(scene["cameras"])
    cameras = {c["name"]: c for c in scene["cameras"]}
    (camera,) = rec.cameras.values()
    assert camera.model_name == "PINHOLE"
    c0 = scene["cameras"][0]
    assert np.allclose(camera.params, [c0["fx"], c0["fy"], c0["cx"], c0["cy"]])
    for image in rec.images.values():
        assert image.has_pose
        expected = np.asarray(cameras[image.name]["world_to_camera"])[:3]
        assert np.allclose(image.cam_from_world().matrix(), expected, atol=1e-6)


def test_drone_size_condition(tiny: Path, scene: dict) -> None:
    rule = scene["size_rule"]
    max_px = rule["max_drone_px"]
    assert max_px == pytest.approx(10.0 * scene["parameters"]["height"] / 1080)
    cameras = {c["name"]: c for c in scene["cameras"]}
    for drone in scene["drones"]:
        lo, hi = np.asarray(drone["box_min"]), np.asarray(drone["box_max"])
        corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
        world = corners @ np.asarray(drone["rotation"]).T + np.asarray(drone["centre"])
        for view in drone["views"]:  # every image the drone's box touches
            uv = _project(cameras[view["name"]], world)
            assert (uv.max(0) - uv.min(0)).max() <= max_px + 1e-6
            if view["mask_pixels"]:
                assert max(view["mask_extent_px"]) <= int(np.ceil(max_px)) + 1
        seen_train = [v for v in drone["views"] if v["seen"] and cameras[v["name"]]["split"] == "train"]
        assert len(seen_train) >= rule["min_views"]
        assert min(v["size_px"] for v in seen_train) >= rule["min_visible_px"]
        assert drone["n_train_views_in_mask"] >= rule["min_views"]


def test_masks_align_with_projected_centres(tiny: Path, scene: dict) -> None:
    from PIL import Image

    drones = {d["id"]: d for d in scene["drones"]}
    checked = 0
    for cam in scene["cameras"]:
        mask = np.asarray(Image.open(tiny / "object_masks" / cam["name"]), dtype=np.int64)
        assert mask.shape == (cam["height"], cam["width"])
        assert set(np.unique(mask)) <= {0, *drones}
        for drone_id in set(np.unique(mask)) - {0}:
            ys, xs = np.nonzero(mask == drone_id)
            centroid = np.array([xs.mean() + 0.5, ys.mean() + 0.5])  # pixel centres at +0.5
            (uv,) = _project(cam, np.asarray([drones[drone_id]["centre"]]))
            assert np.linalg.norm(centroid - uv) <= 1.0, (cam["name"], drone_id)
            checked += 1
    assert checked >= len(drones) * scene["size_rule"]["min_views"]


def test_points_on_terrain_and_near_drones_recorded(tiny: Path, scene: dict) -> None:
    sfm = scene["sfm"]
    assert sfm["n_points"] >= 100
    assert sfm["n_on_terrain"] >= 0.5 * sfm["n_points"]
    heights = np.load(tiny / "terrain_heights.npy")
    assert heights.shape == (scene["terrain"]["resolution"],) * 2
    for drone in scene["drones"]:
        assert drone["sfm_points_within_radius"] >= 0 and drone["sfm_points_within_1m"] >= 0


def test_same_seed_same_layout_other_seed_different(scene: dict) -> None:
    first, again, other = _dry_run(0), _dry_run(0), _dry_run(1)
    assert first["cameras"] == again["cameras"] and first["drones"] == again["drones"]
    assert first["flames"] == again["flames"] and first["prompts"] == again["prompts"]
    # the rendered dataset has the same layout as the dry run
    assert [c["world_to_camera"] for c in scene["cameras"]] == [c["world_to_camera"] for c in first["cameras"]]
    assert [d["centre"] for d in scene["drones"]] == [d["centre"] for d in first["drones"]]
    assert [d["centre"] for d in other["drones"]] != [d["centre"] for d in first["drones"]]
    assert [c["world_to_camera"] for c in other["cameras"]] != [c["world_to_camera"] for c in first["cameras"]]


@pytest.mark.parametrize(
    "args, message",
    [
        (["--preset", "huge"], "unknown preset 'huge'"),
        (["--preset", "tiny", "--drone-px", "12"], "larger than the size limit"),
        (["--preset", "tiny", "--views", "0"], "zero views"),
        (["--preset", "tiny", "--height", "100"], "min_visible_px"),
    ],
)
def test_bad_parameters(tmp_path: Path, args: list[str], message: str) -> None:
    out = tmp_path / "new"
    result = _cli(*args, "--out", str(out), "--quiet")
    assert result.returncode == 2
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and message in lines[0], result.stderr
    assert not out.exists() and not list(tmp_path.glob(".*partial*"))


def test_existing_datasets_are_never_overwritten(tiny: Path, tmp_path: Path) -> None:
    before = (tiny / "scene.json").read_bytes()
    result = _cli("--preset", "tiny", "--seed", "1", "--out", str(tiny), "--quiet")
    assert result.returncode == 2 and "already holds a different dataset" in result.stderr
    assert len(result.stderr.strip().splitlines()) == 1
    same = _cli("--preset", "tiny", "--seed", "0", "--out", str(tiny), "--quiet")
    assert same.returncode == 0 and "already holds this dataset" in same.stdout
    assert (tiny / "scene.json").read_bytes() == before
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    result = _cli("--preset", "tiny", "--out", str(foreign), "--quiet")
    assert result.returncode == 2 and "not empty" in result.stderr
    assert [p.name for p in foreign.iterdir()] == ["notes.txt"]


def test_blender_binary_route(tmp_path: Path) -> None:
    """``--blender PATH`` runs ``PATH -b --factory-startup --python-exit-code 1 --python-expr CODE -- ARGS``;
    a stand-in binary that runs CODE with this Python checks the plumbing (layout only)."""
    fake = tmp_path / "blender"
    fake.write_text(
        "#!/bin/sh\n"
        '[ "$1" = -b ] && [ "$2" = --factory-startup ] && [ "$5" = --python-expr ] || exit 9\n'
        'code="$6"; shift 6\n'
        f'exec {sys.executable} -c "$code" "$@"\n'
    )
    fake.chmod(0o755)
    result = _cli("--preset", "tiny", "--dry-run", "--blender", str(fake))
    assert result.returncode == 0, result.stderr
    assert len(json.loads(result.stdout)["cameras"]) == 12


def test_blender_crash_keeps_log_and_leaves_out_alone(tmp_path: Path) -> None:
    fake = tmp_path / "blender"
    fake.write_text("#!/bin/sh\necho 'Segmentation fault'\nexit 3\n")
    fake.chmod(0o755)
    out = tmp_path / "ds"
    result = _cli("--preset", "tiny", "--out", str(out), "--blender", str(fake), "--quiet")
    assert result.returncode == 2 and "Blender exited with status 3" in result.stderr
    assert not out.exists()
    log = tmp_path / ".ds.partial" / ".work" / "blender.log"
    assert "Segmentation fault" in log.read_text()
