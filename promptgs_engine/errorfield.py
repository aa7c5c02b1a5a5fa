"""The 3D error field: per-pixel training loss back-projected into world space and
accumulated in a sparse voxel grid.

Storage: a sorted array of packed integer voxel keys (21 bits per axis) with, per voxel,
``S`` = decayed sum of the loss of the pixels that landed there and ``H`` = decayed count
of those pixels. Look-ups are binary searches, inserts a sort-merge: all vectorised.

Formulas (also in docs/promptgs.md):

* back-projection: pixel column ``i``, row ``j`` has its centre at ``(u, v) = (i + 0.5,
  j + 0.5)`` (the rasterizer's convention, see ``prompts``); with the rendered expected
  z-depth ``z`` (gsplat "ED": camera-space z, already divided by alpha) the camera point
  is ``z · K⁻¹ [u, v, 1]ᵀ`` and the world point ``Rᵀ (X_cam − t)`` for
  ``world_to_camera = [R | t]``. Pixels with alpha below ``min_alpha`` (background) or a
  non-positive depth are skipped.
* decay: before adding at training step ``s``, ``S`` and ``H`` are multiplied by
  ``0.5 ** ((s − s_last) / half_life)``, so the field follows training.
* voxel error: ``E(v) = S(v) / (H(v) + prior_hits)`` — the mean pixel loss of the voxel,
  shrunk towards 0 where few pixels landed (one stray pixel is not a hot spot).
* normalised error: ``Ê = min(E / E_ref, 1)`` with ``E_ref`` the 99th percentile of
  ``E`` over the field's voxels.
* attention: ``A(x) = Ê(x) · (1 + w(x))`` with ``w(x)`` the largest weight of the prompt
  boxes containing ``x`` (0 outside all prompts).
* peaks (self-diagnosis): ``E`` smoothed over each voxel's 3×3×3 neighbourhood
  (``ΣS / (ΣH + prior_hits)``), greedy non-maximum suppression with ``min_separation``;
  each peak's region is the voxels within ``min_separation / 2`` whose smoothed error is
  at least ``rel_threshold`` × the peak's, boxed axis-aligned with one voxel of padding.
"""

from __future__ import annotations

from typing import Any, Sequence

import numpy as np
import torch

from .prompts import CameraLike, PromptBox, max_weight

__all__ = ["ErrorField", "backproject"]

_BITS = 21
_OFF = 1 << (_BITS - 1)  # voxel coordinates in [-OFF, OFF) are representable
_MASK = (1 << _BITS) - 1
_NEIGHBOURS = torch.tensor([[dx, dy, dz] for dx in (-1, 0, 1) for dy in (-1, 0, 1) for dz in (-1, 0, 1)])


def _pack(coords: torch.Tensor) -> torch.Tensor:
    c = coords.long() + _OFF
    return (c[:, 0] << (2 * _BITS)) | (c[:, 1] << _BITS) | c[:, 2]


def _unpack(keys: torch.Tensor) -> torch.Tensor:
    return torch.stack([(keys >> (2 * _BITS)) & _MASK, (keys >> _BITS) & _MASK, keys & _MASK], dim=1) - _OFF


def _as_tensor(t: Any) -> torch.Tensor:
    if isinstance(t, torch.Tensor):
        return t.detach().cpu().double()
    return torch.as_tensor(np.asarray(t), dtype=torch.float64)


def _hw(t: torch.Tensor, name: str) -> torch.Tensor:
    if t.dim() == 3 and t.shape[-1] == 1:
        t = t[..., 0]
    elif t.dim() == 3 and name == "loss_map":
        t = t.mean(dim=-1)
    if t.dim() != 2:
        raise ValueError(f"{name} must be [H, W] (or [H, W, 1]), got shape {tuple(t.shape)}")
    return t


def backproject(
    loss_map: torch.Tensor,
    depth: torch.Tensor,
    mask: torch.Tensor | None,
    camera: CameraLike,
    top_q: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """World points [P, 3] and their losses [P] (float64, CPU) for the pixels where
    ``mask`` is true and ``depth > 0``; with ``top_q`` in (0, 1] only the highest-loss
    fraction of those pixels. ``loss_map``/``depth``/``mask`` are [H, W] (or [H, W, 1];
    a [H, W, C] loss is averaged over C). When H × W differs from the camera's size the
    intrinsics are rescaled to the map (a downscaled render)."""
    loss = _hw(_as_tensor(loss_map), "loss_map")
    z = _hw(_as_tensor(depth), "depth")
    h, w = loss.shape
    if z.shape != loss.shape:
        raise ValueError(f"depth shape {tuple(z.shape)} differs from loss_map shape {tuple(loss.shape)}")
    valid = torch.isfinite(z) & (z > 0) & torch.isfinite(loss)
    if mask is not None:
        m = mask.detach().cpu() if isinstance(mask, torch.Tensor) else torch.as_tensor(np.asarray(mask))
        m = _hw(m, "mask")
        valid &= m.bool() if m.dtype == torch.bool else m > 0
    jj, ii = torch.nonzero(valid, as_tuple=True)  # rows, columns
    vals = loss[jj, ii]
    if top_q is not None and 0 < top_q < 1 and vals.numel() > 0:
        k = max(1, int(np.ceil(top_q * vals.numel())))
        sel = torch.topk(vals, k, sorted=False).indices
        jj, ii, vals = jj[sel], ii[sel], vals[sel]
    k_mat = _as_tensor(camera.K).clone()
    if (w, h) != (int(camera.width), int(camera.height)):
        k_mat[0] *= w / float(camera.width)
        k_mat[1] *= h / float(camera.height)
    zz = z[jj, ii]
    pix = torch.stack([ii.double() + 0.5, jj.double() + 0.5, torch.ones_like(zz)], dim=1)  # [P, 3]
    cam = (pix @ torch.linalg.inv(k_mat).T) * zz[:, None]
    w2c = _as_tensor(camera.world_to_camera)
    world = (cam - w2c[:3, 3]) @ w2c[:3, :3]  # R^T (X - t), row-vector form
    return world, vals


class ErrorField:
    """Sparse voxel field of accumulated training loss (see the module docstring)."""

    def __init__(
        self,
        voxel_size: float,
        half_life: float = 1000.0,
        prior_hits: float = 1.0,
        min_alpha: float = 0.5,
        prune_below: float = 1e-3,
    ) -> None:
        if not voxel_size > 0:
            raise ValueError(f"voxel_size must be positive, got {voxel_size}")
        self.voxel_size = float(voxel_size)
        self.half_life = float(half_life)
        self.prior_hits = float(prior_hits)
        self.min_alpha = float(min_alpha)
        self.prune_below = float(prune_below)
        self.step = 0
        self.keys = torch.zeros(0, dtype=torch.long)  # sorted, unique
        self.loss_sum = torch.zeros(0, dtype=torch.float64)
        self.hits = torch.zeros(0, dtype=torch.float64)

    @classmethod
    def from_extent(cls, extent: float, resolution: int = 128, **kwargs: Any) -> "ErrorField":
        """Voxel size ``2 · extent / resolution`` (``extent``: the scene radius, e.g.
        ``Scene.extent``), i.e. ``resolution`` voxels across the camera sphere."""
        return cls(2.0 * float(extent) / resolution, **kwargs)

    def __len__(self) -> int:
        return int(self.keys.numel())

    # -- accumulation ---------------------------------------------------------------------
    def _decay_to(self, step: int | None) -> None:
        s = self.step + 1 if step is None else int(step)
        if s > self.step and len(self) and self.half_life > 0:
            f = 0.5 ** ((s - self.step) / self.half_life)
            self.loss_sum *= f
            self.hits *= f
            keep = self.hits >= self.prune_below
            if not bool(keep.all()):
                self.keys, self.loss_sum, self.hits = self.keys[keep], self.loss_sum[keep], self.hits[keep]
        self.step = max(self.step, s)

    def voxel_coords(self, points: torch.Tensor) -> torch.Tensor:
        """long [N, 3] integer voxel coordinates (voxel v spans [v, v+1) · voxel_size)."""
        return torch.floor(_as_tensor(points) / self.voxel_size).long()

    def voxel_centers(self) -> torch.Tensor:
        """float64 [M, 3] world centres of the stored voxels (in key order)."""
        return (_unpack(self.keys).double() + 0.5) * self.voxel_size

    def add_points(self, points: torch.Tensor, losses: torch.Tensor, step: int | None = None) -> int:
        """Add world points [P, 3] with losses [P] at training ``step`` (None: one step after
        the last). Returns the number of points added (points outside the representable
        range, |coordinate| ≥ 2^20 voxels, are dropped)."""
        self._decay_to(step)
        pts = _as_tensor(points).reshape(-1, 3)
        vals = _as_tensor(losses).reshape(-1)
        coords = self.voxel_coords(pts)
        ok = (coords.abs() < _OFF - 1).all(dim=1) & torch.isfinite(pts).all(dim=1) & torch.isfinite(vals)
        coords, vals = coords[ok], vals[ok]
        if vals.numel() == 0:
            return 0
        new_keys, inv = torch.unique(_pack(coords), return_inverse=True)
        new_s = torch.zeros(new_keys.numel(), dtype=torch.float64).index_add_(0, inv, vals)
        new_h = torch.zeros(new_keys.numel(), dtype=torch.float64).index_add_(0, inv, torch.ones_like(vals))
        # Voxels already stored add to their sums; the others are inserted in key order.
        idx, found = self._lookup(new_keys)
        self.loss_sum[idx[found]] += new_s[found]
        self.hits[idx[found]] += new_h[found]
        fresh = ~found
        if bool(fresh.any()):
            # Both key lists are sorted: a new key's place in the merged list is its index
            # plus the number of stored keys below it, and the stored keys fill the other
            # places in their order.
            add_keys = new_keys[fresh]
            m, a = len(self), add_keys.numel()
            add_at = torch.arange(a) + torch.searchsorted(self.keys, add_keys)
            stored_at = torch.ones(m + a, dtype=torch.bool)
            stored_at[add_at] = False
            keys = torch.empty(m + a, dtype=torch.long)
            loss_sum = torch.empty(m + a, dtype=torch.float64)
            hits = torch.empty(m + a, dtype=torch.float64)
            for out, old, add in ((keys, self.keys, add_keys), (loss_sum, self.loss_sum, new_s[fresh]), (hits, self.hits, new_h[fresh])):
                out.masked_scatter_(stored_at, old)
                out[add_at] = add
            self.keys, self.loss_sum, self.hits = keys, loss_sum, hits
        return int(vals.numel())

    def accumulate(
        self,
        loss_map: torch.Tensor,
        depth: torch.Tensor,
        alpha: torch.Tensor | None,
        camera: CameraLike,
        step: int | None = None,
        top_q: float | None = None,
    ) -> int:
        """Back-project one view's per-pixel loss [H, W] with its rendered expected depth
        [H, W] and add it. ``alpha`` is the rendered alpha [H, W] (pixels below
        ``min_alpha`` are skipped) or a bool mask, or None (all pixels). Call once per view
        with the training step; several views of one step share the same ``step``."""
        pts, vals = self.view_points(loss_map, depth, alpha, camera, top_q)
        return self.add_points(pts, vals, step)

    def view_points(
        self,
        loss_map: torch.Tensor,
        depth: torch.Tensor,
        alpha: torch.Tensor | None,
        camera: CameraLike,
        top_q: float | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The world points and losses `accumulate` would add for one view (arguments as
        there), without adding them."""
        mask = None
        if alpha is not None:
            a = alpha.detach().cpu() if isinstance(alpha, torch.Tensor) else torch.as_tensor(np.asarray(alpha))
            mask = a if a.dtype == torch.bool else a.double() >= self.min_alpha
        return backproject(loss_map, depth, mask, camera, top_q)

    # -- queries --------------------------------------------------------------------------
    def _lookup(self, keys: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(index into the stored arrays, found) for packed keys."""
        if len(self) == 0:
            z = torch.zeros(keys.shape, dtype=torch.long)
            return z, torch.zeros(keys.shape, dtype=torch.bool)
        idx = torch.searchsorted(self.keys, keys).clamp(max=len(self) - 1)
        return idx, self.keys[idx] == keys

    def voxel_error(self) -> torch.Tensor:
        """float64 [M]: E = S / (H + prior_hits) per stored voxel."""
        return self.loss_sum / (self.hits + self.prior_hits)

    def reference_error(self) -> float:
        """E_ref, the 99th percentile of the voxel errors (0 for an empty field)."""
        if len(self) == 0:
            return 0.0
        e = self.voxel_error()
        return float(torch.quantile(e, 0.99)) if e.numel() <= 1 << 24 else float(e.max())

    def loss_at(self, points: torch.Tensor) -> torch.Tensor:
        """float32 [N]: the voxel error E at each point (0 where nothing was accumulated)."""
        pts = _as_tensor(points).reshape(-1, 3)
        coords = self.voxel_coords(pts)
        inrange = (coords.abs() < _OFF - 1).all(dim=1)
        idx, found = self._lookup(_pack(coords.clamp(-_OFF + 1, _OFF - 2)))
        found &= inrange
        e = self.voxel_error()
        out = torch.where(found, e[idx] if len(self) else torch.zeros_like(idx, dtype=torch.float64), 0.0)
        return out.float().to(points.device if isinstance(points, torch.Tensor) else "cpu")

    def normalized(self, points: torch.Tensor) -> torch.Tensor:
        """float32 [N]: Ê = min(E / E_ref, 1) in [0, 1]."""
        ref = self.reference_error()
        e = self.loss_at(points)
        return (e / ref).clamp(max=1.0) if ref > 0 else torch.zeros_like(e)

    def attention(self, points: torch.Tensor, prompts: Sequence[PromptBox] = ()) -> torch.Tensor:
        """float32 [N]: A = Ê · (1 + w), w the largest weight of the prompts containing the
        point (0 outside all of them)."""
        a = self.normalized(points)
        if prompts:
            a = a * (1.0 + max_weight(prompts, points.float()).to(a.device))
        return a

    def _smoothed_error(self) -> torch.Tensor:
        """float64 [M]: ΣS / (ΣH + prior_hits) over each voxel's 3×3×3 neighbourhood."""
        coords = _unpack(self.keys)
        s = torch.zeros(len(self), dtype=torch.float64)
        h = torch.zeros(len(self), dtype=torch.float64)
        for off in _NEIGHBOURS:  # 27 vectorised look-ups
            idx, found = self._lookup(_pack(coords + off))
            s += torch.where(found, self.loss_sum[idx], 0.0)
            h += torch.where(found, self.hits[idx], 0.0)
        return s / (h + self.prior_hits)

    def peaks(
        self,
        n: int,
        min_separation: float | None = None,
        rel_threshold: float = 0.5,
        max_candidates: int = 16384,
    ) -> list[PromptBox]:
        """Up to ``n`` high-error regions as proposed prompt boxes (axis-aligned), strongest
        first, centres at least ``min_separation`` apart (default 8 voxels). Each box's
        weight is its peak's smoothed error relative to the strongest peak, in (0, 1]."""
        if n <= 0 or len(self) == 0:
            return []
        sep = 8 * self.voxel_size if min_separation is None else float(min_separation)
        err = self._smoothed_error()
        centers = self.voxel_centers()
        order = torch.argsort(err, descending=True)[:max_candidates]
        cand_c, cand_e = centers[order], err[order]
        alive = cand_e > 0
        boxes: list[PromptBox] = []
        top = None
        while len(boxes) < n and bool(alive.any()):
            k = int(torch.nonzero(alive)[0])  # candidates are sorted: first alive is the max
            peak_c, peak_e = cand_c[k], float(cand_e[k])
            top = peak_e if top is None else top
            alive &= (cand_c - peak_c).norm(dim=1) >= sep
            alive[k] = False
            member = ((centers - peak_c).norm(dim=1) <= sep / 2) & (err >= rel_threshold * peak_e)
            pts = centers[member]
            lo = pts.min(dim=0).values - 1.5 * self.voxel_size  # half a voxel + one of padding
            hi = pts.max(dim=0).values + 1.5 * self.voxel_size
            boxes.append(PromptBox(((lo + hi) / 2).tolist(), (hi - lo).tolist(), (1.0, 0.0, 0.0, 0.0), peak_e / top))
        return boxes

    # -- output and checkpoints -----------------------------------------------------------
    def to_arrays(self, prompts: Sequence[PromptBox] = ()) -> dict[str, np.ndarray]:
        """Snapshot arrays (float32): ``field_centers`` [M, 3] voxel centres,
        ``field_loss`` [M] = E, ``field_attention`` [M] = A with ``prompts``."""
        centers = self.voxel_centers().float()
        return {
            "field_centers": centers.numpy().astype(np.float32).reshape(-1, 3),
            "field_loss": self.voxel_error().float().numpy().astype(np.float32),
            "field_attention": self.attention(centers, prompts).numpy().astype(np.float32),
        }

    def state_dict(self) -> dict[str, Any]:
        return {
            "voxel_size": self.voxel_size,
            "half_life": self.half_life,
            "prior_hits": self.prior_hits,
            "min_alpha": self.min_alpha,
            "prune_below": self.prune_below,
            "step": self.step,
            "keys": self.keys.clone(),
            "loss_sum": self.loss_sum.clone(),
            "hits": self.hits.clone(),
        }

    def load_state_dict(self, state: dict[str, Any]) -> None:
        for name in ("voxel_size", "half_life", "prior_hits", "min_alpha", "prune_below"):
            setattr(self, name, float(state[name]))
        self.step = int(state["step"])
        self.keys = torch.as_tensor(state["keys"], dtype=torch.long).clone()
        self.loss_sum = torch.as_tensor(state["loss_sum"], dtype=torch.float64).clone()
        self.hits = torch.as_tensor(state["hits"], dtype=torch.float64).clone()
