import math
from collections import Counter
from types import SimpleNamespace

import pytest
import torch

from promptgs_engine.prompts import PromptBox, center_prompt
from promptgs_engine.views import (
    RANDOM_MULTIVIEW,
    RELATED_MULTIVIEW,
    SINGLE,
    ViewSchedule,
    rank_views,
    related_views,
    top_k_views,
    views_cap_from_memory,
)


def look_at(center, target, up=(0.0, 0.0, 1.0)):
    """COLMAP world-to-camera (x right, y down, z forward) for a camera at ``center``."""
    c, t, u = (torch.tensor(v, dtype=torch.float64) for v in (center, target, up))
    z = (t - c) / (t - c).norm()
    x = torch.linalg.cross(z, u)
    x = x / x.norm()
    y = torch.linalg.cross(z, x)
    R = torch.stack([x, y, z])
    w2c = torch.eye(4, dtype=torch.float64)
    w2c[:3, :3] = R
    w2c[:3, 3] = -R @ c
    K = torch.tensor([[100.0, 0, 50], [0, 100, 50], [0, 0, 1]])
    return SimpleNamespace(name="c", width=100, height=100, K=K, world_to_camera=w2c.float(), image_path=None)


def ring(n=12, radius=5.0):
    """Cameras on a ring around the origin; even ones face the origin, odd ones face away."""
    cams = []
    for i in range(n):
        a = 2 * math.pi * i / n
        c = (radius * math.cos(a), radius * math.sin(a), 0.0)
        target = (0.0, 0.0, 0.0) if i % 2 == 0 else (2 * c[0], 2 * c[1], 0.0)
        cams.append(look_at(c, target))
    return cams


def test_ranking_picks_cameras_that_see_the_box():
    cams = ring()
    cams.append(look_at((2.5, 0.0, 0.5), (0.0, 0.0, 0.0)))  # 12: closer, sees the box big
    cams.append(look_at((-5.0, 0.0, 0.0), (-5.0, 3.0, 0.0)))  # 13: box 90° off-axis
    cams.append(look_at((0.0, -5.0, 0.0), (2.5, 0.0, 0.0)))  # 14: sees it at the image edge
    ranked = rank_views(center_prompt(), cams)
    idx = [v.index for v in ranked]
    assert set(idx) == {0, 2, 4, 6, 8, 10, 12, 14}
    assert idx[0] == 12 and idx[-1] == 14
    assert all(0 < v.score <= 1 for v in ranked)
    assert top_k_views(center_prompt(), cams, 3)[0] == 12 and len(top_k_views(center_prompt(), cams, 3)) == 3
    assert top_k_views(PromptBox((0, 0, 50), (1, 1, 1)), cams, 3) == []


def test_related_views_per_region():
    cams = ring()
    boxes = [PromptBox((4.0, 0.0, 0.0), (0.3, 0.3, 0.3)), PromptBox((-4.0, 0.0, 0.0), (0.3, 0.3, 0.3))]
    rel = related_views(boxes, cams, 2)
    assert rel[0][0] == 0 and rel[1][0] == 6  # the facing camera next to each box


def test_image_similarity_term():
    cams = ring()
    # every camera sees the box over rows 38..62: a vertical ramp looks the same in each crop
    ramp = torch.linspace(0, 1, 100)
    vertical = ramp[:, None, None].expand(100, 100, 3)
    horizontal = ramp[None, :, None].expand(100, 100, 3)
    same = rank_views(center_prompt(), cams, load_image=lambda i: vertical)
    assert all(v.similarity == pytest.approx(1.0, abs=1e-5) for v in same)
    # cameras 0 and 6 (lowest by geometry, never the reference) see an orthogonal pattern
    mixed = rank_views(center_prompt(), cams, load_image=lambda i: horizontal if i in (0, 6) else vertical)
    sims = {v.index: v.similarity for v in mixed}
    assert sims[0] == pytest.approx(0.5, abs=1e-3) and sims[6] == pytest.approx(0.5, abs=1e-3)
    assert sims[2] == pytest.approx(1.0, abs=1e-5)
    plain = {v.index: v.score for v in rank_views(center_prompt(), cams)}
    assert {v.index: v.score for v in mixed}[0] < plain[0]


def test_views_cap_from_memory():
    assert views_cap_from_memory(1e9, 10e9) == 9
    assert views_cap_from_memory(1e9, 10e9, reserve_fraction=0.0, max_views=4) == 4
    assert views_cap_from_memory(1e9, 1e8) == 1
    with pytest.raises(ValueError):
        views_cap_from_memory(0, 1e9)


def test_schedule_ratio_coverage_and_cap():
    n, cap = 13, 4
    regions = [[0, 1, 2, 3, 4], [5, 6]]
    sched = ViewSchedule(n, max_views_per_step=cap, seed=7, regions=regions)
    batches = [sched.batch(t) for t in range(1000)]
    pattern = [RANDOM_MULTIVIEW] * 2 + [SINGLE] * 3 + [RELATED_MULTIVIEW] * 2 + [SINGLE] * 3
    assert [b.kind for b in batches] == pattern * 100
    assert Counter(b.kind for b in batches) == {RANDOM_MULTIVIEW: 200, SINGLE: 600, RELATED_MULTIVIEW: 200}
    for b in batches:
        assert 1 <= len(b.views) <= cap and len(set(b.views)) == len(b.views)
        assert all(0 <= v < n for v in b.views)
    singles = [b.views[0] for b in batches if b.kind == SINGLE]
    for e in range(len(singles) // n):  # each epoch of single steps is a permutation
        assert sorted(singles[e * n : (e + 1) * n]) == list(range(n))
    assert singles[:n] != singles[n : 2 * n]  # reshuffled per epoch
    randoms = [b.views for b in batches if b.kind == RANDOM_MULTIVIEW]
    assert set().union(*randoms[:4]) == set(range(n))  # ceil(13 / 4) batches cover all
    related = [b for b in batches if b.kind == RELATED_MULTIVIEW]
    assert [b.region for b in related[:4]] == [0, 1, 0, 1]
    assert all(set(b.views) <= set(regions[b.region]) for b in related)
    assert set(related[0].views) | set(related[2].views) == set(regions[0])  # window rotates
    assert related[1].views == [5, 6]


def test_schedule_fallback_determinism_and_cap_changes():
    a = ViewSchedule(10, max_views_per_step=3, seed=1)
    assert all(a.batch(t).kind == RANDOM_MULTIVIEW for t in (0, 1, 5, 6, 15))
    assert [a.batch(t) for t in range(50)] == [ViewSchedule(10, 3, seed=1).batch(t) for t in range(50)]
    assert [a.batch(t).views for t in range(50)] != [ViewSchedule(10, 3, seed=2).batch(t).views for t in range(50)]
    a.set_max_views(1)
    assert all(len(a.batch(t).views) == 1 for t in range(50))
    a.set_regions([[], [3, 4]])
    # The region index is the prompt's, even when an earlier prompt has no views.
    assert a.batch(5).kind == RELATED_MULTIVIEW and a.batch(5).region == 1 and a.batch(5).views == [3]
    # A region's own cap: its related steps hold that many views, and its window moves by
    # that many a visit; the other regions keep the schedule's cap.
    b = ViewSchedule(10, max_views_per_step=2, seed=1)
    b.set_regions([[0, 1, 2, 3], [4, 5, 6]], views_per_step=[None, 1])
    related = [b.batch(t) for t in range(200) if b.batch(t).kind == RELATED_MULTIVIEW]
    assert [r.views for r in related if r.region == 0][:2] == [[0, 1], [2, 3]]
    assert [r.views for r in related if r.region == 1][:4] == [[4], [5], [6], [4]]
    with pytest.raises(ValueError):
        b.set_regions([[0, 1]], views_per_step=[0])
    with pytest.raises(ValueError):
        b.set_regions([[0, 1]], views_per_step=[1, 1])
    single = ViewSchedule(5, ratio=(0, 1, 0, 0))
    assert all(single.batch(t).kind == SINGLE for t in range(20))
    with pytest.raises(ValueError):
        ViewSchedule(5, regions=[[7]])
