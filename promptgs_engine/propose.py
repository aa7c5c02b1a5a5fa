"""Proposing prompts from a run: render every training view at full size, gather the
residual evidence (`residuals`), keep what several views agree on (`proposals`).

Used by ``promptgs propose RUN`` (`propose_run`: a finished run, or a snapshot of one
still training) and by the trainer's ``--propose-prompts`` (`TrainingProposer`, which
`focus.PromptFocus` calls at its steps).
"""

from __future__ import annotations

import dataclasses
import json
import logging
from pathlib import Path
from typing import Callable, Sequence

import numpy as np
import torch
from tqdm import tqdm

from .data import Camera, load_colmap_scene
from .errors import PromptError
from .gaussians import sh_degree_of
from .prompts import PromptBox, check_visible, contains_any
from .proposals import Proposal, ProposalSet, ProposalSettings, group_boxes, load_proposals, merge_rounds, propose
from .render import on_backend_device, render, resolve_backend
from .residuals import ResidualSettings, ViewEvidence, view_evidence
from .run_folder import load_run

log = logging.getLogger("promptgs.propose")

PROPOSALS_FILE = "proposals.json"
# The trainer adds proposals of at least this confidence (the file keeps them all).
TRAIN_MIN_CONFIDENCE = 0.3
# The trainer groups proposals whose centres chain within this many times the median
# box edge (about 60-80 pixels at the objects' depth: their crops would overlap) into one
# prompt: a small box around each object, even at its true position from step 0, trains
# a group of neighbours worse than one box around the group does (its related steps see
# each object in fewer, smaller crops).
GROUP_LINK_EDGES = 8.0


def proposal_step(refine_start: int, refine_stop: int, reset_every: int) -> int:
    """When the trainer proposes: half-way between the first opacity reset and the next.
    By then the render has been through a reset and regrown, so what it still misses is
    missing, not just late; right after a reset every opacity is low and everything looks
    missing. Resampling keeps most of the densification window (at 600 steps: step 150
    of 10–300, resampling at 190, 230, 290; at 1500: 225 of 25–750). Earlier, before the
    first reset has passed, the proposals hold the true objects and as many wrong boxes
    on distant terrain that the render has not fitted yet. A run too short to reset
    proposes half-way through the window."""
    step = reset_every + reset_every // 2
    if not refine_start < step < refine_stop:
        step = (refine_start + refine_stop) // 2
    return step


def proposal_steps(refine_start: int, refine_stop: int, reset_every: int) -> list[int]:
    """The steps the trainer proposes at: `proposal_step`, and one opacity reset later
    where that is still inside the refinement window (at 600 steps: 150 and 250; at
    1500: 225 and 375). The second round adds only what the first one's prompts do not
    hold: where the render of the first round had drawn something at an object's depth in
    every view, the object was rejected as lying on its surface, and a reset later it is
    proposed."""
    first = proposal_step(refine_start, refine_stop, reset_every)
    second = first + reset_every
    return [first, second] if refine_start < second < refine_stop else [first]


RenderFn = Callable[[Camera], tuple[torch.Tensor, torch.Tensor, torch.Tensor]]  # rgb [H,W,3], depth [H,W], alpha [H,W]


def gather_evidence(
    render_fn: RenderFn,
    cameras: Sequence[Camera],
    settings: ResidualSettings = ResidualSettings(),
    quiet: bool = True,
) -> list[ViewEvidence]:
    """Each camera rendered (``render_fn``) and compared with its image."""
    out = []
    for cam in tqdm(cameras, desc="evidence", disable=quiet, unit="view"):
        rgb, depth, alpha = render_fn(cam)
        out.append(view_evidence(cam.load_image(), rgb, depth, alpha, settings))
    return out


def propose_views(
    render_fn: RenderFn,
    cameras: Sequence[Camera],
    residual_settings: ResidualSettings = ResidualSettings(),
    settings: ProposalSettings = ProposalSettings(),
    quiet: bool = True,
    points: torch.Tensor | None = None,
) -> ProposalSet:
    """Proposals from every camera's render (``points``: the dataset's SfM points, which
    reject a proposal lying among them; see `proposals.propose`)."""
    evidence = gather_evidence(render_fn, cameras, residual_settings, quiet)
    settings = dataclasses.replace(settings, detection_threshold=residual_settings.threshold,
                                   min_contrast=residual_settings.min_contrast)
    result = propose(cameras, evidence, [c.name for c in cameras], settings, points=points)
    result.info["residual_settings"] = residual_settings.__dict__
    return result


def visible_boxes(boxes: Sequence[PromptBox], cameras: Sequence[Camera]) -> list[PromptBox]:
    """The boxes that some camera shows (a prompt no camera sees is an error for training)."""
    keep = []
    for box in boxes:
        try:
            check_visible([box], cameras)
            keep.append(box)
        except PromptError:
            continue
    return keep


def params_renderer(params, backend: str, screen_filter: float, rasterize_mode: str, sh_degree: int | None = None) -> RenderFn:
    """A `RenderFn` drawing ``params`` (a Gaussian ParameterDict) with RGB and expected depth."""
    degree = sh_degree_of(params) if sh_degree is None else sh_degree

    @torch.no_grad()
    def draw(cam: Camera):
        device = params["means"].device
        out, alpha, _ = render(
            params["means"], params["quats"], torch.exp(params["scales"]), torch.sigmoid(params["opacities"]),
            torch.cat([params["sh0"], params["shN"]], dim=1),
            cam.world_to_camera[None].to(device), cam.K[None].to(device), cam.width, cam.height,
            sh_degree=degree, backend=backend, eps2d=screen_filter, rasterize_mode=rasterize_mode, render_mode="RGB+ED",
        )
        return out[0, ..., :3].clamp(0, 1).cpu(), out[0, ..., 3].cpu(), alpha[0, ..., 0].cpu()

    return draw


def propose_run(run_dir: Path, out: Path | None = None, snapshot: Path | None = None, quiet: bool = False) -> tuple[ProposalSet, Path]:
    """Proposals for a run folder (its ``point_cloud.ply``, or ``snapshot``), written to
    ``out`` (default ``RUN/proposals.json``)."""
    cfg, params = load_run(run_dir, snapshot)
    scene = load_colmap_scene(cfg.dataset, images=cfg.images, test_every=cfg.test_every)
    cameras = [c.downscaled(cfg.downscale) for c in scene.train_cameras]
    backend = resolve_backend(cfg.backend)
    draw = params_renderer(on_backend_device(params, backend), backend, cfg.effective_screen_filter, cfg.rasterize_mode)
    result = propose_views(draw, cameras, quiet=quiet, points=scene.points)
    result.info.update({"run": str(Path(run_dir).resolve()), "dataset": str(cfg.dataset),
                        "snapshot": str(snapshot) if snapshot else None, "resolution": [cameras[0].width, cameras[0].height]})
    path = Path(out) if out is not None else Path(run_dir) / PROPOSALS_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    result.save(path)
    return result, path


def proposals_to_seed(
    proposals: Sequence[Proposal], given: Sequence[PromptBox], earlier: Sequence[PromptBox]
) -> list[Proposal]:
    """The proposals of a round that get a seed Gaussian: those whose point neither a
    prompt the run was given (a prompt file, the centre box) nor an earlier round's
    proposal box (``earlier``: their boxes of training confidence) holds. Each object is
    seeded once, by the first round that finds it. An object that an earlier round missed
    but whose point lies inside a prompt an earlier round added (a group of its
    neighbours) is seeded too: checked against those group prompts instead, an object
    that only the second round proposed got no seed, the Gaussians resampling put there
    faded, and it was missed in every view."""
    points = torch.tensor([p.point for p in proposals], dtype=torch.float64).reshape(-1, 3)
    held = contains_any([*given, *earlier], points).tolist()
    return [p for p, h in zip(proposals, held) if not h]


class TrainingProposer:
    """The trainer's ``--propose-prompts``: at each of its ``steps`` (`proposal_steps`) it
    renders every training view at full size, proposes, writes ``RUN/proposals.json``
    (what every round so far proposed, `merge_rounds`; ``RUN/proposals_stepNNNNNN.json``
    keeps each round's own) and returns the prompts to add: the proposals of at least
    `TRAIN_MIN_CONFIDENCE`, grouped (`GROUP_LINK_EDGES`), whose centre no existing prompt
    holds (the file's ``trained_as`` lists them and their members). The trainer seeds a
    Gaussian at each of `trained` (`proposals_to_seed`).

    ``cameras``: the training views at full training size; ``points``: the dataset's SfM
    points; ``given``: the prompts the run started with (a prompt file, the centre box);
    ``run_dir``: the run folder, written only where ``writes`` (rank 0 of a distributed
    run); ``backend``, ``screen_filter`` and ``rasterize_mode``: how the run renders."""

    def __init__(
        self,
        cameras: Sequence[Camera],
        points: torch.Tensor,
        steps: Sequence[int],
        run_dir: Path,
        dataset: str,
        backend: str,
        screen_filter: float,
        rasterize_mode: str,
        given: Sequence[PromptBox] = (),
        writes: bool = True,
    ):
        self.cameras = list(cameras)
        self.points = points
        self.steps = list(steps)
        self.run_dir = Path(run_dir)
        self.dataset = dataset
        self.backend = backend
        self.screen_filter = screen_filter
        self.rasterize_mode = rasterize_mode
        self.given = list(given)
        self.writes = writes
        self.result: ProposalSet | None = None
        self.trained: list[Proposal] = []  # the proposals the last `run` trained (their boxes)
        path = self.run_dir / PROPOSALS_FILE
        if path.is_file():  # a resumed run: the snapshot keeps showing what was proposed
            try:
                self.result = _result_from_file(path)
            except (PromptError, ValueError, KeyError, json.JSONDecodeError):
                self.result = None

    def is_step(self, step: int) -> bool:
        return step in self.steps

    def run(self, step: int, existing: Sequence[PromptBox], params, sh_degree: int) -> list[PromptBox]:
        """Propose from the Gaussians ``params`` drawn at ``sh_degree``; the prompts to add
        (the groups whose centre no ``existing`` prompt holds). `trained` is then the
        proposals to seed: those of confidence ≥ `TRAIN_MIN_CONFIDENCE` that
        `proposals_to_seed` keeps."""
        draw = params_renderer(params, self.backend, self.screen_filter, self.rasterize_mode, sh_degree)
        result = propose_views(draw, self.cameras, points=self.points)
        result.info.update({"step": step, "dataset": self.dataset, "resolution": [self.cameras[0].width, self.cameras[0].height]})
        boxes = visible_boxes(result.boxes(TRAIN_MIN_CONFIDENCE), self.cameras)
        earlier = self.result.boxes(TRAIN_MIN_CONFIDENCE) if self.result is not None else []
        self.trained = proposals_to_seed([p for p in result.proposals if any(p.box is b for b in boxes)], self.given, earlier)
        groups: list[PromptBox] = []
        if boxes:
            edge = float(np.median([max(b.size) for b in boxes]))
            groups, members = group_boxes(boxes, GROUP_LINK_EDGES * edge)
            if existing:  # an earlier round (or the user) has these already
                new = ~contains_any(list(existing), torch.tensor([g.center for g in groups], dtype=torch.float64))
                groups, members = [g for g, k in zip(groups, new.tolist()) if k], [m for m, k in zip(members, new.tolist()) if k]
            result.info["trained_as"] = [{**g.to_dict(), "members": m} for g, m in zip(groups, members)]
        # What Blender shows and the file holds: every round's proposals (a drone the first
        # round proposed and its prompt then reconstructed is not proposed again).
        self.result = merge_rounds(self.result, result)
        # Every rank of a distributed run proposes from the same parameters and gets the same
        # boxes; rank 0 alone writes the files: all rounds so far, and each round by its step.
        if self.writes:
            self.result.save(self.run_dir / PROPOSALS_FILE)
            result.save(self.run_dir / f"proposals_step{step:06d}.json")
        log.info("step %d: %d proposed prompts (%d rejected hypotheses; candidates per view: median %d)",
                 step, len(groups), len(result.rejected), int(sorted(result.n_candidates.values())[len(result.n_candidates) // 2]))
        return groups

    def arrays(self) -> dict:
        return self.result.to_arrays() if self.result is not None else {}


def _result_from_file(path: Path) -> ProposalSet:
    """A ProposalSet holding only the boxes of a proposal file (for snapshot arrays)."""
    boxes, conf = load_proposals(path)
    props = [Proposal(b, c, b.center, [], 0, 0, 0.0, 0.0) for b, c in zip(boxes, conf)]
    return ProposalSet(props, [], {}, {})
