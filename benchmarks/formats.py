"""What the file formats keep of a trained model: SPZ's quantisation, glTF's exactness, sizes.

For a finished run (its ``point_cloud.ply``, dataset and settings) and each SH degree
(0..3, the PLY's SH cut to it):

- ``psnr``: the test-view PSNR (as ``promptgs eval``) of the PLY, of the SPZ written from
  it and read back (each ``--spz-sh-bits`` setting), and of the glTF read back; the
  ``loss_db`` of each against the PLY of that degree, and ``vs_ply_render_db``, the PSNR
  of the re-imported model's renders against the PLY's own renders;
- ``bytes_per_gaussian`` of each file (SPZ versions 3 and 4);
- ``round_trip``: PLY -> format -> PLY error per attribute, max and mean of |Δ|, and how
  many values differ at all (``changed``): means, log scales, the activated opacity,
  unit quaternions (sign-aligned), SH DC, SH of degree 1, 2, 3.

    python benchmarks/formats.py RUN --out runs/formats.json

Writes the JSON to ``--out`` and prints a table.
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from promptgs_engine.data import load_colmap_scene  # noqa: E402
from promptgs_engine.evaluation import evaluate, render_view  # noqa: E402
from promptgs_engine.render import on_backend_device  # noqa: E402
from promptgs_engine.run_folder import load_run  # noqa: E402
from promptgs_engine.formats import read_splats, save_gaussians  # noqa: E402
from promptgs_engine.formats.splats import Splats, sigmoid  # noqa: E402
from promptgs_engine.metrics import psnr  # noqa: E402


def _unit(q: np.ndarray) -> np.ndarray:
    q = q.astype(np.float64) / np.linalg.norm(q, axis=1, keepdims=True)
    return q * np.where(q[:, :1] < 0, -1.0, 1.0)


def attribute_errors(a: Splats, b: Splats) -> dict:
    """|b - a| per attribute: max, mean, and the count of values that differ."""
    pairs = {
        "means": (a.means, b.means),
        "log_scales": (a.scales, b.scales),
        "opacity": (sigmoid(a.opacities), sigmoid(b.opacities)),
        "opacity_logit": (a.opacities, b.opacities),
        "unit_quats": (_unit(a.quats), _unit(b.quats)),
        "sh0": (a.sh0, b.sh0),
    }
    for band in range(1, a.sh_degree + 1):
        rows = slice(band * band - 1, (band + 1) ** 2 - 1)
        pairs[f"sh_degree_{band}"] = (a.sh_rest[:, rows], b.sh_rest[:, rows])
    out = {}
    for name, (x, y) in pairs.items():
        d = np.abs(np.asarray(y, dtype=np.float64) - np.asarray(x, dtype=np.float64))
        out[name] = {"max": float(d.max()), "mean": float(d.mean()), "changed": int((d > 0).sum()), "values": int(d.size)}
    return out


def renders(params, cameras, cfg) -> list[torch.Tensor]:
    on_device = on_backend_device(params, cfg.backend)
    return [render_view(on_device, cam, cfg.backend, cfg.effective_screen_filter, cfg.rasterize_mode) for cam in cameras]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("run", type=Path, help="a finished run folder")
    parser.add_argument("--out", type=Path, required=True, help="JSON file to write")
    parser.add_argument("--sh-degrees", type=int, nargs="+", default=[0, 1, 2, 3])
    parser.add_argument("--spz-sh-bits", nargs="+", default=["8,8", "7,6", "6,5", "5,4"],
                        help="SPZ SH code bits, degree 1 and degrees 2-3 (Niantic's default: 5,4)")
    args = parser.parse_args()

    cfg, params = load_run(args.run)
    full = Splats.from_params(params, antialiased=cfg.antialiased)
    scene = load_colmap_scene(cfg.dataset, images=cfg.images, test_every=cfg.test_every)
    cameras = [c.downscaled(cfg.downscale) for c in scene.test_cameras]
    bit_settings = [tuple(int(v) for v in s.split(",")) for s in args.spz_sh_bits]

    def test_psnr(p) -> float:
        m = evaluate(p, scene.test_cameras, cfg.downscale, backend=cfg.backend, quiet=True,
                     screen_filter=cfg.effective_screen_filter, rasterize_mode=cfg.rasterize_mode)
        return float(m["psnr"])

    result = {
        "run": str(args.run), "dataset": cfg.dataset, "images": cfg.images, "n_gaussians": full.n,
        "trained_sh_degree": full.sh_degree, "n_test_views": len(cameras),
        "resolution": [cameras[0].width, cameras[0].height], "machine": platform.processor() or platform.machine(),
        "degrees": {},
    }
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        for degree in args.sh_degrees:
            ref = full.with_sh_degree(degree)
            ref_params = ref.to_params()
            ref_renders = renders(ref_params, cameras, cfg)
            row: dict = {"psnr": {}, "loss_db": {}, "vs_ply_render_db": {}, "bytes_per_gaussian": {},
                         "round_trip": {}, "seconds": {}}
            variants = [("ply", tmp / "m.ply", {})]
            for bits in bit_settings:
                for version in (3, 4):
                    variants.append((f"spz_v{version}_sh{bits[0]}{bits[1]}", tmp / f"m{version}{bits[0]}{bits[1]}.spz",
                                     {"spz_version": version, "spz_sh_bits": bits}))
            variants.append(("glb", tmp / "m.glb", {}))
            for name, path, options in variants:
                t0 = time.perf_counter()
                save_gaussians(path, ref, **options)
                t1 = time.perf_counter()
                back = read_splats(path)
                t2 = time.perf_counter()
                row["bytes_per_gaussian"][name] = path.stat().st_size / ref.n
                row["seconds"][name] = {"write": t1 - t0, "read": t2 - t1}
                row["round_trip"][name] = attribute_errors(ref, back)
                if name.startswith("spz_v4"):
                    continue  # the same codes as version 3: the same Gaussians
                back_params = back.to_params()
                row["psnr"][name] = test_psnr(back_params)
                got = renders(back_params, cameras, cfg)
                row["vs_ply_render_db"][name] = float(np.mean([psnr(g, r) for g, r in zip(got, ref_renders)]))
            for name, value in row["psnr"].items():
                row["loss_db"][name] = row["psnr"]["ply"] - value
            result["degrees"][str(degree)] = row
            print(f"SH degree {degree}: " + ", ".join(
                f"{name} {row['psnr'][name]:.3f} dB ({row['loss_db'][name]:+.3f}), {row['bytes_per_gaussian'][name]:.1f} B"
                for name in row["psnr"]), flush=True)
    result["note"] = "timings were taken on a shared 2-core machine while other work ran: indicative only"
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=2))
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
