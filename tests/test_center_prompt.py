"""The centre prompt is defined in the scene's own frame, and a box among the cameras warns."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from promptgs_engine.bench.toy_scene import look_at
from promptgs_engine.config import TrainConfig
from promptgs_engine.data import Camera
from promptgs_engine.errors import PromptError
from promptgs_engine.prompts import (
    PromptBox, camera_center, center_prompt, check_visible, placement_warnings, scene_center_prompt, scene_look_point,
)
from promptgs_engine.train import Trainer


def _camera(centre, target, size=96, f=80.0) -> Camera:
    K = torch.tensor([[f, 0, size / 2], [0, f, size / 2], [0, 0, 1]], dtype=torch.float32)
    w2c = torch.tensor(look_at(np.asarray(centre, float), np.asarray(target, float)), dtype=torch.float32)
    return Camera("c", size, size, K, w2c, Path("none"))


def _ring_capture(look, radius, n=12, seed=0):
    """``n`` cameras on a ring of ``radius`` around ``look``, a little above it, all looking
    at it, and SfM points scattered around it: a capture in its own frame."""
    look = np.asarray(look, float)
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        centre = look + radius * np.array([math.cos(a), math.sin(a), 0.4 + 0.1 * math.sin(3 * a)])
        cams.append(_camera(centre, look))
    points = look + 0.2 * radius * np.random.default_rng(seed).standard_normal((500, 3))
    return cams, points


def test_the_centre_prompt_is_where_the_cameras_look_and_scales_with_the_scene():
    # A capture whose origin lies far below everything it shows (a COLMAP model's origin
    # and scale are arbitrary).
    cams, points = _ring_capture((5.0, -3.0, 40.0), radius=3.0)
    box = scene_center_prompt(cams, points)
    distance = float(np.median([np.linalg.norm(camera_center(c) - (5.0, -3.0, 40.0)) for c in cams]))
    assert np.allclose(box.center, (5.0, -3.0, 40.0), atol=0.01)
    assert box.size == pytest.approx((0.25 * distance,) * 3, rel=0.01)
    assert check_visible([box], cams) and placement_warnings([box], cams, points) == []
    # The paper's unit box at the origin means nothing here: no camera sees it.
    with pytest.raises(PromptError, match="seen by none"):
        check_visible([center_prompt()], cams)
    # The same capture moved and ten times larger: the box moves and grows with it.
    big_cams, big_points = _ring_capture((-300.0, 80.0, 2.0), radius=30.0)
    big = scene_center_prompt(big_cams, big_points)
    moved = np.array([-300.0, 80.0, 2.0]) + 10 * (np.array(box.center) - (5.0, -3.0, 40.0))
    assert np.allclose(big.center, moved, atol=1e-3)
    assert big.size[0] == pytest.approx(10 * box.size[0], rel=1e-4)


def test_a_forward_facing_capture_gets_its_box_at_the_depth_of_its_points():
    # Parallel optical axes (+x) never meet; the SfM points, 20 units ahead, set the depth.
    cams = []
    for y in (-1.0, 0.0, 1.0):
        for z in (-0.5, 0.5):
            cams.append(_camera((0.0, y, z), (10.0, y, z)))
    rng = np.random.default_rng(1)
    points = np.stack([rng.uniform(19, 21, 400), rng.uniform(-4, 4, 400), rng.uniform(-3, 3, 400)], 1)
    look, distance = scene_look_point(cams, points)
    assert abs(look[0] - 20.0) < 0.5 and abs(look[1]) < 0.1 and abs(look[2]) < 0.1
    assert 19.5 < distance < 20.6


def test_a_box_among_the_cameras_gets_a_warning_naming_the_camera():
    cams, points = _ring_capture((0.0, 0.0, 0.0), radius=5.0)
    near_camera = PromptBox(tuple(float(v) for v in camera_center(cams[3]) * 0.97), (0.3, 0.3, 0.3))
    in_scene = PromptBox((0.5, 0.0, 0.0), (0.3, 0.3, 0.3))
    lines = placement_warnings([in_scene, near_camera], cams, points, names=[f"view_{i}" for i in range(len(cams))])
    assert len(lines) == 1
    assert lines[0].startswith("prompt 1 ") and "lies among the cameras" in lines[0] and "view_3" in lines[0]
    assert "\n" not in lines[0]


def test_training_warns_about_a_box_among_the_cameras(toy, tmp_path, capsys):
    # The toy's cameras ring the scene at radius 6, about 3 units up; a box just inside the
    # ring by view 1 (the first training camera, at (5.54, 2.30, 3.55)) is seen by the
    # cameras across the ring, but lies among them.
    box = {"prompts": [{"center": [5.26, 2.19, 3.37], "size": [0.4, 0.4, 0.4], "rotation_wxyz": [1, 0, 0, 0]}]}
    (tmp_path / "near.json").write_text(json.dumps(box))
    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run"), strategy="promptgs", prompts=str(tmp_path / "near.json"))
    Trainer(cfg, quiet=True)
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("promptgs: warning:")]
    assert any("prompt 0" in line and "lies among the cameras" in line and "view_001" in line for line in err), err
    # The centre prompt of the same scene lands where the toy's cameras look (0, 0, 0.6),
    # sized from their distance, and gets no warning.
    cfg = TrainConfig(dataset=str(toy), out=str(tmp_path / "run2"), strategy="promptgs", center_prompt=True)
    focus = Trainer(cfg, quiet=True).focus
    (centre_box,) = focus.prompts
    assert np.allclose(centre_box.center, (0.0, 0.0, 0.6), atol=0.1)
    assert 1.4 < centre_box.size[0] < 1.9  # a quarter of the ~6.7 units the cameras stand away
    assert "lies among the cameras" not in capsys.readouterr().err
