"""Where a run's Gaussians come from: a training job repeated with an id on every Gaussian.

Each Gaussian gets an id at the start, carried through gsplat's growth and pruning (they
copy every per-Gaussian tensor of the strategy state, so a grown copy starts with its
parent's id); after each step the copies, and the Gaussians that resampling or a
proposal added, get ids of their own, and each such birth is recorded with its parent's
id (0 for an added one) and place (a split removes the parent and appends two copies:
the first keeps the id, so along a line a split shows as a move). Optionally the Gaussians within ``--radius`` of a
point are recorded after every step (id, place, opacity, largest scale, base colour,
whether resampling made them). The id changes no bit of the run: it ends with the
Gaussians and PSNR of the job run plainly.

    python benchmarks/lineage.py JOB.json --out OUT [--near X Y Z --radius R]
    python benchmarks/lineage.py JOB.json --out OUT --trace INDEX   # after a first run: INDEX's line

Writes the run into ``OUT/run`` and ``OUT/lineage.json``: the births, the watched
Gaussians per step, and for ``--trace`` (an index into the final model) its line of
ancestors with the step each was born at and where.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import torch

from promptgs_engine.cli import main as cli_main
from promptgs_engine.gaussians import sh_to_rgb
from promptgs_engine.strategies.default import ResettingDefaultStrategy
from promptgs_engine.train import Trainer

ID = "lineage_id"  # a per-Gaussian tensor of the strategy state: growth and pruning carry it


class Lineage:
    def __init__(self, near: list[float] | None, radius: float) -> None:
        self.next_id = 1
        self.births: list[dict[str, Any]] = []
        self.near = torch.tensor(near, dtype=torch.float32) if near else None
        self.radius = radius
        self.watched: dict[int, list[dict[str, Any]]] = {}

    def start(self, state: dict[str, Any], n: int) -> None:
        state[ID] = torch.arange(1, n + 1, dtype=torch.float64)
        self.next_id = n + 1

    def after_step(self, params, state: dict[str, Any], step: int) -> None:
        ids = state.get(ID)
        if ids is None:
            return
        means = params["means"].detach()
        # Copies of a parent share its id; an added Gaussian has id 0. Every one after the
        # first holder of an id (and every 0) is a birth.
        order = torch.argsort(ids, stable=True)
        sorted_ids = ids[order]
        repeat = torch.zeros_like(sorted_ids, dtype=torch.bool)
        repeat[1:] = sorted_ids[1:] == sorted_ids[:-1]
        repeat |= sorted_ids == 0
        for i in order[repeat].tolist():
            parent = int(ids[i])
            ids[i] = float(self.next_id)
            self.births.append({"step": step, "id": self.next_id, "parent": parent,
                                "position": [round(float(v), 4) for v in means[i]]})
            self.next_id += 1
        if self.near is not None:
            close = ((means - self.near.to(means.device)).norm(dim=1) < self.radius).nonzero().flatten()
            carved = state.get("carved")
            self.watched[step] = [
                {
                    "id": int(ids[i]),
                    "position": [round(float(v), 4) for v in means[i]],
                    "opacity": round(float(torch.sigmoid(params["opacities"][i].detach()).flatten()[0]), 4),
                    "scale": round(float(torch.exp(params["scales"][i].detach()).max()), 4),
                    "colour": [round(float(v), 3) for v in sh_to_rgb(params["sh0"][i, 0].detach())],
                    "carved": bool(carved[i] > 0) if isinstance(carved, torch.Tensor) else None,
                }
                for i in close.tolist()
            ]

    def line_of(self, final_id: int) -> list[dict[str, Any]]:
        by_id = {b["id"]: b for b in self.births}
        line, current = [], final_id
        while current in by_id:
            line.append(by_id[current])
            current = by_id[current]["parent"]
        return line


def install(lineage: Lineage) -> None:
    init = Trainer.__init__
    post = ResettingDefaultStrategy.step_post_backward

    def trainer_init(self: Trainer, *args: Any, **kwargs: Any) -> None:
        init(self, *args, **kwargs)
        lineage.start(self.strategy_state, self.n_gaussians)

    def step_post_backward(self, params, optimizers, state, step, info, packed: bool = False) -> None:
        post(self, params, optimizers, state, step, info, packed=packed)
        lineage.after_step(params, state, step)

    Trainer.__init__ = trainer_init
    ResettingDefaultStrategy.step_post_backward = step_post_backward


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("job", type=Path, help="a job file (promptgs train --job)")
    ap.add_argument("--out", type=Path, required=True)
    ap.add_argument("--near", type=float, nargs=3, metavar=("X", "Y", "Z"), help="record the Gaussians near this point")
    ap.add_argument("--radius", type=float, default=0.5)
    ap.add_argument("--trace", type=int, action="append", default=[], help="index in the final model whose line to report")
    args = ap.parse_args(argv)
    lineage = Lineage(args.near, args.radius)
    install(lineage)
    run = args.out / "run"
    cli_main(["train", "--job", str(args.job), "--out", str(run), "--overwrite", "--quiet"])
    ckpt = torch.load(run / "ckpt.pt", map_location="cpu", weights_only=False)
    final_ids = ckpt["strategy_state"][ID]
    metrics = json.loads((run / "metrics.json").read_text())
    result = {
        "job": str(args.job),
        "n_gaussians": metrics.get("n_gaussians"),
        "psnr": metrics.get("psnr"),
        "near": args.near,
        "radius": args.radius,
        "traced": {str(i): lineage.line_of(int(final_ids[i])) for i in args.trace},
        "births": lineage.births,
        "watched": {str(k): v for k, v in lineage.watched.items()},
    }
    (args.out / "lineage.json").write_text(json.dumps(result))
    print(f"{result['n_gaussians']} Gaussians, PSNR {result['psnr']:.4f}; {len(lineage.births)} births recorded")
    for index, line in result["traced"].items():
        print(f"Gaussian {index}: " + " <- ".join(f"step {b['step']} at {b['position']}" for b in line))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
