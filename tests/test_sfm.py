"""`promptgs sfm`: photos or a video to a dataset, resume, events, bad input, chaining into train.

The video is rendered here: a camera moving inside a box whose walls carry random
shapes (numpy ray casting), encoded with PyAV, so the true camera path is known.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image, ImageDraw, ImageFilter

from promptgs_engine.cli import main as cli_main
from promptgs_engine.data import load_colmap_scene
from promptgs_engine.sfm.compare import camera_centres, compare_centres, umeyama
from promptgs_engine.sfm.inputs import natural_key
from promptgs_engine.sfm.pairs import choose_matcher, exhaustive_pairs, sequential_pairs
from promptgs_engine.sfm.video import extract_frames, sharpness
from scenes import subset_of_model

av = pytest.importorskip("av")

W, H, FOCAL = 160, 120, 120.0
VIDEO_FPS, N_FRAMES = 10, 30


# --- a synthetic capture ---------------------------------------------------------------


def _wall_textures(seed: int = 0, size: int = 512, n_shapes: int = 400) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    faces = []
    for _ in range(6):
        im = Image.new("RGB", (size, size), tuple(int(c) for c in rng.integers(60, 200, 3)))
        draw = ImageDraw.Draw(im)
        for _ in range(n_shapes):
            x, y = rng.random(2) * size
            r = size * (0.004 + 0.04 * rng.random() ** 2)
            colour = tuple(int(c) for c in rng.integers(0, 256, 3))
            if rng.random() < 0.5:
                draw.ellipse([x - r, y - r * (0.5 + rng.random()), x + r, y + r], fill=colour)
            else:
                draw.rectangle([x - r, y - r, x + r * (0.5 + rng.random()), y + r], fill=colour)
        faces.append(np.asarray(im, np.float32) / 255)
    return faces


def _render_box(faces, centre, world_to_cam_rot, half: float = 2.0, ss: int = 2) -> np.ndarray:
    """View from inside the cube [-half, half]^3 (COLMAP camera: x right, y down, z forward)."""
    j, i = np.meshgrid((np.arange(W * ss) + 0.5) / ss, (np.arange(H * ss) + 0.5) / ss)
    rays = np.stack([(j - W / 2) / FOCAL, (i - H / 2) / FOCAL, np.ones_like(j)], -1) @ world_to_cam_rot
    nearest = np.full(j.shape, np.inf)
    image = np.zeros(j.shape + (3,))
    size = faces[0].shape[0]
    for axis in range(3):
        for side, sign in enumerate((-1.0, 1.0)):
            with np.errstate(divide="ignore", invalid="ignore"):
                t = (sign * half - centre[axis]) / rays[..., axis]
            hit = (t > 0) & (t < nearest)
            p = centre + t[..., None] * rays
            a, b = [k for k in range(3) if k != axis]
            u = ((p[..., a] / (2 * half) + 0.5) * (size - 1)).clip(0, size - 1).astype(int)
            v = ((p[..., b] / (2 * half) + 0.5) * (size - 1)).clip(0, size - 1).astype(int)
            image[hit] = faces[2 * axis + side][v[hit], u[hit]]
            nearest[hit] = t[hit]
    return (image.reshape(H, ss, W, ss, 3).mean((1, 3)) * 255).round().astype(np.uint8)


def _camera_path(k: int) -> tuple[np.ndarray, np.ndarray]:
    """Centre and world-to-camera rotation of video frame k (an arc, looking outwards)."""
    a = k / N_FRAMES * 1.6
    centre = np.array([1.2 * np.cos(a), 1.2 * np.sin(a), 0.3 * np.sin(3 * a)])
    z = np.array([-1.5 * np.cos(a + 0.8), -1.5 * np.sin(a + 0.8), -0.3]) - centre
    z /= np.linalg.norm(z)
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    return centre, np.stack([x, np.cross(z, x), z])


def _encode(frames: list[np.ndarray], path: Path) -> None:
    out = av.open(str(path), "w")
    stream = out.add_stream("libx264" if "libx264" in av.codecs_available else "mpeg4", rate=VIDEO_FPS)
    stream.width, stream.height, stream.pix_fmt = W, H, "yuv420p"
    stream.options = {"crf": "18"} if stream.codec_context.name == "libx264" else {}
    for frame in frames:
        for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
            out.mux(packet)
    for packet in stream.encode():
        out.mux(packet)
    out.close()


@pytest.fixture(scope="module")
def box_video(tmp_path_factory) -> tuple[Path, list[np.ndarray]]:
    """A 3 s video of the box (10 fps) and the true camera centre of each frame."""
    faces = _wall_textures()
    frames, centres = [], []
    for k in range(N_FRAMES):
        centre, rot = _camera_path(k)
        frames.append(_render_box(faces, centre, rot))
        centres.append(centre)
    path = tmp_path_factory.mktemp("video") / "box.mp4"
    _encode(frames, path)
    return path, centres


@pytest.fixture(scope="module")
def box_sfm(box_video, tmp_path_factory) -> Path:
    video, _ = box_video
    out = tmp_path_factory.mktemp("sfm") / "box"
    assert cli_main(["sfm", str(video), "--out", str(out), "--fps", "5", "--quiet"]) == 0
    return out


def _run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    code = cli_main(argv)
    captured = capsys.readouterr()
    return code, captured.out, captured.err


# --- pieces ----------------------------------------------------------------------------


def test_pairs_exhaustive_and_sequential():
    assert exhaustive_pairs(4) == [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
    plain = set(sequential_pairs(100, overlap=3, quadratic=False, loop_key_images=0))
    assert {(10, 11), (10, 12), (10, 13)} <= plain and (10, 14) not in plain and len(plain) == 97 + 98 + 99
    pairs = set(sequential_pairs(100, overlap=3, quadratic=True, loop_key_images=5))
    assert (10, 14) in pairs and (10, 18) not in pairs  # quadratic: 2^k ahead up to 2^(overlap-1) = 4
    assert (0, 80) in pairs and (20, 80) in pairs  # loop pairs between key images 0, 20, …, 80
    assert all(i < j for i, j in pairs)
    assert choose_matcher("auto", 40, "images") == "exhaustive"
    assert choose_matcher("auto", 400, "images") == "sequential"
    assert choose_matcher("auto", 40, "video") == "sequential"
    assert sorted(["10.jpg", "2.jpg", "1.jpg"], key=natural_key) == ["1.jpg", "2.jpg", "10.jpg"]


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(1)
    src = rng.normal(size=(20, 3))
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    rot = q * np.sign(np.linalg.det(q))
    dst = 2.5 * src @ rot.T + np.array([1.0, -2.0, 0.5])
    s, r, t = umeyama(src, dst)
    assert s == pytest.approx(2.5) and np.allclose(r, rot) and np.allclose(t, [1.0, -2.0, 0.5])
    moved = {str(k): dst[k] + (0.3 if k == 0 else 0.0) for k in range(20)}
    report = compare_centres({str(k): src[k] for k in range(20)}, moved)
    assert report["max_error"] > 0.01 and report["median_error"] < report["max_error"]


def test_sharpest_frame_of_each_window_is_kept(tmp_path):
    """One sharp frame among blurred ones in every half second: each kept frame is the sharp one."""
    rng = np.random.default_rng(2)
    sharp = [np.asarray(Image.fromarray(rng.integers(0, 256, (H // 8, W // 8, 3), dtype=np.uint8)).resize((W, H), Image.NEAREST)) for _ in range(4)]
    frames = []
    for k in range(4):  # windows of 5 frames at 10 fps and --fps 2; the sharp one is at position k
        blurred = np.asarray(Image.fromarray(sharp[k]).filter(ImageFilter.GaussianBlur(3)))
        frames += [sharp[k] if i == k else blurred for i in range(5)]
    video = tmp_path / "blur.mp4"
    _encode(frames, video)
    stats = extract_frames(video, tmp_path / "frames", fps=2.0)
    assert stats.decoded == 20 and stats.written == 4
    for k in range(4):
        kept = np.asarray(Image.open(tmp_path / "frames" / f"frame_{k + 1:06d}.jpg"), np.float32)
        assert stats.times_s[k] == pytest.approx(0.5 * k + 0.1 * k)
        assert np.abs(kept - sharp[k]).mean() < 12
        assert sharpness(kept.mean(-1)) > 2 * sharpness(np.asarray(Image.fromarray(sharp[k]).filter(ImageFilter.GaussianBlur(3)), np.float32).mean(-1))


# --- the video route end to end --------------------------------------------------------


def test_video_route_recovers_the_camera_path(box_video, box_sfm):
    _, true_centres = box_video
    summary = json.loads((box_sfm / "sfm_summary.json").read_text())
    assert summary["status"] == "ok" and summary["kind"] == "video" and summary["matcher"] == "sequential"
    assert summary["images_given"] == 15 and summary["images_registered"] == 15
    assert summary["mean_reprojection_error_px"] < 1.0
    assert set(summary["stage_seconds"]) == {"frames", "features", "matching", "mapping", "undistortion"}
    times = json.loads((box_sfm / "colmap" / "frames" / "frames.json").read_text())["stats"]["times_s"]
    truth = {f"frame_{k + 1:06d}.jpg": true_centres[round(t * VIDEO_FPS)] for k, t in enumerate(times)}
    report = compare_centres(camera_centres(box_sfm / "sparse" / "0"), truth)
    assert report["common"] == 15
    assert report["max_error"] < 0.03 and report["median_error"] < 0.015, report
    # The trainer reads the result as it is: PINHOLE cameras, images beside them.
    scene = load_colmap_scene(box_sfm)
    assert len(scene.train_cameras) + len(scene.test_cameras) == 15 and len(scene.points) > 100
    assert all(c.K[0, 0] == pytest.approx(FOCAL, rel=0.05) for c in scene.train_cameras)


def test_rerun_resumes_from_the_database(box_video, box_sfm, capsys):
    video, _ = box_video
    code, out, _ = _run_cli(["sfm", str(video), "--out", str(box_sfm), "--fps", "5", "--quiet"], capsys)
    assert code == 0
    summary = json.loads(out)
    assert summary["features_reused"] == 15 and summary["pairs_reused"] == summary["pairs"]
    assert summary["images_registered"] == 15
    # Other feature settings on the same folder are refused, not mixed in.
    code, _, err = _run_cli(["sfm", str(video), "--out", str(box_sfm), "--fps", "5", "--max-image-size", "100", "--quiet"], capsys)
    assert code == 2 and "other settings" in err and "max_image_size 1600 (now 100)" in err


def test_global_mapper_recovers_the_camera_path(box_video, box_sfm, tmp_path, capsys):
    """`--mapper global` (GLOMAP) on the features and matches of the module's run (kept in
    the database, so only mapping runs) registers every frame on the true path."""
    video, true_centres = box_video
    out = tmp_path / "global"
    shutil.copytree(box_sfm, out)
    code, printed, err = _run_cli(["sfm", str(video), "--out", str(out), "--fps", "5", "--quiet", "--mapper", "global"], capsys)
    assert code == 0, err
    summary = json.loads(printed)
    assert summary["pairs_reused"] == summary["pairs"] and summary["mapper"] == "global" and summary["mappers_tried"] == {"global": 15}
    assert summary["images_registered"] == 15 and (out / "colmap" / "models-global" / "0").is_dir()
    times = json.loads((out / "colmap" / "frames" / "frames.json").read_text())["stats"]["times_s"]
    truth = {f"frame_{k + 1:06d}.jpg": true_centres[round(t * VIDEO_FPS)] for k, t in enumerate(times)}
    report = compare_centres(camera_centres(out / "sparse" / "0"), truth)
    assert report["common"] == 15 and report["max_error"] < 0.03 and report["median_error"] < 0.015, report


def test_events_stream(box_video, tmp_path, capsys):
    video, _ = box_video
    code, out, _ = _run_cli(["sfm", str(video), "--out", str(tmp_path / "ev"), "--fps", "2.5", "--events", "--matcher", "exhaustive"], capsys)
    assert code == 0
    events = [json.loads(line) for line in out.splitlines()]
    kinds = [e["event"] for e in events]
    assert kinds[0] == "sfm_start" and kinds[-1] == "sfm_done"
    stages = [e["stage"] for e in events if e["event"] == "sfm_stage"]
    assert stages == ["frames", "features", "matching", "mapping", "undistortion"]
    last = {}
    for e in events:
        if e["event"] == "sfm_progress":
            last[e["stage"]] = e
    assert last["features"]["done"] == last["features"]["total"] == 8  # 3 s in windows of 0.4 s
    assert last["matching"]["done"] == 28  # exhaustive: 8 * 7 / 2 pairs
    assert events[-1]["summary"]["images_registered"] == 8

    code, out, err = _run_cli(["sfm", str(tmp_path / "missing"), "--out", str(tmp_path / "ev2"), "--events"], capsys)
    assert code == 2 and json.loads(out.splitlines()[-1])["event"] == "error"


def test_train_on_a_video_runs_sfm_first(box_video, box_sfm, tmp_path, capsys):
    video, _ = box_video
    run = tmp_path / "run"
    # A finished reconstruction in RUN/sfm is used as it is (here: copied from the module's).
    shutil.copytree(box_sfm, run / "sfm")
    code, out, err = _run_cli(["train", str(video), "--out", str(run), "--iterations", "20", "--quiet", "--fps", "5"], capsys)
    assert code == 0, err
    cfg = json.loads((run / "cfg.json").read_text())
    assert Path(cfg["dataset"]) == run / "sfm"
    assert (run / "point_cloud.ply").is_file()


def test_train_on_a_photo_folder_runs_sfm_into_the_run(box_sfm, tmp_path, capsys):
    photos = tmp_path / "photos"
    shutil.copytree(box_sfm / "colmap" / "frames", photos, ignore=shutil.ignore_patterns("*.json"))
    run = tmp_path / "run"
    code, _, err = _run_cli(["train", str(photos), "--out", str(run), "--iterations", "10", "--quiet", "--matcher", "sequential"], capsys)
    assert code == 0, err
    summary = json.loads((run / "sfm" / "sfm_summary.json").read_text())
    assert summary["kind"] == "images" and summary["images_registered"] == 15
    assert json.loads((run / "cfg.json").read_text())["dataset"] == str(run / "sfm")


# --- bad input: one line naming the problem, exit code 2 --------------------------------


def _error_line(err: str) -> str:
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("promptgs: error: ")
    return lines[0]


def test_bad_inputs_end_with_one_line(box_sfm, tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    code, _, err = _run_cli(["sfm", str(empty), "--out", str(tmp_path / "o1")], capsys)
    assert code == 2 and "no images found" in _error_line(err) and str(empty) in err

    broken = tmp_path / "broken"
    broken.mkdir()
    shutil.copy(box_sfm / "colmap" / "frames" / "frame_000001.jpg", broken / "a.jpg")
    (broken / "b.jpg").write_bytes(b"\xff\xd8 not really a jpeg")
    code, _, err = _run_cli(["sfm", str(broken), "--out", str(tmp_path / "o2")], capsys)
    assert code == 2 and "unreadable image file" in _error_line(err) and str(broken / "b.jpg") in err

    video = tmp_path / "clip.mp4"
    video.write_bytes(b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 8)
    code, _, err = _run_cli(["sfm", str(video), "--out", str(tmp_path / "o3")], capsys)
    assert code == 2 and "cannot open the video" in _error_line(err) and str(video) in err

    code, _, err = _run_cli(["sfm", str(tmp_path / "nothing"), "--out", str(tmp_path / "o4")], capsys)
    assert code == 2 and "not found" in _error_line(err)

    busy = tmp_path / "busy"
    busy.mkdir()
    (busy / "notes.txt").write_text("mine")
    code, _, err = _run_cli(["sfm", str(box_sfm / "colmap" / "frames"), "--out", str(busy)], capsys)
    assert code == 2 and "holds no earlier sfm output" in _error_line(err)
    assert (busy / "notes.txt").read_text() == "mine"

    code, _, err = _run_cli(["sfm", str(box_sfm / "colmap" / "frames"), "--out", str(tmp_path / "o5"), "--threads", "0"], capsys)
    assert code == 2 and "--threads must be a positive whole number" in _error_line(err)


def test_too_few_registered_says_how_many_and_what_to_try(box_sfm, tmp_path, capsys):
    """Six frames of the box and four unrelated noise images: 6 of 10 register, 0.9 asked."""
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for k in range(1, 7):
        shutil.copy(box_sfm / "colmap" / "frames" / f"frame_{k:06d}.jpg", mixed / f"a{k}.jpg")
    rng = np.random.default_rng(3)
    for k in range(4):
        Image.fromarray(rng.integers(0, 256, (H, W, 3), dtype=np.uint8)).save(mixed / f"noise{k}.jpg")
    out = tmp_path / "o"
    code, _, err = _run_cli(["sfm", str(mixed), "--out", str(out), "--min-registered", "0.9", "--quiet"], capsys)
    line = _error_line(err)
    assert code == 2 and "only 6 of 10 images registered" in line and "at least 9 needed" in line and "try " in line
    summary = json.loads((out / "sfm_summary.json").read_text())
    assert summary["status"] == "failed" and summary["images_registered"] == 6
    assert (out / "colmap" / "database.db").is_file() and not (out / "sparse").exists()


# --- photos of the made pinhole scene (tests/scenes.py) ---------------------------------


@pytest.fixture(scope="module")
def photos_sfm(made_scenes, tmp_path_factory) -> tuple[Path, dict, tuple[str, ...]]:
    """`promptgs sfm` of the made scene's views through its first camera (every second view)."""
    facts = made_scenes["pinhole"]
    names = facts.names[::2]
    assert len({tuple(facts.intrinsics[n].ravel()) for n in names}) == 1  # one camera took them all
    photos = tmp_path_factory.mktemp("photos") / "images"
    photos.mkdir()
    for name in names:
        (photos / name).symlink_to(facts.path / "images" / name)
    out = photos.parent / "sfm"
    assert cli_main(["sfm", str(photos), "--out", str(out), "--quiet", "--threads", "1"]) == 0
    return out, json.loads((out / "sfm_summary.json").read_text()), names


def test_photos_register_where_they_were_taken(made_scenes, photos_sfm):
    """Twelve photos of one camera: all register, the camera centres are the ones the scene
    was made with up to a similarity (measured: median 0.15%, all under 0.24% of the
    extent), and the focal length is the camera's."""
    facts = made_scenes["pinhole"]
    out, summary, names = photos_sfm
    assert summary["status"] == "ok" and summary["kind"] == "images" and summary["matcher"] == "exhaustive"
    assert summary["images_given"] == summary["images_registered"] == len(names) == 12
    truth = {name: -pose[:3, :3].T @ pose[:3, 3] for name, pose in facts.poses.items() if name in names}
    report = compare_centres(camera_centres(out / "sparse" / "0"), truth)
    assert report["common"] == 12 and report["median_error"] < 0.005 and report["max_error"] < 0.01, report
    scene = load_colmap_scene(out)
    true_focal = facts.intrinsics[names[0]][0, 0]
    assert all(c.K[0, 0] == pytest.approx(true_focal, rel=0.005) for c in scene.cameras)


@pytest.mark.slow
def test_training_on_the_sfm_model_of_photos_matches_the_true_model(made_scenes, photos_sfm, tmp_path):
    """Same photos, same steps: the PSNR on the held-out views is no more than 0.5 dB below
    that of the model the scene was made with."""
    from promptgs_engine.config import TrainConfig
    from promptgs_engine.run import run_training

    facts = made_scenes["pinhole"]
    out, _, names = photos_sfm
    given = subset_of_model(facts.model_dir, facts.path / "images", set(names), tmp_path / "given")
    psnr = {}
    for label, dataset in (("sfm", out), ("given", given)):
        cfg = TrainConfig(dataset=str(dataset), out=str(tmp_path / f"run_{label}"), iterations=300, checkpoint_every=0, sh_degree=1)
        psnr[label] = run_training(cfg, quiet=True)["psnr"]
    assert psnr["sfm"] > psnr["given"] - 0.5, psnr
