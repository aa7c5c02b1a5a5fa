"""A finished run rendered by Blender's own Gaussian splats (Cycles, Blender 5.3+) from a
dataset camera, against the photo and against ``promptgs render`` of the same camera.

A worker process in a 5.3 ``bpy`` (tests/blender_lines.py) installs the extension zip
built from this checkout, imports the run's dataset, loads the run's ``point_cloud.ply``
with *Load Result* (the Gaussians object is then a ``GAUSSIAN_SPLAT`` point cloud under
the dataset root) and renders it with Cycles on the CPU from the camera, at the run's
image size, with the Standard view transform and a black world, for each setting of
``--variants``: ``SAMPLES`` (Cycles' default pixel filter, Blackman-Harris 1.5 px) or
``SAMPLESbox`` (a 0.01 px filter: one ray per pixel position per sample), and ``SAMPLESdc``
(degree-0 colour only: the ``radiance:sh_*`` attributes removed). With ``--snapshot`` it
also renders a snapshot of a run in training with EEVEE (the engine of the viewport's
Material Preview) from the same camera.

The driver (this interpreter: torch and the engine) renders the camera with ``promptgs
render``, computes the PSNRs and writes ``cycles_splats.json`` and
``cycles_splats.png`` (photo | promptgs render | the Cycles renders of ``--figure``) into ``--out``.

    python benchmarks/blender_cycles_splats.py RUN --camera 12.jpg --out runs/bench/cycles_splats \\
        --variants 16 16box 256 256box 256dc [--snapshot RUN2/snapshots/step_000300.npz]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
ADDON = "bl_ext.user_default.promptgs"


def worker(config: dict) -> dict:
    import bpy

    bpy.ops.extensions.package_install_files(filepath=config["zip"], repo="user_default", enable_on_install=True)
    results, importer = sys.modules[f"{ADDON}.results"], sys.modules[f"{ADDON}.importer"]
    for name in ("Cube", "Light", "Camera"):
        if name in bpy.data.objects:
            bpy.data.objects.remove(bpy.data.objects[name])
    bpy.ops.promptgs.import_colmap(directory=config["dataset"], images=config["images"])
    sc = bpy.context.scene
    for obj in bpy.data.objects:
        if obj.name.startswith("PromptGS Sparse Points"):
            obj.hide_render = True
    importer.use_camera(sc, bpy.data.objects[config["camera"]])
    sc.render.resolution_x, sc.render.resolution_y = config["size"]
    sc.render.resolution_percentage = 100
    sc.view_settings.view_transform, sc.view_settings.look = "Standard", "None"
    sc.world = sc.world or bpy.data.worlds.new("World")
    sc.world.use_nodes = False
    sc.world.color = (0.0, 0.0, 0.0)
    out = {"blender": bpy.app.version_string, "renders": {}}
    obj = results.load_result(bpy.context, Path(config["ply"]))
    assert obj.data.type == "GAUSSIAN_SPLAT", obj.data.type
    sh = {a.name: results.display.get_attribute(obj, a.name) for a in obj.data.attributes if a.name.startswith("radiance:sh_")}
    sc.render.engine = "CYCLES"
    sc.cycles.device = "CPU"
    for variant in config["variants"]:
        samples = int("".join(c for c in variant if c.isdigit()))
        sc.cycles.samples = samples
        sc.cycles.use_denoising = False
        sc.cycles.filter_width = 0.01 if "box" in variant else 1.5
        if "dc" in variant:
            for name in sh:
                obj.data.attributes.remove(obj.data.attributes[name])
        sc.render.filepath = str(Path(config["out"]) / f"cycles_{variant}.png")
        start = time.time()
        bpy.ops.render.render(write_still=True)
        out["renders"][variant] = {"path": sc.render.filepath, "seconds": round(time.time() - start, 1)}
        if "dc" in variant:
            obj = results.load_result(bpy.context, Path(config["ply"]))
    if config.get("snapshot"):
        obj = results.apply_snapshot(bpy.context, Path(config["snapshot"]))
        sc.render.engine = "BLENDER_EEVEE_NEXT" if "BLENDER_EEVEE_NEXT" in [
            e.identifier for e in bpy.types.RenderSettings.bl_rna.properties["engine"].enum_items] else "BLENDER_EEVEE"
        sc.render.filepath = str(Path(config["out"]) / "eevee_snapshot.png")
        start = time.time()
        bpy.ops.render.render(write_still=True)
        out["snapshot"] = {"path": sc.render.filepath, "seconds": round(time.time() - start, 1),
                           "engine": sc.render.engine, "n": len(obj.data.points)}
    return out


def psnr(a, b) -> float:
    """PSNR of two 8-bit images."""
    import numpy as np

    return float(10 * np.log10(255.0 ** 2 / np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, nargs="?")
    parser.add_argument("--camera", default="12.jpg")
    parser.add_argument("--out", type=Path, default=Path("runs/bench/cycles_splats"))
    parser.add_argument("--variants", nargs="*", default=["16", "16box", "256box", "256dc"])
    parser.add_argument("--figure", nargs="*", help="variants in the side-by-side picture (default: the first)")
    parser.add_argument("--snapshot", type=Path, help="a snapshot .npz to render with EEVEE as well")
    parser.add_argument("--worker", type=Path, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        config = json.loads(args.worker.read_text())
        (Path(config["out"]) / "worker.json").write_text(json.dumps(worker(config)))
        return
    import numpy as np
    from PIL import Image

    sys.path[:0] = [str(REPO / "tests"), str(REPO / "tools")]
    import build_extension
    from blender_lines import LINES, line_python

    from promptgs_engine.evaluation import render_run

    run = args.run.resolve()
    cfg = json.loads((run / "cfg.json").read_text())
    out = args.out.resolve()
    out.mkdir(parents=True, exist_ok=True)
    [ours_path] = render_run(run, out / "promptgs_render", [args.camera], quiet=True)
    ours = np.asarray(Image.open(ours_path).convert("RGB"))
    photo = np.asarray(Image.open(Path(cfg["dataset"]) / cfg["images"] / args.camera).convert("RGB").resize(
        (ours.shape[1], ours.shape[0]), Image.LANCZOS))
    line = next(candidate for candidate in LINES if candidate.bpy >= "5.3")
    tmp = Path(tempfile.mkdtemp(prefix="cycles-splats-"))
    config = {"zip": str(build_extension.build(tmp / "zip")), "dataset": cfg["dataset"], "images": cfg["images"],
              "camera": args.camera, "ply": str(run / "point_cloud.ply"), "out": str(out),
              "size": [ours.shape[1], ours.shape[0]], "variants": args.variants,
              "snapshot": str(args.snapshot.resolve()) if args.snapshot else None}
    (tmp / "config.json").write_text(json.dumps(config))
    (tmp / "home").mkdir()
    done = subprocess.run([line_python(line), __file__, "--worker", str(tmp / "config.json")],
                          env=dict(os.environ, HOME=str(tmp / "home")), capture_output=True, text=True)
    if done.returncode != 0:
        raise SystemExit(f"the Blender worker failed:\n{done.stderr[-3000:]}")
    result = json.loads((out / "worker.json").read_text())
    report = {"run": str(run), "camera": args.camera, "size": config["size"], "blender": result["blender"],
              "promptgs_render_vs_photo_db": round(psnr(ours, photo), 2), "load_average": os.getloadavg(),
              "cycles": {}}
    for variant, render in result["renders"].items():
        cycles = np.asarray(Image.open(render["path"]).convert("RGB"))
        report["cycles"][variant] = {"vs_photo_db": round(psnr(cycles, photo), 2),
                                     "vs_promptgs_render_db": round(psnr(cycles, ours), 2), "seconds": render["seconds"]}
        print(f"Cycles {variant:>7}: {report['cycles'][variant]['vs_photo_db']:.2f} dB vs photo, "
              f"{report['cycles'][variant]['vs_promptgs_render_db']:.2f} dB vs promptgs render, {render['seconds']} s")
    print(f"promptgs render: {report['promptgs_render_vs_photo_db']:.2f} dB vs photo")
    if "snapshot" in result:
        report["snapshot"] = result["snapshot"]
    shown = [np.asarray(Image.open(result["renders"][v]["path"]).convert("RGB")) for v in args.figure or args.variants[:1]]
    Image.fromarray(np.concatenate([photo, ours, *shown], axis=1)).save(out / "cycles_splats.png")
    (out / "cycles_splats.json").write_text(json.dumps(report, indent=1))
    print(out / "cycles_splats.json")


if __name__ == "__main__":
    main()
