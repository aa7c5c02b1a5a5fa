import math

import numpy as np
import pytest
import torch
from PIL import Image

from promptgs_engine.bench.toy_scene import look_at
from promptgs_engine.data import Camera
from promptgs_engine.sky import EXTRAPOLATE_DEGREES, SKY_RADIUS_FACTOR, fibonacci_directions, sky_points

SKY = (0.2, 0.4, 0.9)
GROUND = (0.3, 0.6, 0.2)


def _cameras(tmp_path, n=6, width=64, height=48, focal=40.0):
    """Cameras on a ring of radius 2 at height 0, looking level at the origin; each image
    is sky above the horizon row and ground below it."""
    img = np.zeros((height, width, 3), dtype=np.uint8)
    img[: height // 2] = np.array(SKY) * 255
    img[height // 2 :] = np.array(GROUND) * 255
    path = tmp_path / "split.png"
    Image.fromarray(img).save(path)
    K = torch.tensor([[focal, 0, width / 2], [0, focal, height / 2], [0, 0, 1]], dtype=torch.float32)
    cams = []
    for i, a in enumerate(np.linspace(0, 2 * math.pi, n, endpoint=False)):
        center = np.array([2 * math.cos(a), 2 * math.sin(a), 0.0])
        w2c = torch.tensor(look_at(center, np.zeros(3)), dtype=torch.float32)
        cams.append(Camera(f"{i}.png", width, height, K, w2c, path))
    return cams


def test_fibonacci_directions_are_unit_and_cover_the_sphere():
    d = fibonacci_directions(2000)
    assert torch.allclose(d.norm(dim=1), torch.ones(2000), atol=1e-5)
    assert abs(float(d.mean(dim=0).norm())) < 0.01
    # Every direction has a neighbour within about twice the mean spacing.
    spacing = math.sqrt(4 * math.pi / 2000)
    nearest = torch.cdist(d, d).fill_diagonal_(9).min(dim=1).values
    assert float(nearest.max()) < 2 * spacing


def test_sky_points_lie_beyond_the_scene_where_cameras_look_with_the_colour_they_see(tmp_path):
    cams = _cameras(tmp_path)
    scene_points = (torch.rand(500, 3) - 0.5) * 20  # out to about 10 from the origin
    points, colors, shell_radius = sky_points(cams, scene_points, n_directions=4000)
    assert points.shape[0] > 0 and colors.shape == points.shape
    # On a sphere around the cameras' centre (the origin), beyond cameras and points.
    radius = points.norm(dim=1)
    assert torch.allclose(radius, radius[0].expand_as(radius), rtol=1e-4)
    reach = float(torch.quantile(scene_points.norm(dim=1), 0.95))
    assert float(radius[0]) >= SKY_RADIUS_FACTOR * reach - 1e-3
    assert shell_radius == pytest.approx(float(radius[0]), rel=1e-5)
    # Level cameras with a vertical half field of view of atan(24/40) = 31 degrees see
    # elevations up to 31 degrees (seen from the origin, up to about 7 degrees of
    # parallax more: the cameras stand 2 from it, the shell about 17); extrapolation adds
    # up to EXTRAPOLATE_DEGREES, and nothing near the zenith or the nadir is kept.
    elevation = torch.rad2deg(torch.asin(points[:, 2] / radius))
    limit = math.degrees(math.atan(24 / 40)) + 7 + EXTRAPOLATE_DEGREES + 2
    assert float(elevation.abs().max()) < limit
    assert float(elevation.abs().max()) > 40  # the extrapolated band is there
    # Above the horizon the colour is the sky's, below it the ground's.
    above, below = elevation > 8, elevation < -8
    assert torch.allclose(colors[above], torch.tensor(SKY).expand(int(above.sum()), 3), atol=0.01)
    assert torch.allclose(colors[below], torch.tensor(GROUND).expand(int(below.sum()), 3), atol=0.01)


def test_extrapolated_directions_continue_the_nearest_seen_colour(tmp_path):
    cams = _cameras(tmp_path)
    points, colors, _ = sky_points(cams, torch.full((1, 3), 10.0), n_directions=4000)
    elevation = torch.rad2deg(torch.asin(points[:, 2] / points.norm(dim=1)))
    seen_top = math.degrees(math.atan(24 / 40)) + 7
    beyond = elevation > seen_top + 2  # no camera sees these
    assert bool(beyond.any())
    assert torch.allclose(colors[beyond], torch.tensor(SKY).expand(int(beyond.sum()), 3), atol=0.01)


def _pruning_setup(sizes, background):
    from promptgs_engine.gaussians import init_from_points
    from promptgs_engine.strategies import DefaultSchedule, make_default_strategy
    from promptgs_engine.strategies.default import BACKGROUND, BACKGROUND_RADIUS
    from promptgs_engine.config import TrainConfig
    from promptgs_engine.train import make_optimizers

    n = len(sizes)
    params = init_from_points(torch.arange(3.0 * n).reshape(n, 3), torch.full((n, 3), 0.5), sh_degree=0, init_opacity=0.5)
    with torch.no_grad():
        params["scales"].copy_(torch.log(torch.tensor(sizes)).unsqueeze(-1).expand(n, 3))
    opts = make_optimizers(params, TrainConfig(dataset="d", out="o"), extent=1.0)
    strategy = make_default_strategy("3dgs", DefaultSchedule.for_iterations(1000))
    state = strategy.initialize_state(scene_scale=1.0)  # 3DGS's limit: 0.1
    state[BACKGROUND] = torch.tensor(background)
    state[BACKGROUND_RADIUS] = 10.0  # the shell's limit: 0.1 × 10 = 1.0
    return strategy, params, opts, state


def test_pruning_by_size_keeps_the_background_shell_within_its_own_angular_limit():
    # Scene Gaussians of size 0.05 and 0.5, shell Gaussians of size 0.5 and 2.0: 3DGS's
    # limit (0.1 × scene scale) removes the scene's 0.5; the shell's 0.5 is within the
    # same limit taken as an angle at the shell's radius, its 2.0 is not.
    strategy, params, opts, state = _pruning_setup([0.05, 0.5, 0.5, 2.0], [0.0, 0.0, 1.0, 1.0])
    assert strategy._prune_gs(params, opts, state, step=strategy.reset_every + 1) == 2
    assert torch.exp(params["scales"][:, 0]).tolist() == pytest.approx([0.05, 0.5])
    assert state["background"].tolist() == [0.0, 1.0]
    # Before the first reset only faint Gaussians go, as in 3DGS.
    strategy, params, opts, state = _pruning_setup([0.05, 0.5, 0.5, 2.0], [0.0, 0.0, 1.0, 1.0])
    assert strategy._prune_gs(params, opts, state, step=strategy.reset_every) == 0


def test_the_trainer_marks_the_background_shell_for_the_strategy(toy, tmp_path):
    from promptgs_engine.config import TrainConfig
    from promptgs_engine.strategies.default import BACKGROUND, BACKGROUND_RADIUS
    from promptgs_engine.train import Trainer

    trainer = Trainer(TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), iterations=10, sky=True), quiet=True)
    marks = trainer.strategy_state[BACKGROUND]
    assert trainer.n_sky_points > 0 and int(marks.sum()) == trainer.n_sky_points
    assert bool((marks[-trainer.n_sky_points :] == 1).all())
    centre = torch.stack([c.center.float() for c in trainer.scene.train_cameras]).mean(dim=0)
    shell = trainer.params["means"][-trainer.n_sky_points :].detach().cpu()  # "auto" may have picked a GPU
    assert float((shell - centre).norm(dim=1).mean()) == pytest.approx(trainer.strategy_state[BACKGROUND_RADIUS], rel=1e-4)
