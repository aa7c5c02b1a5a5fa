"""Which training views matter for a region, and the multiview batch schedule.

Relevance of camera ``i`` to a box (a prompt or an error-field peak), from its
projection (``prompts.project_box``); cameras that show none of the box score 0::

    r_i = (w_a · a_i/max_j a_j + w_f · f_i + w_d · d_min/d_i + w_c · max(cos θ_i, 0)
           [+ w_s · s_i]) / (w_a + w_f + w_d + w_c [+ w_s])

``a`` visible silhouette area in pixels, ``f`` fraction of the silhouette inside the
image, ``d`` distance from the camera centre to the box centre (``d_min`` over the
cameras that see the box), ``θ`` angle between the optical axis and the direction to the
box centre. ``s`` (only when images are given) is the image-space similarity of the
region: the box's pixel bounding box is cropped from each view, pooled to 8×8 RGB,
centred, and compared by cosine similarity with the crop of the best-ranked view by
geometry; ``s = (1 + cos) / 2``.

Schedule: a cycle of ``random multiview : single : related multiview : single`` steps in
the ratio 2:3:2:3 (configurable). Single-view steps walk a fresh seeded permutation of
all training cameras per epoch (as 3DGS does); random multiview steps walk their own
seeded permutations in chunks of ``max_views_per_step``, so both cover every camera over
time; related multiview steps take the top-K views of one region, rotating over regions
and, when a region has more than ``max_views_per_step`` views (or its own, smaller cap:
`ViewSchedule.set_regions`), rotating a window over its views. Without regions, related
steps fall back to random multiview batches. The batch of
a step is a pure function of (seed, step, regions, cap), so resuming is exact.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Callable, Sequence

import numpy as np
import torch
import torch.nn.functional as F

from .data import Camera
from .prompts import BoxProjection, CameraLike, PromptBox, project_box

__all__ = [
    "RelevanceWeights",
    "ViewRelevance",
    "rank_views",
    "top_k_views",
    "related_views",
    "views_cap_from_memory",
    "ViewBatch",
    "ViewSchedule",
    "RANDOM_MULTIVIEW",
    "SINGLE",
    "RELATED_MULTIVIEW",
    "DEFAULT_RATIO",
    "entries_with_related_steps",
    "TrainView",
]

RANDOM_MULTIVIEW = "random_multiview"
SINGLE = "single"
RELATED_MULTIVIEW = "related_multiview"
DEFAULT_RATIO = (2, 3, 2, 3)  # random multiview, single, related multiview, single


def entries_with_related_steps(whole_view_entries: int, ratio: tuple[int, int, int, int] = DEFAULT_RATIO) -> int:
    """Schedule entries that hold ``whole_view_entries`` entries of whole views when the
    related steps of ``ratio`` come on top of them: ``⌈n · cycle / (cycle − related)⌉``
    (1500 → 1875 at 2:3:2:3)."""
    cycle, related = sum(ratio), ratio[2]
    if related >= cycle:
        raise ValueError(f"ratio {ratio} has no whole-view steps")
    return -(-int(whole_view_entries) * cycle // (cycle - related))


@dataclass(frozen=True)
class RelevanceWeights:
    area: float = 0.4
    in_image: float = 0.2
    distance: float = 0.2
    angle: float = 0.2
    similarity: float = 0.2  # used only when images are given


@dataclass
class ViewRelevance:
    index: int  # camera index in the list given
    score: float  # r_i in [0, 1]
    projection: BoxProjection
    similarity: float | None = None


def _crop_descriptor(image: torch.Tensor, bbox: tuple[int, int, int, int]) -> torch.Tensor | None:
    h, w = image.shape[:2]
    i0, j0, i1, j1 = max(bbox[0], 0), max(bbox[1], 0), min(bbox[2], w), min(bbox[3], h)
    if i1 <= i0 or j1 <= j0:
        return None
    crop = image[j0:j1, i0:i1].float()
    if crop.dim() == 2:
        crop = crop[..., None]
    d = F.adaptive_avg_pool2d(crop.permute(2, 0, 1)[None], 8)[0].reshape(-1)
    return d - d.mean()


def rank_views(
    box: PromptBox,
    cameras: Sequence[CameraLike],
    weights: RelevanceWeights = RelevanceWeights(),
    min_pixels: float = 0.0,
    load_image: Callable[[int], torch.Tensor] | None = None,
) -> list[ViewRelevance]:
    """The cameras that show more than ``min_pixels`` of ``box``, most relevant first (see
    the module docstring for the score). ``load_image(i)`` -> [H, W, 3] (at the camera's
    size) enables the image-space similarity term."""
    projs = [project_box(box, cam) for cam in cameras]
    seen = [i for i, p in enumerate(projs) if p.in_front and p.visible_area > min_pixels]
    if not seen:
        return []
    a = np.array([projs[i].visible_area for i in seen])
    f = np.array([projs[i].in_image_fraction for i in seen])
    d = np.array([max(projs[i].distance, 1e-12) for i in seen])
    c = np.array([max(projs[i].view_cos, 0.0) for i in seen])
    num = weights.area * a / a.max() + weights.in_image * f + weights.distance * d.min() / d + weights.angle * c
    den = weights.area + weights.in_image + weights.distance + weights.angle
    sims: list[float | None] = [None] * len(seen)
    if load_image is not None and weights.similarity > 0:
        ref = seen[int(np.argmax(num))]
        ref_desc = _crop_descriptor(load_image(ref), projs[ref].pixel_bbox())  # type: ignore[arg-type]
        s = np.zeros(len(seen))
        for n, i in enumerate(seen):
            desc = _crop_descriptor(load_image(i), projs[i].pixel_bbox())  # type: ignore[arg-type]
            if ref_desc is not None and desc is not None:
                cos = float(F.cosine_similarity(ref_desc, desc, dim=0, eps=1e-8))
                s[n] = (1.0 + cos) / 2.0
            sims[n] = float(s[n])
        num = num + weights.similarity * s
        den += weights.similarity
    score = np.clip(num / den, 0.0, 1.0)
    out = [ViewRelevance(i, float(score[n]), projs[i], sims[n]) for n, i in enumerate(seen)]
    out.sort(key=lambda v: (-v.score, v.index))
    return out


def top_k_views(box: PromptBox, cameras: Sequence[CameraLike], k: int, **kwargs) -> list[int]:
    """Indices of the (at most) ``k`` most relevant cameras for ``box``; fewer when fewer
    cameras see it. Keyword arguments go to :func:`rank_views`."""
    return [v.index for v in rank_views(box, cameras, **kwargs)[: max(k, 0)]]


def related_views(boxes: Sequence[PromptBox], cameras: Sequence[CameraLike], k: int, **kwargs) -> list[list[int]]:
    """``top_k_views`` for each box: the regions argument of :class:`ViewSchedule`."""
    return [top_k_views(b, cameras, k, **kwargs) for b in boxes]


def views_cap_from_memory(
    bytes_per_view: float,
    available_bytes: float,
    reserve_fraction: float = 0.1,
    max_views: int | None = None,
) -> int:
    """How many views one step may hold: ``floor(available · (1 − reserve) / per_view)``,
    at least 1, at most ``max_views`` when given."""
    if bytes_per_view <= 0:
        raise ValueError(f"bytes_per_view must be positive, got {bytes_per_view}")
    cap = int(math.floor(max(available_bytes, 0.0) * (1.0 - reserve_fraction) / bytes_per_view))
    cap = max(cap, 1)
    return min(cap, max_views) if max_views is not None else cap


@dataclass(frozen=True)
class ViewBatch:
    step: int
    kind: str  # RANDOM_MULTIVIEW | SINGLE | RELATED_MULTIVIEW (the kind actually used)
    views: list[int]  # training-camera indices, distinct
    region: int | None = None  # index into the regions for related batches


class ViewSchedule:
    """Deterministic per-step view batches (see the module docstring).

    ``ratio`` = (random multiview, single, related multiview, single) steps per cycle;
    ``regions`` = one list of camera indices (e.g. ``top_k_views``) per prompt / error
    region."""

    def __init__(
        self,
        n_cameras: int,
        max_views_per_step: int = 4,
        seed: int = 0,
        regions: Sequence[Sequence[int]] | None = None,
        ratio: tuple[int, int, int, int] = DEFAULT_RATIO,
    ) -> None:
        if n_cameras < 1:
            raise ValueError("ViewSchedule needs at least one camera")
        if len(ratio) != 4 or min(ratio) < 0 or sum(ratio) == 0:
            raise ValueError(f"ratio must be 4 non-negative counts, not all zero: {ratio}")
        self.n = int(n_cameras)
        self.seed = int(seed)
        self.ratio = tuple(int(r) for r in ratio)
        self.cap = 1
        self.set_max_views(max_views_per_step)
        kinds = [RANDOM_MULTIVIEW] * ratio[0] + [SINGLE] * ratio[1] + [RELATED_MULTIVIEW] * ratio[2] + [SINGLE] * ratio[3]
        self._slots = kinds
        seen: dict[str, int] = {}
        self._slot_ordinal = []
        for k in kinds:
            self._slot_ordinal.append(seen.get(k, 0))
            seen[k] = seen.get(k, 0) + 1
        self._per_cycle = seen
        self._perm_cache: dict[tuple[int, int], np.ndarray] = {}
        self.regions: list[list[int]] = []
        self.set_regions(regions or [])

    def set_max_views(self, cap: int) -> None:
        """Views per multiview step (e.g. from :func:`views_cap_from_memory`)."""
        if cap < 1:
            raise ValueError(f"max_views_per_step must be >= 1, got {cap}")
        self.cap = int(cap)

    def set_regions(self, regions: Sequence[Sequence[int]], views_per_step: Sequence[int | None] | None = None) -> None:
        """Replace the related-view lists (one per prompt; a batch's ``region`` is the
        index in this list). Empty lists get no related steps; duplicates are dropped.
        ``views_per_step`` (one per region, None for the schedule's cap) caps the views of
        that region's related steps below ``max_views_per_step``; its window then moves
        by that many views a visit."""
        out = []
        for r in regions:
            lst = list(dict.fromkeys(int(i) for i in r))
            if any(i < 0 or i >= self.n for i in lst):
                raise ValueError(f"region view index out of range 0..{self.n - 1}: {lst}")
            out.append(lst)
        caps = list(views_per_step) if views_per_step is not None else [None] * len(out)
        if len(caps) != len(out):
            raise ValueError(f"views_per_step has {len(caps)} entries for {len(out)} regions")
        if any(c is not None and c < 1 for c in caps):
            raise ValueError(f"views_per_step must be >= 1 or None: {caps}")
        self.regions = out
        self.region_caps = [None if c is None else int(c) for c in caps]
        self._usable = [i for i, lst in enumerate(out) if lst]

    @property
    def cycle_length(self) -> int:
        return len(self._slots)

    def _perm(self, tag: int, epoch: int) -> np.ndarray:
        key = (tag, epoch)
        if key not in self._perm_cache:
            if len(self._perm_cache) > 16:
                self._perm_cache.clear()
            self._perm_cache[key] = np.random.default_rng([self.seed, tag, epoch]).permutation(self.n)
        return self._perm_cache[key]

    def _ordinal(self, step: int) -> tuple[str, int]:
        c, r = divmod(step, self.cycle_length)
        kind = self._slots[r]
        return kind, c * self._per_cycle[kind] + self._slot_ordinal[r]

    def _walk(self, tag: int, ordinal: int) -> list[int]:
        m = min(self.cap, self.n)
        per_epoch = -(-self.n // m)
        epoch, b = divmod(ordinal, per_epoch)
        return [int(i) for i in self._perm(tag, epoch)[b * m : (b + 1) * m]]

    def batch(self, step: int) -> ViewBatch:
        """The views to train on at ``step`` (0-based)."""
        if step < 0:
            raise ValueError(f"step must be >= 0, got {step}")
        kind, o = self._ordinal(step)
        if kind == SINGLE:
            epoch, pos = divmod(o, self.n)
            return ViewBatch(step, SINGLE, [int(self._perm(0, epoch)[pos])])
        if kind == RANDOM_MULTIVIEW:
            return ViewBatch(step, RANDOM_MULTIVIEW, self._walk(1, o))
        if not self._usable:  # related step without regions
            return ViewBatch(step, RANDOM_MULTIVIEW, self._walk(2, o))
        visit, k = divmod(o, len(self._usable))
        region = self._usable[k]
        views = self.regions[region]
        m = min(self.cap, self.region_caps[region] or self.cap, len(views))
        start = (visit * m) % len(views)
        return ViewBatch(step, RELATED_MULTIVIEW, [views[(start + i) % len(views)] for i in range(m)], region)

    def __iter__(self):
        step = 0
        while True:
            yield self.batch(step)
            step += 1


@dataclass
class TrainView:
    """A camera a training step renders (possibly a crop of a training view) and its
    ground-truth image."""

    camera: Camera
    gt: torch.Tensor  # [H, W, 3]
    source: int  # index of the training camera
    crop: bool = False  # a crop around a prompt (related-view step), not the whole image
    statistics: bool = False  # a statistics step: the only kind that votes for growth outside the prompts
    screen_filter: float | None = None  # px²; None: the run's (full-size renders)
    window: tuple[int, int, int, int] | None = None  # a crop's (x0, y0, width, height) in the source view
