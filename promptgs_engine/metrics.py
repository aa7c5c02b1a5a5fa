"""Image-quality metrics: PSNR, SSIM, and object-region metrics for tiny objects.

Images are ``[H, W, 3]`` float tensors in [0, 1]; masks are ``[H, W]`` bool (True = object).
"""

from __future__ import annotations

import math
from typing import Iterator

import torch
import torch.nn.functional as F

from .losses import ssim_map


def mse_to_psnr(mse: float) -> float:
    return float("inf") if mse <= 0 else -10.0 * math.log10(mse)


def loss_and_mse(loss: torch.Tensor, img: torch.Tensor, ref: torch.Tensor) -> tuple[float, float]:
    """A training step's loss and its image's MSE against ``ref`` as Python numbers, read
    from the device together: on a GPU each read makes the host wait."""
    with torch.no_grad():
        # squared in place: the values of ``(img - ref) ** 2`` without a second image-sized array
        mse = (img.detach() - ref).square_().mean()
    loss_value, mse_value = torch.stack([loss.detach(), mse]).tolist()
    return loss_value, mse_value


def psnr(img: torch.Tensor, ref: torch.Tensor) -> float:
    return mse_to_psnr(float(((img - ref) ** 2).mean()))


def ssim(img: torch.Tensor, ref: torch.Tensor) -> float:
    return float(ssim_map(img[None], ref[None]).mean())


def masked_psnr(img: torch.Tensor, ref: torch.Tensor, mask: torch.Tensor) -> float | None:
    """PSNR over the masked (object) pixels only; None when the mask is empty."""
    if not bool(mask.any()):
        return None
    return mse_to_psnr(float(((img - ref) ** 2)[mask].mean()))


def object_boxes(instance_mask: torch.Tensor, dilate: int = 4) -> list[tuple[int, int, int, int]]:
    """Bounding boxes ``(y0, y1, x0, x1)`` (end-exclusive) of each object id > 0, dilated."""
    h, w = instance_mask.shape
    boxes = []
    for obj in torch.unique(instance_mask):
        if int(obj) == 0:
            continue
        ys, xs = torch.nonzero(instance_mask == obj, as_tuple=True)
        boxes.append(
            (
                max(int(ys.min()) - dilate, 0),
                min(int(ys.max()) + 1 + dilate, h),
                max(int(xs.min()) - dilate, 0),
                min(int(xs.max()) + 1 + dilate, w),
            )
        )
    return boxes


def object_region_psnr(
    img: torch.Tensor, ref: torch.Tensor, instance_mask: torch.Tensor, dilate: int = 4
) -> float | None:
    """PSNR over the union of each object's bounding box dilated by ``dilate`` pixels.

    ``instance_mask`` holds an object id per pixel (0 = background); a binary mask is one
    object. None when there is no object in the image.
    """
    region = torch.zeros_like(instance_mask, dtype=torch.bool)
    for y0, y1, x0, x1 in object_boxes(instance_mask, dilate):
        region[y0:y1, x0:x1] = True
    return masked_psnr(img, ref, region) if bool(region.any()) else None


def resize_mask(mask: torch.Tensor, height: int, width: int) -> torch.Tensor:
    """Resize an id mask to the evaluation resolution.

    Downscaling by a whole factor keeps the largest id in each block, so an object of a
    few pixels is not lost; other sizes use nearest neighbour.
    """
    h, w = mask.shape
    if (h, w) == (height, width):
        return mask
    m = mask[None, None].float()
    if h % height == 0 and w % width == 0 and h // height == w // width:
        return F.max_pool2d(m, h // height)[0, 0].to(mask.dtype)
    return F.interpolate(m, size=(height, width), mode="nearest")[0, 0].to(mask.dtype)


# Below this mean contrast (|drone-free − real| over the object's pixels, in [0, 1]) an
# object is not visible in a view (hidden, or the same colour as what is behind it), and
# the (object, view) pair is left out of recall.
RECALL_MIN_CONTRAST = 0.02


def visible_objects(
    instance_mask: torch.Tensor, contrast_map: torch.Tensor, min_contrast: float = RECALL_MIN_CONTRAST
) -> Iterator[tuple[int, torch.Tensor, float]]:
    """``(object id, its pixels, its contrast)`` for each object of a view whose mean
    contrast (``contrast_map`` [H, W], |object-free truth − truth|) reaches
    ``min_contrast``: the (object, view) pairs that recall counts."""
    for obj in torch.unique(instance_mask).tolist():
        if obj == 0:
            continue
        pixels = instance_mask == obj
        contrast = float(contrast_map[pixels].mean())
        if contrast >= min_contrast:
            yield int(obj), pixels, contrast


def object_recall(
    img: torch.Tensor,
    ref: torch.Tensor,
    ref_without_objects: torch.Tensor,
    instance_mask: torch.Tensor,
    min_contrast: float = RECALL_MIN_CONTRAST,
) -> dict[int, bool]:
    """Which objects a render reconstructs in one view.

    An object counts as reconstructed when the render's mean absolute error over the
    object's pixels is less than half that of the object-free ground truth
    (``ref_without_objects``, e.g. the drone-free render) there: the render explains most
    of the object's contrast. Objects whose contrast is below ``min_contrast`` are not
    visible in this view and are left out. Returns ``{object id: reconstructed}``.
    """
    err_render = (img - ref).abs().mean(dim=-1)
    err_without = (ref_without_objects - ref).abs().mean(dim=-1)
    return {
        obj: float(err_render[pixels].mean()) < 0.5 * contrast
        for obj, pixels, contrast in visible_objects(instance_mask, err_without, min_contrast)
    }
