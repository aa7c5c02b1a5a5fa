import io
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from promptgs_engine.errorfield import ErrorField, backproject
from promptgs_engine.prompts import PromptBox

W, H, F, CX, CY = 64, 48, 100.0, 32.0, 24.0


def cam(w2c=None, w=W, h=H):
    K = torch.tensor([[F, 0, CX], [0, F, CY], [0, 0, 1]], dtype=torch.float32)
    w2c = torch.eye(4) if w2c is None else w2c
    return SimpleNamespace(name="c", width=w, height=h, K=K, world_to_camera=w2c, image_path=None)


def posed_camera():
    # rotation of 30° about x then 20° about y, camera centre at (1, 2, -3)
    a, b = math.radians(30), math.radians(20)
    rx = torch.tensor([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    ry = torch.tensor([[math.cos(b), 0, math.sin(b)], [0, 1, 0], [-math.sin(b), 0, math.cos(b)]])
    R = (ry @ rx).float()
    C = torch.tensor([1.0, 2.0, -3.0])
    w2c = torch.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ C
    return cam(w2c)


def spot(col, row, w=W, h=H, value=1.0):
    loss = torch.zeros(h, w)
    loss[row, col] = value
    return loss


def project(camera, world):
    w2c = camera.world_to_camera.double()
    x = w2c[:3, :3] @ world.double() + w2c[:3, 3]
    uvw = camera.K.double() @ x
    return uvw[:2] / uvw[2], x[2]


def test_backprojected_spot_reprojects_to_the_pixel_centre():
    c = posed_camera()
    pts, vals = backproject(spot(40, 10), torch.full((H, W), 4.2), None, c, top_q=1e-9)
    assert pts.shape == (1, 3) and vals.tolist() == [1.0]
    uv, z = project(c, pts[0])
    assert uv.tolist() == pytest.approx([40.5, 10.5], abs=1e-4) and float(z) == pytest.approx(4.2)
    # a half-resolution map of the same camera: pixel (20, 5) is centred at full-res (41, 11)
    pts, _ = backproject(spot(20, 5, W // 2, H // 2), torch.full((H // 2, W // 2), 4.2), None, c, top_q=1e-9)
    uv, _ = project(c, pts[0])
    assert uv.tolist() == pytest.approx([41.0, 11.0], abs=1e-4)


def test_spot_lands_in_the_right_voxel():
    # depth 4.9: u = 40.5 gives x = 0.4165 (voxel 4); u = 40 would give 0.392 (voxel 3)
    field = ErrorField(voxel_size=0.1)
    field.accumulate(spot(40, 10), torch.full((H, W), 4.9), torch.ones(H, W), cam(), step=0)
    arrays = field.to_arrays()
    hottest = arrays["field_centers"][np.argmax(arrays["field_loss"])]
    expected = (np.array([4, -7, 49]) + 0.5) * 0.1  # x 0.4165, y -0.6615, z 4.9
    assert hottest == pytest.approx(expected, abs=1e-5)
    assert field.loss_at(torch.tensor([[0.4165, -0.6615, 4.9]])).item() > 0
    assert field.loss_at(torch.tensor([[0.3, -0.6615, 4.9], [9.0, 9.0, 9.0]])).tolist() == [0.0, 0.0]


def test_alpha_mask_and_top_q():
    field = ErrorField(voxel_size=0.1, min_alpha=0.5)
    alpha = torch.zeros(H, W)
    alpha[:, : W // 2] = 1.0  # only the left half is covered by Gaussians
    loss = torch.rand(H, W, generator=torch.Generator().manual_seed(0))
    n = field.accumulate(loss, torch.full((H, W), 3.0), alpha, cam(), step=0)
    assert n == H * W // 2
    assert (field.voxel_centers()[:, 0] < 0).all()  # left half of the image: x < 0
    assert field.accumulate(loss, torch.full((H, W), 3.0), None, cam(), step=0, top_q=0.1) == math.ceil(0.1 * H * W)


def test_decay_halves_after_half_life():
    field = ErrorField(voxel_size=1.0, half_life=100, prior_hits=0.0)
    p = torch.tensor([[0.5, 0.5, 0.5]])
    field.add_points(p, torch.tensor([2.0]), step=0)
    field.add_points(torch.tensor([[5.5, 0.5, 0.5]]), torch.tensor([1.0]), step=100)
    assert field.loss_sum.tolist() == pytest.approx([1.0, 1.0])  # old voxel decayed by 1/2
    assert field.loss_at(p).item() == pytest.approx(2.0)  # the mean is unchanged by decay
    field.add_points(torch.zeros(0, 3), torch.zeros(0), step=100 + 2000)
    assert len(field) == 0  # 2^-20 of a hit: pruned


def _two_hot_spots(seed=0):
    g = torch.Generator().manual_seed(seed)
    field = ErrorField(voxel_size=0.1)
    bg = torch.rand(3000, 3, generator=g) * 10 - 5
    field.add_points(bg, torch.full((3000,), 0.05), step=0)
    a = torch.randn(300, 3, generator=g) * 0.05 + torch.tensor([0.0, 0.0, 0.0])
    b = torch.randn(300, 3, generator=g) * 0.05 + torch.tensor([3.0, -1.0, 2.0])
    field.add_points(torch.cat([a, b]), torch.cat([torch.full((300,), 1.0), torch.full((300,), 0.6)]), step=0)
    return field


def test_peaks_find_two_separated_hot_spots():
    field = _two_hot_spots()
    boxes = field.peaks(2, min_separation=1.0)
    assert len(boxes) == 2
    assert boxes[0].contains(torch.tensor([[0.0, 0.0, 0.0]])).item()
    assert boxes[1].contains(torch.tensor([[3.0, -1.0, 2.0]])).item()
    assert boxes[0].weight == 1.0 and 0.3 < boxes[1].weight < 1.0
    for b in boxes:
        assert max(b.size) < 1.0  # a tight region, not the whole scene


def test_attention_formula_and_arrays():
    field = _two_hot_spots()
    prompt = PromptBox((3.0, -1.0, 2.0), (0.5, 0.5, 0.5), weight=2.0)
    pts = torch.tensor([[0.0, 0.0, 0.0], [3.0, -1.0, 2.0]])
    norm = field.normalized(pts)
    assert ((norm > 0) & (norm <= 1)).all()
    att = field.attention(pts, [prompt])
    assert att.tolist() == pytest.approx([norm[0].item(), 3 * norm[1].item()])
    arr = field.to_arrays([prompt])
    m = len(field)
    assert arr["field_centers"].shape == (m, 3) and arr["field_loss"].shape == (m,)
    assert all(v.dtype == np.float32 for v in arr.values())
    inside = prompt.contains(torch.from_numpy(arr["field_centers"])).numpy()
    assert inside.any()
    ratio = arr["field_attention"][inside] / np.maximum(np.minimum(arr["field_loss"][inside] / field.reference_error(), 1), 1e-12)
    assert ratio == pytest.approx(3.0, rel=1e-4)


def test_state_dict_round_trip():
    field = _two_hot_spots()
    buf = io.BytesIO()
    torch.save(field.state_dict(), buf)
    buf.seek(0)
    other = ErrorField(voxel_size=1.0)
    other.load_state_dict(torch.load(buf))
    pts = torch.rand(100, 3) * 6 - 3
    assert torch.equal(field.loss_at(pts), other.loss_at(pts))
    assert other.step == field.step and other.voxel_size == 0.1
    assert ErrorField.from_extent(5.0, resolution=100).voxel_size == pytest.approx(0.1)
    assert ErrorField(0.1).peaks(3) == [] and ErrorField(0.1).loss_at(pts).sum() == 0


def test_accumulated_sums_match_a_count_per_voxel():
    """Points added over many steps, into voxels old and new: every stored voxel holds the
    sum of the losses and the number of points that fell in it, keys sorted and unique."""
    field = ErrorField(0.1, half_life=0.0)
    g = torch.Generator().manual_seed(0)
    expected: dict = {}
    for step in range(12):
        pts = torch.rand(300, 3, generator=g, dtype=torch.float64) * 2.0 - 1.0
        vals = torch.rand(300, generator=g, dtype=torch.float64)
        field.add_points(pts, vals, step=step)
        for key, v in zip(map(tuple, torch.floor(pts / 0.1).long().tolist()), vals.tolist()):
            total, hits = expected.get(key, (0.0, 0))
            expected[key] = (total + v, hits + 1)
    assert len(field) == len(expected)
    assert bool((field.keys[1:] > field.keys[:-1]).all())
    for centre, total, hits in zip(field.voxel_centers(), field.loss_sum.tolist(), field.hits.tolist()):
        want_total, want_hits = expected[tuple(torch.floor(centre / 0.1).long().tolist())]
        assert abs(total - want_total) < 1e-9 and hits == want_hits
