import numpy as np
import pytest
import torch
from plyfile import PlyData

from promptgs_engine.errors import PromptGSError
from promptgs_engine.gaussians import (
    init_from_points,
    load_ply,
    nearest_neighbor_distance,
    save_ply,
    sh_degree_of,
    sh_to_rgb,
)


def _random_params(n=50, degree=3, seed=0):
    g = torch.Generator().manual_seed(seed)
    pts = torch.randn(n, 3, generator=g)
    cols = torch.rand(n, 3, generator=g)
    p = init_from_points(pts, cols, sh_degree=degree)
    with torch.no_grad():
        for v in p.values():
            v.add_(0.1 * torch.randn(v.shape, generator=g))
    return p


def test_init_from_points_sizes_by_neighbour_distance():
    pts = torch.tensor([[0.0, 0, 0], [1.0, 0, 0], [0, 2.0, 0], [10.0, 10, 10]])
    d = nearest_neighbor_distance(pts, k=1)
    assert torch.allclose(d, torch.tensor([1.0, 1.0, 2.0, (100 + 64 + 100) ** 0.5]), atol=1e-5)
    p = init_from_points(pts, torch.full((4, 3), 0.25), sh_degree=2, init_opacity=0.1)
    assert p["shN"].shape == (4, 8, 3)
    assert sh_degree_of(p) == 2
    assert torch.allclose(torch.sigmoid(p["opacities"]), torch.full((4,), 0.1))
    assert torch.allclose(sh_to_rgb(p["sh0"][:, 0]), torch.full((4, 3), 0.25), atol=1e-6)
    # Isotropic and the same order as the neighbour distance (mean of 3 nearest).
    s = torch.exp(p["scales"])
    assert torch.allclose(s[:, 0], s[:, 2])
    assert torch.argmax(s[:, 0]) == 3


def test_ply_round_trip_keeps_every_parameter(tmp_path):
    p = _random_params()
    save_ply(p, tmp_path / "g.ply")
    q = load_ply(tmp_path / "g.ply")
    for k in p:
        assert torch.equal(p[k].detach(), q[k].detach()), k


def test_ply_uses_the_standard_3dgs_layout(tmp_path):
    p = _random_params(n=4, degree=1)
    save_ply(p, tmp_path / "g.ply")
    v = PlyData.read(str(tmp_path / "g.ply"))["vertex"]
    names = list(v.data.dtype.names)
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    # f_rest is channel-major: the first K-1 values are the red channel's coefficients.
    assert np.allclose(v["f_rest_0"], p["shN"][:, 0, 0].detach().numpy())
    assert np.allclose(v["f_rest_1"], p["shN"][:, 1, 0].detach().numpy())
    assert np.allclose(v["f_rest_3"], p["shN"][:, 0, 1].detach().numpy())


def test_load_ply_rejects_other_files(tmp_path):
    with pytest.raises(PromptGSError, match="no such PLY"):
        load_ply(tmp_path / "missing.ply")
    (tmp_path / "junk.ply").write_text("not a ply")
    with pytest.raises(PromptGSError, match="not a readable PLY"):
        load_ply(tmp_path / "junk.ply")
