import json
import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from promptgs_engine.errors import PromptError
from promptgs_engine.prompts import (
    PromptBox,
    boxes_contain,
    center_prompt,
    check_visible,
    contains_any,
    load_prompts,
    max_weight,
    project_box,
    prompts_from_json,
    save_prompts,
)

S45 = math.sin(math.radians(22.5))
C45 = math.cos(math.radians(22.5))
ROT_Y45 = (C45, 0.0, S45, 0.0)  # 45° about the y axis


def cam(w2c=None, f=100.0, cx=50.0, cy=50.0, w=100, h=100):
    K = torch.tensor([[f, 0, cx], [0, f, cy], [0, 0, 1]], dtype=torch.float32)
    w2c = torch.eye(4) if w2c is None else torch.as_tensor(w2c, dtype=torch.float32)
    return SimpleNamespace(name="c", width=w, height=h, K=K, world_to_camera=w2c, image_path=None)


# -- containment ----------------------------------------------------------------------


def test_contains_axis_aligned_and_rotated():
    pts = torch.tensor([[0.0, 0, 0], [0.55, 0, 0], [0.4, 0, 0.4], [0.5, 0.5, 0.5], [0, 0, 0.51]])
    aa = PromptBox((0, 0, 0), (1, 1, 1))
    assert aa.contains(pts).tolist() == [True, False, True, True, False]
    rot = PromptBox((0, 0, 0), (1, 1, 1), ROT_Y45)
    # (0.55,0,0) -> local (0.39, 0, 0.39): inside; (0.4,0,0.4) -> local (0, 0, 0.57): outside
    # (0,0,0.51) -> local (-0.36, 0, 0.36): inside; the corner (0.5,0.5,0.5) -> (0, .5, .71): outside
    assert rot.contains(pts).tolist() == [True, True, False, False, True]
    # a translated, elongated, rotated box: 90° about z maps local x to world y
    q = (math.cos(math.pi / 4), 0, 0, math.sin(math.pi / 4))
    long = PromptBox((10, 0, 0), (4, 1, 1), q)
    p2 = torch.tensor([[10, 1.9, 0], [11.9, 0, 0], [10, -2.1, 0]])
    assert long.contains(p2).tolist() == [True, False, False]
    # 30° about z: the long axis points along (cos 30°, sin 30°, 0); catches R vs Rᵀ
    t = math.radians(30)
    tilted = PromptBox((0, 0, 0), (4, 1, 1), (math.cos(t / 2), 0, 0, math.sin(t / 2)))
    p3 = torch.tensor([[1.9 * math.cos(t), 1.9 * math.sin(t), 0], [1.9 * math.cos(t), -1.9 * math.sin(t), 0]])
    assert tilted.contains(p3).tolist() == [True, False]


def test_union_and_max_weight():
    a = PromptBox((0, 0, 0), (2, 2, 2), weight=1.0)
    b = PromptBox((1, 0, 0), (2, 2, 2), weight=3.0)
    pts = torch.tensor([[-0.5, 0, 0], [0.5, 0, 0], [1.5, 0, 0], [5, 0, 0]])
    assert boxes_contain([a, b], pts).tolist() == [[True, True, False, False], [False, True, True, False]]
    assert contains_any([a, b], pts).tolist() == [True, True, True, False]
    assert max_weight([a, b], pts).tolist() == [1.0, 3.0, 3.0, 0.0]
    assert contains_any([], pts).tolist() == [False] * 4


def test_corners_and_center_prompt():
    c = center_prompt()
    assert c.center == (0, 0, 0) and c.size == (1, 1, 1) and c.volume() == 1.0
    corners = PromptBox((1, 2, 3), (2, 4, 6)).corners()
    assert torch.allclose(corners.min(0).values, torch.tensor([0.0, 0, 0], dtype=torch.float64))
    assert torch.allclose(corners.max(0).values, torch.tensor([2.0, 4, 6], dtype=torch.float64))
    r = PromptBox((0, 0, 0), (1, 1, 1), ROT_Y45).corners()
    assert r[:, 0].abs().max().item() == pytest.approx(math.sqrt(2) / 2)


def test_from_matrix_round_trip():
    box = PromptBox((1, -2, 3), (0.5, 2, 3), (0.9, 0.1, -0.3, 0.2), 2.0)
    back = PromptBox.from_matrix(box.box_to_world(), weight=2.0)
    assert np.allclose(back.box_to_world(), box.box_to_world())
    blender_cube = PromptBox.from_matrix(np.diag([0.5, 0.5, 0.5, 1.0]), base_edge=2.0)
    assert blender_cube.size == pytest.approx((1, 1, 1))


# -- projection -------------------------------------------------------------------------


def test_projection_of_box_in_front():
    p = project_box(PromptBox((0, 0, 5), (1, 1, 1)), cam())
    half = 100 * 0.5 / 4.5  # front face at z = 4.5 bounds the silhouette
    assert p.in_front and p.visible
    assert p.bbox == pytest.approx((50 - half, 50 - half, 50 + half, 50 + half))
    assert p.visible_area == pytest.approx((2 * half) ** 2)
    assert p.in_image_fraction == pytest.approx(1.0)
    assert p.distance == pytest.approx(5.0) and p.view_cos == pytest.approx(1.0)
    assert p.pixel_bbox() == (38, 38, 62, 62)


def test_projection_of_rotated_box():
    p = project_box(PromptBox((0, 0, 5), (1, 1, 1), ROT_Y45), cam())
    r = math.sqrt(2) / 2
    u = 100 * r / 5  # side edges at x = ±r, z = 5
    v_front = 100 * 0.5 / (5 - r)  # front edge at z = 5 - r
    v_side = 100 * 0.5 / 5
    # hexagon = two trapezoids of width u with parallel sides 2·v_front and 2·v_side
    assert p.visible_area == pytest.approx(2 * u * (v_front + v_side))
    assert p.bbox == pytest.approx((50 - u, 50 - v_front, 50 + u, 50 + v_front))


def test_projection_with_camera_pose():
    # camera at world (0, 0, -5) looking along +z, rotated 90° about its optical axis:
    # world x maps to camera y (down), world y to camera -x
    R = torch.tensor([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    C = torch.tensor([0.0, 0, -5])
    w2c = torch.eye(4)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ C
    p = project_box(PromptBox((0.5, 0, 0), (0.2, 0.2, 0.2)), cam(w2c))
    # centre at camera (0, 0.5, 5): v = 50 + 100·0.5/5 = 60
    x0, y0, x1, y1 = p.bbox
    assert (x0 + x1) / 2 == pytest.approx(50.0, abs=1e-6)
    assert 58 < (y0 + y1) / 2 < 62 and p.distance == pytest.approx(math.sqrt(25.25))


def test_projection_behind_camera():
    p = project_box(PromptBox((0, 0, -5), (1, 1, 1)), cam())
    assert not p.in_front and not p.visible and p.bbox is None and p.visible_area == 0
    assert p.distance == pytest.approx(5.0)


def test_projection_partly_outside_image():
    # principal point at the left image edge: the box's silhouette is cut in half
    p = project_box(PromptBox((0, 0, 5), (1, 1, 1)), cam(cx=0.0))
    half = 100 * 0.5 / 4.5
    assert p.projected_area == pytest.approx((2 * half) ** 2)
    assert p.in_image_fraction == pytest.approx(0.5)
    assert p.visible_area == pytest.approx(2 * half * half)
    assert p.bbox == pytest.approx((0.0, 50 - half, half, 50 + half))
    # entirely to the side: in front but not visible
    q = project_box(PromptBox((20, 0, 5), (1, 1, 1)), cam())
    assert q.in_front and not q.visible and q.in_image_fraction == 0.0


def test_projection_box_around_camera_fills_image():
    p = project_box(PromptBox((0, 0, 0), (2, 2, 2)), cam())
    assert p.in_front and p.visible_area == pytest.approx(100 * 100)
    assert p.in_image_fraction < 0.01


def test_check_visible_names_unseen_box():
    boxes = [PromptBox((0, 0, 5), (1, 1, 1)), PromptBox((0, 0, -5), (1, 1, 1))]
    with pytest.raises(PromptError, match=r"p\.json: prompt 1 .*none of the 2 training cameras"):
        check_visible(boxes, [cam(), cam(cx=0.0)], source="p.json")
    assert check_visible(boxes[:1], [cam(), cam(cx=500.0)]) == [[0]]


# -- file format ------------------------------------------------------------------------


def test_file_round_trip(tmp_path):
    boxes = [PromptBox((1, 2, 3), (0.5, 1, 2), (0.5, 0.5, 0.5, 0.5), 2.5), center_prompt()]
    path = tmp_path / "prompts.json"
    save_prompts(path, boxes)
    assert load_prompts(path) == boxes
    raw = json.loads(path.read_text())
    assert set(raw["prompts"][0]) == {"center", "size", "rotation_wxyz", "weight"}
    # weight is optional
    (tmp_path / "b.json").write_text('{"prompts": [{"center": [0,0,0], "size": [1,1,1], "rotation_wxyz": [1,0,0,0]}]}')
    assert load_prompts(tmp_path / "b.json")[0].weight == 1.0
    assert prompts_from_json({"prompts": []}) == []


GOOD = {"center": [0, 0, 0], "size": [1, 1, 1], "rotation_wxyz": [1, 0, 0, 0], "weight": 1}


@pytest.mark.parametrize(
    "change, message",
    [
        ({"center": None}, r"missing key\(s\) 'center'"),
        ({"size": [1, float("nan"), 1]}, r"'size' has a non-finite number"),
        ({"center": [0, float("inf"), 0]}, r"'center' has a non-finite number"),
        ({"size": [1, 0, 1]}, r"'size' must be positive"),
        ({"size": [1, -2, 1]}, r"'size' must be positive"),
        ({"rotation_wxyz": [0, 0, 0, 0]}, r"'rotation_wxyz' is the zero quaternion"),
        ({"rotation_wxyz": [1, 0, 0]}, r"'rotation_wxyz' must be a list of 4 numbers"),
        ({"weight": -1}, r"'weight' must be a finite number >= 0"),
        ({"center": [0, "a", 0]}, r"'center' must be a list of 3 numbers"),
        ({"colour": 1}, r"unknown key\(s\) 'colour'"),
    ],
)
def test_bad_entries_name_file_and_entry(tmp_path, change, message):
    bad = dict(GOOD)
    for k, v in change.items():
        if v is None:
            del bad[k]
        else:
            bad[k] = v
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"prompts": [GOOD, bad]}))  # json writes NaN/Infinity
    with pytest.raises(PromptError, match=r"bad\.json: prompt 1: " + message) as e:
        load_prompts(path)
    assert "\n" not in str(e.value)


def test_bad_files(tmp_path):
    with pytest.raises(PromptError, match="nope.json: prompt file not found"):
        load_prompts(tmp_path / "nope.json")
    (tmp_path / "x.json").write_text("{not json")
    with pytest.raises(PromptError, match=r"x\.json: not valid JSON"):
        load_prompts(tmp_path / "x.json")
    (tmp_path / "y.json").write_text("[1, 2]")
    with pytest.raises(PromptError, match=r"y\.json: expected an object"):
        load_prompts(tmp_path / "y.json")
    (tmp_path / "z.json").write_text('{"prompts": [5]}')
    with pytest.raises(PromptError, match=r"z\.json: prompt 0: expected an object"):
        load_prompts(tmp_path / "z.json")
    with pytest.raises(PromptError):
        PromptBox((0, 0, 0), (1, 1, 0))
