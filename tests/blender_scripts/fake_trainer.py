"""A stand-in for ``python -m promptgs_engine train`` that speaks the events protocol.

Used as the add-on's "trainer Python" in tests (through a small executable wrapper):
parses ``--out`` and ``--job``, writes snapshot ``.npz`` files with numpy and prints
JSON-lines events. ``FAKE_TRAINER_MODE`` picks the behaviour: ``ok`` (default), ``crash``
(stderr lines, exit code 3), ``slow`` (runs until interrupted; SIGINT stops it cleanly),
``stepwise`` (``sfm`` holds at its mapping stage until ``sfm_go`` appears beside its output),
``ply`` (as ``ok``, and ends with RUN/point_cloud.ply, the last snapshot's Gaussians),
``badsnapshot`` (as ``ok``, but its last snapshot is not a readable file),
``tree`` (as ``slow``, with two child processes in their own sessions, as torchrun's
ranks are: one ignores SIGINT, the other SIGINT and SIGTERM; their pids go to RUN/tree.json).
Every ``checkpoint_every`` steps it writes RUN/ckpt.pt (the step, as text), and
``--resume`` continues from it, as the real trainer does.
``propose``, ``dataset`` and ``sfm`` answer as those commands do; a job with
``propose_prompts`` writes RUN/proposals.json half-way, as ``train --propose-prompts`` does.
"""

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np


def emit(**event):
    event["time"] = time.time()
    print(json.dumps(event), flush=True)


def snapshot(out: Path, step: int, n: int, seed: int) -> Path:
    rng = np.random.default_rng(seed + step)
    q = rng.normal(size=(n, 4)).astype(np.float32)
    data = {
        "means": rng.normal(size=(n, 3)).astype(np.float32),
        "opacity": rng.uniform(size=n).astype(np.float32),
        "scale": rng.uniform(0.01, 0.1, size=(n, 3)).astype(np.float32),
        "rotation": q / np.linalg.norm(q, axis=1, keepdims=True),
        "color": rng.uniform(size=(n, 3)).astype(np.float32),
        "score": rng.uniform(size=n).astype(np.float32),
        "error": rng.uniform(size=n).astype(np.float32),
        "field_centers": (0.1 * rng.integers(-5, 5, size=(64, 3))).astype(np.float32),  # voxel centres
        "field_loss": rng.uniform(size=64).astype(np.float32),
        "field_attention": rng.uniform(size=64).astype(np.float32),
    }
    path = out / "snapshots" / f"step_{step:06d}.npz"
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, **data)
    return path


def write_ply(path: Path, snapshot_path: Path) -> None:
    """A 3DGS PLY of a snapshot's Gaussians (positions as they are; the rest in PLY form)."""
    with np.load(snapshot_path) as npz:
        means, opacity, scale, rotation, color = (npz[k] for k in ("means", "opacity", "scale", "rotation", "color"))
    columns = {"x": means[:, 0], "y": means[:, 1], "z": means[:, 2]}
    for i in range(3):
        columns[f"f_dc_{i}"] = (color[:, i] - 0.5) / 0.28209479177387814
    columns["opacity"] = np.log(opacity / (1.0 - opacity))
    for i in range(3):
        columns[f"scale_{i}"] = np.log(scale[:, i])
    for i in range(4):
        columns[f"rot_{i}"] = rotation[:, i]
    table = np.stack(list(columns.values()), axis=1).astype("<f4")
    header = f"ply\nformat binary_little_endian 1.0\nelement vertex {len(table)}\n"
    header += "".join(f"property float {name}\n" for name in columns) + "end_header\n"
    path.write_bytes(header.encode() + table.tobytes())


def spawn_ranks(out: Path) -> None:
    """Two stand-ins for torchrun's ranks: own sessions, deaf to SIGINT (and the second to SIGTERM)."""
    pids = []
    for ignored in ("signal.SIGINT", "signal.SIGINT, signal.SIGTERM"):
        code = (f"import signal, time\nfor s in ({ignored},): signal.signal(s, signal.SIG_IGN)\n"
                "while True: time.sleep(0.1)\n")
        pids.append(subprocess.Popen([sys.executable, "-c", code], start_new_session=True,
                                     stdin=subprocess.DEVNULL).pid)
    (out / "tree.json").write_text(json.dumps(pids))


def dataset(argv, mode):
    """``promptgs dataset mountain``: a few progress lines, or one error line."""
    if mode == "crash":
        print("promptgs: error: --preset tiny: cannot find a blender binary", file=sys.stderr)
        sys.exit(2)
    out = Path(argv[argv.index("--out") + 1])
    for i in range(3):
        print(f"rendering view {i + 1}/3", flush=True)
    (out / "done").write_text(" ".join(argv))


def sfm(argv, mode):
    """``promptgs sfm PHOTOS --out DATASET --events``: the stages, then a dataset made of
    the model beside PHOTOS (a COLMAP dataset's images/ folder) and links to the photos."""
    source, out = Path(argv[argv.index("sfm") + 1]), Path(argv[argv.index("--out") + 1])
    photos = sorted(p.name for p in source.iterdir())
    emit(event="sfm_start", input=str(source), kind="images", out=str(out), options={})
    try:
        for index, (stage, unit) in enumerate([("features", "img"), ("matching", "pair"), ("mapping", "img")], 1):
            total = len(photos) if unit == "img" else 3 * len(photos)
            emit(event="sfm_stage", stage=stage, index=index, n_stages=4, total=total, unit=unit, detail="")
            if mode == "stepwise" and stage == "mapping":
                # Wait until the test has seen this stage's line (it then writes sfm_go): on
                # a loaded machine the whole run can otherwise end between two of its reads.
                deadline = time.time() + 60
                while not (out.parent / "sfm_go").exists() and time.time() < deadline:
                    time.sleep(0.01)
            if mode == "crash" and stage == "mapping":
                emit(event="error", message=f"{source}: only 6 of {len(photos)} images registered", stage=stage, step=None, log=None)
                sys.exit(2)
            for done in range(0, total + 1, max(1, total // 4)):
                emit(event="sfm_progress", stage=stage, done=done, total=total, unit=unit)
                time.sleep(0.2 if mode == "slow" else 0.001)
        while mode == "slow":
            time.sleep(0.05)
    except KeyboardInterrupt:
        (out.parent / "sfm_cancelled").write_text("1")
        emit(event="error", message="cancelled", stage="mapping", step=None, log=None)
        sys.exit(130)
    shutil.copytree(source.parent / "sparse", out / "sparse")
    (out / "images").symlink_to(source)
    summary = {"status": "ok", "images_given": len(photos), "images_registered": len(photos) - 1, "points": 9262}
    emit(event="sfm_done", out=str(out), summary=summary)


# What `promptgs propose` writes for the fake run (dataset coordinates): a rotated, flat
# box of high confidence and a small one of low confidence.
PROPOSALS = [
    {"center": [0.21, -0.34, 1.52], "size": [0.06, 0.04, 0.09], "rotation_wxyz": [0.9, 0.1, -0.3, 0.2], "weight": 0.82,
     "confidence": 0.82, "evidence": {"point": [0.21, -0.34, 1.52], "n_seeing": 31, "n_supporting": 24}},
    {"center": [-0.4, 0.1, 0.8], "size": [0.03, 0.03, 0.03], "rotation_wxyz": [1.0, 0.0, 0.0, 0.0], "weight": 0.21,
     "confidence": 0.21, "evidence": {"point": [-0.4, 0.1, 0.8], "n_seeing": 12, "n_supporting": 5}},
]


def proposal_file(**info) -> str:
    rotated = [dict(p, rotation_wxyz=(np.array(p["rotation_wxyz"]) / np.linalg.norm(p["rotation_wxyz"])).tolist())
               for p in PROPOSALS]
    return json.dumps({"schema": "promptgs-proposals/1", "prompts": rotated, "rejected": [], "unmatched": {}, **info})


def propose(argv, mode):
    """``promptgs propose RUN --out FILE [--snapshot S]``: the fixed proposals, or one error line."""
    run, out = Path(argv[argv.index("propose") + 1]), Path(argv[argv.index("--out") + 1])
    (out.parent / "argv.json").write_text(json.dumps(argv))
    if mode == "crash":
        print(f"promptgs: error: {run}: the run has no point_cloud.ply yet", file=sys.stderr)
        sys.exit(2)
    out.write_text(proposal_file())
    print(f"{len(PROPOSALS)} proposals; wrote {out}", flush=True)


def propose_in_training(out: Path, step: int) -> None:
    """``train --propose-prompts`` at its proposal step: RUN/proposals.json, first half
    written (as a reader may find it), then whole, then again with ``trained_as``; a
    pause after it, so that a client sees it while the run goes on."""
    path = out / "proposals.json"
    text = proposal_file(step=step)
    path.write_text(text[: len(text) // 2])
    time.sleep(0.3)
    path.write_text(text)
    time.sleep(0.3)
    trained = [{k: PROPOSALS[0][k] for k in ("center", "size", "rotation_wxyz", "weight")} | {"members": [0]}]
    path.write_text(proposal_file(step=step, trained_as=trained))
    time.sleep(1.0)


def main(argv):
    signal.signal(signal.SIGINT, signal.default_int_handler)  # as the real CLI does
    mode = os.environ.get("FAKE_TRAINER_MODE", "ok")
    if "propose" in argv:
        return propose(argv, mode)
    if "dataset" in argv:
        return dataset(argv, mode)
    if "sfm" in argv:
        return sfm(argv, mode)
    out = Path(argv[argv.index("--out") + 1])
    job = json.loads(Path(argv[argv.index("--job") + 1]).read_text()) if "--job" in argv else {}
    iterations = int(job.get("iterations", 30))
    checkpoint_every = int(job.get("checkpoint_every") or 1000)
    print("fake trainer: not an event line", flush=True)
    print(f"fake trainer: {mode} run into {out}", file=sys.stderr, flush=True)
    if mode == "crash":
        print("Traceback (most recent call last):\nRuntimeError: the fake trainer crashed", file=sys.stderr)
        sys.exit(3)
    step = 0
    if "--resume" in argv:
        if not (out / "ckpt.pt").is_file():
            print(f"promptgs: error: {out}: nothing to resume (no ckpt.pt)", file=sys.stderr)
            sys.exit(2)
        step = int((out / "ckpt.pt").read_text())
        print(f"fake trainer: resumed at step {step}", file=sys.stderr, flush=True)
        (out / "resumed_at").write_text(str(step))
    if mode == "tree":
        spawn_ranks(out)
    emit(event="start", out=str(out), iterations=iterations, backend="cpu", strategy=job.get("strategy"),
         n_train=10, n_test=2, n_gaussians=100)
    slow = mode in ("slow", "tree")
    last = None
    try:
        while slow or step < iterations:
            step += 1
            n = 100 + 10 * step
            emit(event="progress", step=step, iterations=iterations, loss=1.0 / step, psnr=10.0 + step,
                 n_gaussians=n, elapsed_s=step * 0.01, eta_s=(iterations - step) * 0.01)
            if step % checkpoint_every == 0:
                (out / "ckpt.pt").write_text(str(step))
            if step % 10 == 0:
                last = snapshot(out, step, n, 0)
                if mode == "badsnapshot" and step == iterations:
                    last.write_bytes(b"not a snapshot")
                emit(event="snapshot", step=step, path=str(last), n_gaussians=n)
                if mode == "badsnapshot":
                    time.sleep(0.3)  # each snapshot on its own: a client loads every one
            if job.get("propose_prompts") and step == iterations // 2:
                propose_in_training(out, step)
            time.sleep(0.05 if slow else 0.001)
    except KeyboardInterrupt:
        (out / "cancelled").write_text(str(step))
        emit(event="error", message="KeyboardInterrupt", step=step, log=str(out / "train.log"))
        sys.exit(130)
    (out / "ckpt.pt").write_text(str(step))
    ply = ""
    if mode == "ply" and last is not None:
        write_ply(out / "point_cloud.ply", last)
        ply = str(out / "point_cloud.ply")
    emit(event="done", out=str(out), ply=ply, metrics={"psnr": 20.0})


if __name__ == "__main__":
    main(sys.argv[1:])
