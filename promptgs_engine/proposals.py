"""Proposed prompts: residual candidates of several views that meet in 3D.

Each view's candidates (`residuals.view_evidence`: pixels where the render misses a
small, high-contrast blob the image has) define rays. A static object that 3DGS lost
shows in many views, and their rays meet at it; a terrain texture the render has not
fitted, noise, or a moving object gives rays that do not meet. Steps (formulas also in
docs/promptgs.md, "Proposed prompts"):

1. **Voting along the rays.** Each candidate's ray is sampled from the camera up to the
   render's depth at its pixel (the missing object must lie in front of what the render
   shows there; × 1.1 for slack), every voxel of a fine grid (``voxel_px`` pixels at the
   typical depth) records which views' rays pass through it (a bit mask per voxel), and a
   voxel's count is the number of distinct views over its 3 × 3 × 3 neighbourhood. Only
   the voxels that the ray of a *seeding* candidate (``detection_threshold`` or more)
   passes are counted, but there the rays of every candidate count (``weak_votes``): an
   object of low contrast against its background is a seeding candidate in one or two
   views and a weaker one in a dozen (the sparse mountain's black and red drones).
2. **Hypotheses.** Voxels reached by at least ``min_views`` views, best first (greedy,
   ``suppress_voxels`` apart): in each view the nearest unused candidate within
   ``gather_px`` of the voxel's projection joins; the point is triangulated (least
   squares over the rays) and views whose reprojection error exceeds ``tolerance_px``
   leave one by one. A hypothesis without a seeding candidate among its views is
   dropped: weaker candidates support what a strong one proposes, never alone (rays of
   weak candidates on the horizon rows of cameras at one height all meet in the plane
   of the cameras).
3. **Check against every view.** The point is projected into all cameras; a view *sees*
   it when it falls in the image and the render's surface there is not clearly in front
   of it (depth ≥ 0.9 × the point's). A seeing view *supports* it when one of its
   candidates (any strength) lies within ``support_px`` of the projection and no earlier
   hypothesis claimed it (a candidate explains one point: with a repetitive texture, rays
   through different spots meet at ghost points above the ground, whose views' blobs
   belong to the spots), or when the residual at the pixel it projects into has, along
   the object's colour, a strength of at least ``matched_strength`` (in the local-noise
   units of ``S``) and a contrast of at least ``min_contrast`` (``matched`` support). The
   object's colour is the mean unit direction of the residual's response (per colour
   channel) at the candidates it was triangulated from. A faint object's residual is
   often no local maximum of ``S ≥ support_threshold`` in a view, and so no candidate,
   yet it is there with the object's colour; a point where rays met by chance lands on
   residuals of any colour.
4. **Decision.** Accepted when at least ``min_views`` views are consistent and the
   supporting views are at least ``min_support_fraction`` of the seeing ones. Otherwise
   rejected with a reason: ``few_views`` (its rays meet in fewer than ``min_views``
   views), ``surface`` (in most supporting views the render's surface is not behind the
   point around it, at 6 of 8 points of a ring just outside the object, by
   ``min_clearance`` of its depth and by three standard deviations of its triangulated
   depth (step 5): a texture
   detail or a silhouette the render has not fitted, or a distant point whose depth the
   views cannot tell apart from the surface's), ``explained`` (most views that see the spot show no residual, and the image
   has a blob there: the render already draws it), ``inconsistent`` (most views that
   see the spot show nothing there: a moving object or a view-dependent effect),
   ``reconstructed`` (with the dataset's SfM points given: one lies within
   ``sfm_radii`` object radii of the point, so SfM triangulated structure there: a
   texture detail or the tip of a leaf, which training from those points will fit, not
   an object that SfM and the render both lost).
5. **Box and confidence.** The box is centred on the point, its axes are those of the
   triangulation's covariance ``σ² (Σ JᵀJ)⁻¹`` (``J`` the 2 × 3 projection Jacobians,
   ``σ`` the reprojection RMS, at least 0.5 px): half-sizes ``3·sqrt(eigenvalue)``,
   at least the object's radius (``2 × blob width + 2`` pixels at the point's depth) and
   at most 8 times it. Confidence (`confidence`)
   ``f · (1 − exp(−(n − 2) / 6)) · min(1, s / t) · (1 − 0.5 · rms / tolerance_px)``
   with ``f`` the supporting fraction, ``n`` the supporting views, ``s`` the consistent
   views' median residual strength and ``t`` the detection threshold, in [0, 1].

Strong candidates that no accepted proposal uses and that no explained hypothesis
accounts for are listed as ``unmatched`` per view: a moving object shows there.

The proposal file (``promptgs propose``) is a prompt file (docs/interfaces.md) whose
entries also carry ``confidence`` and ``evidence``; the format is in
docs/interfaces.md, "Proposal file".
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Sequence

import numpy as np

from .prompts import CameraLike, PromptBox
from .residuals import ViewEvidence

__all__ = ["ProposalSettings", "Proposal", "Rejected", "ProposalSet", "propose", "load_proposals", "group_boxes"]

SCHEMA = "promptgs-proposals/1"
_BITS = 21
_OFF = 1 << (_BITS - 1)
_WORD_BITS = 62  # views per int64 word of a voxel's view mask (keeps the words positive)


@dataclass(frozen=True)
class ProposalSettings:
    """Parameters of the multi-view step (see the module docstring)."""

    min_views: int = 3
    voxel_px: float = 2.0  # voting voxel edge, in pixels at the typical candidate depth
    gather_px: float = 4.0  # candidates this close to a hypothesis' projection join it
    tolerance_px: float = 1.5  # reprojection error of a consistent view
    support_px: float = 2.0  # a view supports a point with a candidate this close to its projection
    min_support_fraction: float = 0.4  # supporting / seeing views of an accepted proposal
    detection_threshold: float = 5.0  # candidates this strong seed hypotheses (ResidualSettings.threshold)
    occlusion_margin: float = 0.1  # the render's surface must be nearer than (1 − margin) × depth to hide the point
    min_clearance: float = 0.05  # an object lies in front of the render's surface by this fraction of its depth
    depth_slack: float = 1.1  # rays are followed to this multiple of the render's depth
    suppress_voxels: float = 3.0  # hypotheses are at least this many voxels apart
    max_hypotheses: int = 4000
    max_proposals: int = 64
    max_rejected: int = 64
    max_unmatched_per_view: int = 16
    unmatched_strength: float = 10.0  # candidates this strong that nothing accounts for are listed
    weak_votes: bool = True  # weaker candidates vote too, in the voxels that seeding ones reach
    matched_strength: float = 2.0  # residual along the object's colour that supports a point (0: off)
    min_contrast: float = 0.03  # ... and its contrast (ResidualSettings.min_contrast)
    # An SfM point this close to a point, in object radii, rejects it: real fine structure
    # (fern's frond tips) lies about four radii from its nearest SfM point and must not be
    # proposed as a missing object; the generated scenes' drones lie ten radii or more away.
    sfm_radii: float = 5.0


@dataclass
class Observation:
    """One view's evidence for a proposal: the candidate pixel and its strength."""

    view: str
    uv: tuple[float, float]
    strength: float
    reprojection_px: float

    def to_dict(self) -> dict[str, Any]:
        return {"view": self.view, "uv": [round(self.uv[0], 2), round(self.uv[1], 2)],
                "strength": round(self.strength, 2), "reprojection_px": round(self.reprojection_px, 3)}


@dataclass
class Proposal:
    """An accepted proposal: a small oriented box around a triangulated point."""

    box: PromptBox  # weight = confidence
    confidence: float
    point: tuple[float, float, float]
    observations: list[Observation]  # the consistent views (triangulated from)
    n_seeing: int  # views that see the point (in the image, not hidden by the render's surface)
    n_supporting: int  # seeing views with residual evidence there
    rms_px: float
    radius: float  # estimated object radius (world units)
    colour: tuple[float, float, float] = (0.5, 0.5, 0.5)  # the images' median colour at its candidates
    pixel: float = 0.0  # world size of one pixel at the point (median over its views)

    def to_dict(self) -> dict[str, Any]:
        entry = self.box.to_dict()
        entry["confidence"] = round(self.confidence, 4)
        entry["evidence"] = {
            "point": [float(v) for v in self.point],
            "radius": float(self.radius),
            "colour": [round(float(c), 4) for c in self.colour],
            "pixel": float(self.pixel),
            "rms_px": round(self.rms_px, 3),
            "n_seeing": self.n_seeing,
            "n_supporting": self.n_supporting,
            "observations": [o.to_dict() for o in self.observations],
        }
        return entry


@dataclass
class Rejected:
    """A hypothesis that was not boxed, and why."""

    point: tuple[float, float, float]
    reason: str  # few_views | surface | explained | inconsistent | reconstructed
    observations: list[Observation]
    n_seeing: int
    n_supporting: int

    def to_dict(self) -> dict[str, Any]:
        return {"point": [float(v) for v in self.point], "reason": self.reason, "n_seeing": self.n_seeing,
                "n_supporting": self.n_supporting, "observations": [o.to_dict() for o in self.observations]}


@dataclass
class ProposalSet:
    proposals: list[Proposal]
    rejected: list[Rejected]
    unmatched: dict[str, list[dict[str, Any]]]  # view name -> [{"uv", "strength"}]
    n_candidates: dict[str, int]  # view name -> candidates found
    settings: ProposalSettings = field(default_factory=ProposalSettings)
    info: dict[str, Any] = field(default_factory=dict)

    def boxes(self, min_confidence: float = 0.0) -> list[PromptBox]:
        return [p.box for p in self.proposals if p.confidence >= min_confidence]

    def to_json(self) -> dict[str, Any]:
        return {
            "schema": SCHEMA,
            "prompts": [p.to_dict() for p in self.proposals],
            "rejected": [r.to_dict() for r in self.rejected],
            "unmatched": self.unmatched,
            "n_candidates": self.n_candidates,
            "settings": self.settings.__dict__,
            **self.info,
        }

    def save(self, path: str | Path) -> None:
        path = Path(path)
        tmp = path.with_name(path.name + ".tmp")
        tmp.write_text(json.dumps(self.to_json(), indent=1) + "\n", encoding="utf-8")
        tmp.replace(path)

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Snapshot arrays (float32): ``proposal_centers`` [P, 3], ``proposal_sizes`` [P, 3],
        ``proposal_rotations`` [P, 4] wxyz, ``proposal_confidence`` [P]."""
        p = self.proposals
        return {
            "proposal_centers": np.asarray([x.box.center for x in p], np.float32).reshape(-1, 3),
            "proposal_sizes": np.asarray([x.box.size for x in p], np.float32).reshape(-1, 3),
            "proposal_rotations": np.asarray([x.box.rotation_wxyz for x in p], np.float32).reshape(-1, 4),
            "proposal_confidence": np.asarray([x.confidence for x in p], np.float32).reshape(-1),
        }


def merge_rounds(earlier: ProposalSet | None, latest: ProposalSet) -> ProposalSet:
    """What the proposal rounds of a run have shown so far: ``earlier``'s proposals, then
    those of ``latest`` whose point no earlier proposal's box holds (a drone proposed in
    the first round and reconstructed by the second is still shown). Rejections, candidate
    counts and settings are the latest round's; ``trained_as`` lists every round's groups,
    and ``rounds`` the steps of the rounds merged."""
    import torch

    from .prompts import contains_any

    def rounds(ps: ProposalSet) -> list:
        return list(ps.info.get("rounds", [ps.info["step"]] if "step" in ps.info else []))

    before = earlier.proposals if earlier is not None else []
    points = torch.tensor([p.point for p in latest.proposals], dtype=torch.float64).reshape(-1, 3)
    held = contains_any([p.box for p in before], points).tolist()
    info = {**(earlier.info if earlier is not None else {}), **latest.info}
    info["trained_as"] = list(earlier.info.get("trained_as", []) if earlier is not None else []) + list(
        latest.info.get("trained_as", []))
    info["rounds"] = (rounds(earlier) if earlier is not None else []) + rounds(latest)
    return ProposalSet(before + [p for p, h in zip(latest.proposals, held) if not h], latest.rejected,
                       latest.unmatched, latest.n_candidates, latest.settings, info)


def load_proposals(path: str | Path) -> tuple[list[PromptBox], list[float]]:
    """The boxes of a proposal file and their confidences (a plain prompt file reads with
    confidence 1). Raises :class:`PromptError` as `prompts.load_prompts` does."""
    from .prompts import load_prompts

    boxes = load_prompts(path)
    obj = json.loads(Path(path).read_text(encoding="utf-8"))
    return boxes, [float(e.get("confidence", 1.0)) for e in obj["prompts"]]


def group_boxes(boxes: Sequence[PromptBox], link: float) -> tuple[list[PromptBox], list[list[int]]]:
    """Boxes whose centres are chained within ``link`` of each other (single linkage),
    each group as one axis-aligned box around its members' corners (weight: the largest
    member weight). Returns the group boxes and their member indices, largest weight first."""
    n = len(boxes)
    parent = list(range(n))

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    centers = np.array([b.center for b in boxes], dtype=np.float64).reshape(-1, 3)
    for i in range(n):
        for j in range(i + 1, n):
            if np.linalg.norm(centers[i] - centers[j]) <= link:
                parent[root(i)] = root(j)
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(root(i), []).append(i)
    out = []
    for members in groups.values():
        corners = np.concatenate([boxes[i].corners().numpy() for i in members])
        lo, hi = corners.min(axis=0), corners.max(axis=0)
        weight = max(boxes[i].weight for i in members)
        out.append((PromptBox(tuple((lo + hi) / 2), tuple(hi - lo), (1.0, 0.0, 0.0, 0.0), weight), sorted(members)))
    out.sort(key=lambda g: (-g[0].weight, g[1][0]))
    return [g[0] for g in out], [g[1] for g in out]


# -- geometry -----------------------------------------------------------------------------


@dataclass
class _Cam:
    R: np.ndarray  # [3, 3] world to camera
    t: np.ndarray  # [3]
    K: np.ndarray  # [3, 3]
    Kinv: np.ndarray
    center: np.ndarray  # [3]
    width: int
    height: int

    @classmethod
    def of(cls, camera: CameraLike) -> "_Cam":
        w2c = np.asarray(_np(camera.world_to_camera), np.float64)
        K = np.asarray(_np(camera.K), np.float64)
        R, t = w2c[:3, :3], w2c[:3, 3]
        return cls(R, t, K, np.linalg.inv(K), -R.T @ t, int(camera.width), int(camera.height))

    def project(self, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """uv [N, 2] and depth z [N] of world points [N, 3]."""
        p = x @ self.R.T + self.t
        z = p[:, 2]
        q = p @ self.K.T
        return q[:, :2] / np.maximum(z, 1e-9)[:, None], z

    def rays(self, uv: np.ndarray) -> np.ndarray:
        """World directions [N, 3] scaled so the parameter along them is camera depth z."""
        pix = np.concatenate([uv, np.ones((len(uv), 1))], axis=1)
        return (pix @ self.Kinv.T) @ self.R  # R^T (K^-1 p), row form

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """[2, 3] derivative of the pixel position at world point x [3]."""
        p = self.R @ x + self.t
        z = p[2]
        fx, fy, s = self.K[0, 0], self.K[1, 1], self.K[0, 1]
        j_cam = np.array([[fx / z, s / z, -(fx * p[0] + s * p[1]) / z**2], [0.0, fy / z, -fy * p[1] / z**2]])
        return j_cam @ self.R


def _t(x: np.ndarray):
    import torch

    return torch.as_tensor(np.asarray(x, np.float64).reshape(1, 3))


def _np(x: Any) -> np.ndarray:
    if hasattr(x, "detach"):
        x = x.detach().cpu().double().numpy()
    return np.asarray(x)


def _pack(c: np.ndarray) -> np.ndarray:
    c = c.astype(np.int64) + _OFF
    return (c[:, 0] << (2 * _BITS)) | (c[:, 1] << _BITS) | c[:, 2]


def _unpack(k: np.ndarray) -> np.ndarray:
    m = (1 << _BITS) - 1
    return np.stack([(k >> (2 * _BITS)) & m, (k >> _BITS) & m, k & m], axis=1) - _OFF


_POPCOUNT8 = np.array([bin(i).count("1") for i in range(256)], dtype=np.int64)


def _popcount(words: np.ndarray) -> np.ndarray:
    """Set bits per row of non-negative int64 words [M, W]."""
    total = np.zeros(words.shape[0], dtype=np.int64)
    for w in range(words.shape[1]):
        x = words[:, w]
        for b in range(8):
            total += _POPCOUNT8[(x >> (8 * b)) & 255]
    return total


def triangulate(centers: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """The point nearest to rays ``centers + s · dirs`` [N, 3] in the least-squares sense,
    each ray weighted by 1 / |dir|² (so distances count roughly in pixels at one depth)."""
    a = np.zeros((3, 3))
    b = np.zeros(3)
    for c, d in zip(centers, dirs):
        u = d / np.linalg.norm(d)
        p = np.eye(3) - np.outer(u, u)
        a += p
        b += p @ c
    return np.linalg.lstsq(a, b, rcond=None)[0]


# -- the multi-view step -------------------------------------------------------------------


def _vote(cams: list[_Cam], evidence: Sequence[ViewEvidence], voxel: float, max_depth: float, slack: float, min_strength: float):
    """Voxel keys [M] and view bit masks [M, W] of every voxel the ray of a candidate of
    at least ``min_strength`` passes."""
    n_words = (len(cams) + _WORD_BITS - 1) // _WORD_BITS
    keys_all, masks_all = [], []
    for vi, (cam, ev) in enumerate(zip(cams, evidence)):
        seeds = np.nonzero(ev.strength >= min_strength)[0]
        if not len(seeds):
            continue
        uv = ev.uv[seeds]
        dirs = cam.rays(uv)  # [K, 3], parameter = depth
        far = np.minimum(ev.depth_at(uv) * slack, max_depth)
        far = np.where(np.isfinite(far), far, max_depth)
        step = voxel / np.linalg.norm(dirs, axis=1)  # depth step of one voxel along each ray
        n_steps = np.ceil(far / step).astype(np.int64)
        ray_id = np.repeat(np.arange(len(seeds)), n_steps)
        k = np.arange(int(n_steps.sum())) - np.repeat(np.cumsum(n_steps) - n_steps, n_steps)
        s = (k + 0.5) * step[ray_id]
        pts = cam.center[None] + s[:, None] * dirs[ray_id]
        coords = np.floor(pts / voxel).astype(np.int64)
        ok = np.all(np.abs(coords) < _OFF - 2, axis=1)
        keys = np.unique(_pack(coords[ok]))
        word = np.zeros((len(keys), n_words), dtype=np.int64)
        word[:, vi // _WORD_BITS] = 1 << (vi % _WORD_BITS)
        keys_all.append(keys)
        masks_all.append(word)
    if not keys_all:
        return np.zeros(0, np.int64), np.zeros((0, n_words), np.int64)
    keys = np.concatenate(keys_all)
    masks = np.concatenate(masks_all)
    # A (voxel, view) pair occurs once (unique per view), so summing the bits is OR-ing them.
    order = np.argsort(keys, kind="stable")
    keys, masks = keys[order], masks[order]
    starts = np.flatnonzero(np.r_[True, keys[1:] != keys[:-1]])
    return keys[starts], np.add.reduceat(masks, starts, axis=0)


def _neighbourhood_views(keys: np.ndarray, masks: np.ndarray, at: np.ndarray | None = None) -> np.ndarray:
    """Distinct views over the 3 × 3 × 3 neighbourhood of each voxel ``at`` (default:
    every voxel of ``keys``, sorted, with view masks ``masks``)."""
    at = keys if at is None else at
    coords = _unpack(at)
    union = np.zeros((len(at), masks.shape[1]), dtype=masks.dtype)
    for dx in (-1, 0, 1):
        for dy in (-1, 0, 1):
            for dz in (-1, 0, 1):
                nk = _pack(coords + np.array([dx, dy, dz]))
                idx = np.clip(np.searchsorted(keys, nk), 0, len(keys) - 1)
                found = keys[idx] == nk
                union[found] |= masks[idx[found]]
    return _popcount(union)


def propose(
    cameras: Sequence[CameraLike],
    evidence: Sequence[ViewEvidence],
    names: Sequence[str] | None = None,
    settings: ProposalSettings = ProposalSettings(),
    points: Any = None,
) -> ProposalSet:
    """Multi-view proposals from per-view residual evidence (cameras at the evidence's
    resolution, in the same order). ``points`` [P, 3] (array or tensor), the dataset's
    SfM points, reject the proposals that lie among them (``reconstructed``); without
    them that test is skipped. See the module docstring."""
    if len(cameras) != len(evidence):
        raise ValueError(f"{len(cameras)} cameras but {len(evidence)} evidence lists")
    names = list(names) if names is not None else [str(getattr(c, "name", i)) for i, c in enumerate(cameras)]
    cams = [_Cam.of(c) for c in cameras]
    sfm = None if points is None else np.asarray(_np(points), np.float64).reshape(-1, 3)
    counts = {names[i]: len(e) for i, e in enumerate(evidence)}
    empty = ProposalSet([], [], {}, counts, settings)
    if sum(counts.values()) == 0:
        return empty
    # Typical candidate depth: the render's depth at the candidates (the objects lie in
    # front of it), else the distance between the cameras.
    depths = np.concatenate([e.depth_at(e.uv) for e in evidence if len(e)])
    finite = depths[np.isfinite(depths)]
    centers = np.stack([c.center for c in cams])
    spread = float(np.linalg.norm(centers - centers.mean(axis=0), axis=1).max()) if len(cams) > 1 else 1.0
    typical = float(np.median(finite)) * 0.6 if finite.size else spread
    max_depth = float(np.percentile(finite, 99)) * settings.depth_slack if finite.size else 4.0 * spread
    max_depth = max(max_depth, 2.0 * spread)
    focal = float(np.median([c.K[0, 0] for c in cams]))
    voxel = settings.voxel_px * typical / focal
    keys, masks = _vote(cams, evidence, voxel, max_depth, settings.depth_slack, settings.detection_threshold)
    if settings.weak_votes and len(keys):
        # Every candidate's ray votes, but only the voxels that a seeding one reaches are
        # counted: weaker candidates support what a strong one proposes.
        all_keys, all_masks = _vote(cams, evidence, voxel, max_depth, settings.depth_slack, 0.0)
        nviews = _neighbourhood_views(all_keys, all_masks, at=keys)
    else:
        nviews = _neighbourhood_views(keys, masks) if len(keys) else np.zeros(0, np.int64)
    good = np.nonzero(nviews >= settings.min_views)[0]
    order = good[np.argsort(-nviews[good], kind="stable")][: settings.max_hypotheses]
    voxel_centers = (_unpack(keys[order]).astype(np.float64) + 0.5) * voxel

    pool = _Pool(cams, evidence, settings.depth_slack)
    used = pool.used
    explained = [np.zeros(len(e), dtype=bool) for e in evidence]
    done: list[np.ndarray] = []
    proposals: list[Proposal] = []
    rejected: list[Rejected] = []
    suppress = settings.suppress_voxels * voxel
    for x0 in voxel_centers:
        if done and np.min(np.linalg.norm(np.asarray(done) - x0, axis=1)) < suppress:
            continue
        done.append(x0)
        picks = pool.gather(x0, settings.gather_px)
        if len(picks) < 2 or not _seeded(evidence, picks, settings):
            continue
        x, picks, errs = _refine(cams, evidence, picks, settings.tolerance_px)
        obs = [Observation(names[v], tuple(evidence[v].uv[k]), float(evidence[v].strength[k]), float(e))
               for (v, k), e in zip(picks, errs)]
        if not _seeded(evidence, picks, settings):
            continue  # weaker candidates only support what a seeding one proposes
        if len(picks) < settings.min_views:
            if len(picks) >= 2 and len(rejected) < settings.max_rejected:
                rejected.append(Rejected(tuple(x), "few_views", obs, 0, 0))
            continue
        if any(p.box.contains(_t(x))[0] for p in proposals):
            for v, k in picks:  # the same object again (another of its blobs)
                used[v][k] = True
            continue
        ring_px = 2.0 * max(float(evidence[v].scale[k]) for v, k in picks) + 2.0
        rms = float(np.sqrt(np.mean(np.square(errs))))
        cov = _covariance(cams, x, picks, rms)
        direction = _colour_direction(evidence, picks)
        seeing, supporting, image_has, floating = _check(cams, evidence, used, x, cov, settings, ring_px, direction)
        n_see, n_sup = int(seeing.sum()), int((seeing & supporting).sum())
        frac = n_sup / max(n_see, 1)
        for v, k in picks:
            used[v][k] = True
        if int((supporting & floating).sum()) * 2 <= n_sup:
            # In most supporting views the point lies on the render's surface: a texture
            # detail the render has not fitted, not an object in front of the scene.
            if len(rejected) < settings.max_rejected:
                rejected.append(Rejected(tuple(x), "surface", obs, n_see, n_sup))
            continue
        if frac < settings.min_support_fraction:
            silent = seeing & ~supporting
            reason = "explained" if int((silent & image_has).sum()) >= int((silent & ~image_has).sum()) else "inconsistent"
            if reason == "explained":
                for v, k in picks:
                    explained[v][k] = True
            if len(rejected) < settings.max_rejected:
                rejected.append(Rejected(tuple(x), reason, obs, n_see, n_sup))
            continue
        box, radius = _box(cams, evidence, x, picks, cov)
        if sfm is not None and len(sfm) and float(np.min(np.linalg.norm(sfm - x, axis=1))) < settings.sfm_radii * radius:
            # Structure-from-motion triangulated points there: a detail of a surface it
            # reconstructed (a texture, the tip of a leaf), not an object that both it
            # and the render lost.
            if len(rejected) < settings.max_rejected:
                rejected.append(Rejected(tuple(x), "reconstructed", obs, n_see, n_sup))
            continue
        strength = float(np.median([o.strength for o in obs]))
        conf = confidence(frac, n_sup, strength, rms, settings)
        box = PromptBox(box.center, box.size, box.rotation_wxyz, conf)
        colour = tuple(float(c) for c in np.median([evidence[v].colour[k] for v, k in picks], axis=0))
        pixel = float(np.median([cams[v].project(x[None])[1][0] / cams[v].K[0, 0] for v, _ in picks]))
        proposals.append(Proposal(box, conf, tuple(float(v) for v in x), obs, n_see, n_sup, rms, radius, colour, pixel))
    proposals.sort(key=lambda p: -p.confidence)
    proposals = proposals[: settings.max_proposals]
    unmatched: dict[str, list[dict[str, Any]]] = {}
    for v, ev in enumerate(evidence):
        free = np.nonzero(~used[v] & ~explained[v] & (ev.strength >= settings.unmatched_strength))[0]
        free = free[np.argsort(-ev.strength[free])][: settings.max_unmatched_per_view]
        if len(free):
            unmatched[names[v]] = [{"uv": [round(float(a), 2) for a in ev.uv[k]], "strength": round(float(ev.strength[k]), 2)} for k in free]
    info = {"voxel": voxel, "n_voxels": int(len(keys)), "n_hypotheses": len(done)}
    return ProposalSet(proposals, rejected, unmatched, counts, settings, info)


def confidence(fraction: float, n_supporting: int, strength: float, rms_px: float, settings: ProposalSettings) -> float:
    """``f · (1 − exp(−(n − 2) / 6)) · min(1, s / t) · (1 − 0.5 · rms / tolerance)``:
    ``f`` the supporting fraction of the seeing views, ``n`` the supporting views, ``s``
    the consistent views' median residual strength, ``t`` the detection threshold. The
    view term is 0.49 for 6 supporting views, 0.74 for 10, 0.95 for 20: a few views that
    agree happen by chance on a textured scene, twenty rarely do."""
    views = 1.0 - math.exp(-(n_supporting - 2) / 6.0)
    blob = min(1.0, strength / settings.detection_threshold)
    fit = 1.0 - 0.5 * min(rms_px / settings.tolerance_px, 1.0)
    return float(min(max(fraction * views * blob * fit, 0.0), 1.0))


def _seeded(evidence, picks, settings: ProposalSettings) -> bool:
    """Whether a candidate of at least the detection threshold is among ``picks``."""
    return any(evidence[v].strength[k] >= settings.detection_threshold for v, k in picks)


class _Pool:
    """Every view's candidates in flat arrays, to find per view the one nearest to a
    point's projection in one pass. ``used`` holds a view of ``used_flat`` per view, so
    marking ``used[v][k]`` marks the pool."""

    def __init__(self, cams: list[_Cam], evidence: Sequence[ViewEvidence], slack: float):
        sizes = np.array([len(e) for e in evidence], dtype=np.int64)
        self.starts = np.r_[0, np.cumsum(sizes)]
        self.view = np.repeat(np.arange(len(evidence)), sizes)
        self.uv = np.concatenate([e.uv for e in evidence]).reshape(-1, 2)
        self.far = np.concatenate([e.depth_at(e.uv) * slack for e in evidence]) if len(self.uv) else np.zeros(0)
        self.used_flat = np.zeros(len(self.uv), dtype=bool)
        self.used = [self.used_flat[a:b] for a, b in zip(self.starts[:-1], self.starts[1:])]
        self.R = np.stack([c.R for c in cams])
        self.t = np.stack([c.t for c in cams])
        self.K = np.stack([c.K for c in cams])

    def gather(self, x: np.ndarray, gather_px: float) -> list[tuple[int, int]]:
        """(view, candidate) pairs: per view the nearest unused candidate within
        ``gather_px`` of x's projection that lies in front of the render's depth there
        (with its slack)."""
        p = self.R @ x + self.t  # [V, 3]
        z = p[:, 2]
        q = np.einsum("vij,vj->vi", self.K, p)
        proj = q[:, :2] / np.where(z > 0, z, 1.0)[:, None]
        d = np.linalg.norm(self.uv - proj[self.view], axis=1)
        d[self.used_flat | (z[self.view] <= 0)] = np.inf
        picks = []
        for v in np.unique(self.view):
            a, b = self.starts[v], self.starts[v + 1]
            k = int(np.argmin(d[a:b]))
            if d[a + k] <= gather_px and self.far[a + k] >= z[v]:
                picks.append((int(v), k))
        return picks


def _refine(cams, evidence, picks, tolerance_px):
    """Triangulate, then drop the worst view while its reprojection error exceeds the
    tolerance. Returns (point, kept picks, their errors in px)."""
    picks = list(picks)
    while True:
        c = np.stack([cams[v].center for v, _ in picks])
        d = np.stack([cams[v].rays(evidence[v].uv[k : k + 1])[0] for v, k in picks])
        x = triangulate(c, d)
        errs = []
        for v, k in picks:
            uv, z = cams[v].project(x[None])
            errs.append(float(np.linalg.norm(uv[0] - evidence[v].uv[k])) if z[0] > 0 else np.inf)
        worst = int(np.argmax(errs))
        if errs[worst] <= tolerance_px or len(picks) <= 2:
            return x, picks, errs
        picks.pop(worst)


_RING = np.array([[np.cos(a), np.sin(a)] for a in np.arange(8) * np.pi / 4])


def _colour_direction(evidence, picks) -> np.ndarray | None:
    """The unit mean colour direction of the residual at the picked candidates (None if
    they disagree completely)."""
    acc = np.zeros(3)
    for v, k in picks:
        acc += evidence[v].residual_direction(k)
    n = np.linalg.norm(acc)
    return acc / n if n > 1e-9 else None


def _check(cams, evidence, used, x, cov, settings: ProposalSettings, radius_px: float = 4.0, direction=None):
    """Per view: sees x (in the image, not hidden), supports it (a free candidate there,
    or the residual along the object's colour ``direction``, see the module docstring),
    the image has a blob there, and x floats (the render's surface there lies clearly
    behind it: by ``min_clearance`` of its depth and by three standard deviations of the
    triangulated depth along the view's axis, ``cov`` being the point's covariance)."""
    n = len(cams)
    seeing = np.zeros(n, bool)
    supporting = np.zeros(n, bool)
    image_has = np.zeros(n, bool)
    floating = np.zeros(n, bool)
    for v, (cam, ev) in enumerate(zip(cams, evidence)):
        uv, z = cam.project(x[None])
        if z[0] <= 0 or not (0 <= uv[0, 0] < cam.width and 0 <= uv[0, 1] < cam.height):
            continue
        surface = ev.depth_at(uv)[0]
        if surface < (1.0 - settings.occlusion_margin) * z[0]:
            continue  # hidden behind the render's surface
        seeing[v] = True
        # Floating: the render's surface lies clearly behind the point around it (at
        # least 6 of 8 points on a ring just outside the object), not only at its pixel:
        # a point on a silhouette (a ridge against the sky) has the ridge on one side,
        # a spot on the ground has the ground beside it; a neighbouring object or a
        # smear the render drew for this one covers only part of the ring.
        ring = uv + _RING * radius_px
        sigma_z = float(np.sqrt(max(cam.R[2] @ cov @ cam.R[2], 0.0)))
        behind = ev.depth_at(ring) > z[0] + max(settings.min_clearance * z[0], 3.0 * sigma_z)
        floating[v] = int(behind.sum()) >= 6
        free = ~used[v]
        supporting[v] = bool(free.any()) and float(np.min(np.linalg.norm(ev.uv[free] - uv, axis=1))) <= settings.support_px
        if not supporting[v] and direction is not None and settings.matched_strength > 0:
            supporting[v] = ev.response_along(uv, direction, settings.min_contrast)[0] >= settings.matched_strength
        image_has[v] = ev.image_blob_at(uv, 1)[0] >= 0.03
    return seeing, supporting, image_has, floating


def _covariance(cams, x, picks, rms) -> np.ndarray:
    """[3, 3] covariance of a triangulated point: ``σ² (Σ JᵀJ)⁻¹`` over its views, with
    ``σ`` the reprojection RMS (at least 0.5 px)."""
    jtj = np.zeros((3, 3))
    for v, _ in picks:
        j = cams[v].jacobian(x)
        jtj += j.T @ j
    return max(rms, 0.5) ** 2 * np.linalg.pinv(jtj)


def _box(cams, evidence, x, picks, cov) -> tuple[PromptBox, float]:
    """The oriented box of a triangulated point (module docstring, step 5) and the object radius."""
    radius = 0.0
    for v, k in picks:
        z = float(cams[v].project(x[None])[1][0])
        px = 2.0 * float(evidence[v].scale[k]) + 2.0
        radius = max(radius, px * z / float(cams[v].K[0, 0]))
    vals, vecs = np.linalg.eigh(cov)
    half = np.clip(3.0 * np.sqrt(np.maximum(vals, 0.0)), radius, 8.0 * radius)
    if np.linalg.det(vecs) < 0:
        vecs[:, 0] = -vecs[:, 0]
    m = np.eye(4)
    m[:3, :3] = vecs * (2.0 * half)[None, :]
    m[:3, 3] = x
    return PromptBox.from_matrix(m, base_edge=1.0), radius
