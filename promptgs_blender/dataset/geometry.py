"""Mesh geometry of drones and flames as numpy arrays (no bpy)."""

from __future__ import annotations

import math

import numpy as np

Mesh = tuple[np.ndarray, list[list[int]]]  # vertices [V, 3], faces as index lists


def box(lo: tuple[float, float, float], hi: tuple[float, float, float], yaw: float = 0.0) -> Mesh:
    """An axis-aligned box between ``lo`` and ``hi``, turned by ``yaw`` about z around the origin."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    v = np.array([[x0, y0, z0], [x1, y0, z0], [x1, y1, z0], [x0, y1, z0],
                  [x0, y0, z1], [x1, y0, z1], [x1, y1, z1], [x0, y1, z1]], dtype=np.float64)
    c, s = math.cos(yaw), math.sin(yaw)
    v = v @ np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
    f = [[0, 3, 2, 1], [4, 5, 6, 7], [0, 1, 5, 4], [1, 2, 6, 5], [2, 3, 7, 6], [3, 0, 4, 7]]
    return v, f


def cylinder(centre: tuple[float, float, float], radius: float, height: float, segments: int = 12) -> Mesh:
    """A closed vertical cylinder standing on ``centre``."""
    a = np.linspace(0, 2 * np.pi, segments, endpoint=False)
    ring = np.stack([np.cos(a) * radius, np.sin(a) * radius, np.zeros_like(a)], axis=1) + np.array(centre)
    v = np.concatenate([ring, ring + np.array([0, 0, height])])
    f = [[i, (i + 1) % segments, segments + (i + 1) % segments, segments + i] for i in range(segments)]
    f.append(list(range(segments - 1, -1, -1)))
    f.append(list(range(segments, 2 * segments)))
    return v, f


def merge(parts: list[Mesh]) -> Mesh:
    verts, faces, offset = [], [], 0
    for v, f in parts:
        verts.append(v)
        faces.extend([[i + offset for i in face] for face in f])
        offset += len(v)
    return np.concatenate(verts), faces


def drone_parts() -> dict[str, Mesh]:
    """A quadcopter of size 1 across (rotor rim to rotor rim), origin at the body centre.

    Its bounding box is ``layout.DRONE_BOX_MIN .. DRONE_BOX_MAX``. Returns the frame (body,
    arms, skids) and the rotor discs as separate meshes for two materials.
    """
    frame = [box((-0.2, -0.2, -0.09), (0.2, 0.2, 0.07))]  # body
    frame.append(box((-0.08, -0.08, -0.16), (0.08, 0.08, -0.09)))  # camera gimbal
    for yaw in (math.pi / 4, -math.pi / 4):
        frame.append(box((-0.47, -0.05, -0.01), (0.47, 0.05, 0.05), yaw))  # arms
    for side in (-1, 1):
        frame.append(box((-0.2, side * 0.14 - 0.02, -0.2), (0.2, side * 0.14 + 0.02, -0.17)))  # skids
        frame.append(box((-0.02, side * 0.14 - 0.02, -0.17), (0.02, side * 0.14 + 0.02, -0.09)))
    rotors = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            rotors.append(cylinder((sx * 0.31, sy * 0.31, 0.05), 0.19, 0.04))
    return {"frame": merge(frame), "rotors": merge(rotors)}


FLAME_COLOURS = np.array([[1.0, 0.6, 0.1], [1.0, 0.28, 0.02], [0.8, 0.09, 0.005], [0.35, 0.02, 0.002]])


def _flame_colour(t: np.ndarray, warmth: float) -> np.ndarray:
    """Colour along a tongue, t = 0 at the base to 1 at the tip; ``warmth`` shifts it to red."""
    x = np.clip(t * 0.8 + warmth * 0.35, 0.0, 0.999) * (len(FLAME_COLOURS) - 1)
    i = np.floor(x).astype(int)
    f = (x - i)[:, None]
    return FLAME_COLOURS[i] * (1 - f) + FLAME_COLOURS[i + 1] * f


def flame_mesh(seed: int, height: float, radius: float, n_tongues: int) -> tuple[np.ndarray, list[list[int]], np.ndarray]:
    """Flame tongues around the origin: vertices, faces and RGBA vertex colours.

    Each tongue is a wobbly, leaning cone; colour runs from a pale yellow core at the base
    to dark red at the tip and alpha fades towards the tip (used as emission vs transparency).
    """
    rng = np.random.default_rng(seed)
    rings, seg = 10, 10
    verts, faces, cols = [], [], []
    offset = 0
    for k in range(n_tongues):
        core = k == 0
        a = rng.uniform(0, 2 * np.pi)
        d = 0.0 if core else radius * 0.6 * math.sqrt(rng.uniform(0.1, 1.0))
        base = np.array([d * math.cos(a), d * math.sin(a), -0.05 * height])
        h = height * (1.0 if core else rng.uniform(0.45, 0.9))
        r0 = radius * (0.55 if core else rng.uniform(0.25, 0.45))
        lean = rng.normal(size=2) * 0.15 * h
        phase = rng.uniform(0, 2 * np.pi, size=2)
        warmth = 0.0 if core else rng.uniform(0.2, 0.8)
        ang = np.linspace(0, 2 * np.pi, seg, endpoint=False)
        for j in range(rings):
            t = j / rings
            r = r0 * (1 - t) ** 0.75 * (1 + 0.25 * math.sin(3 * math.pi * t + phase[0]))
            wob = 1 + 0.18 * np.sin(ang * 3 + phase[1] + 5 * t) + rng.normal(size=seg) * 0.06
            ring = np.stack([np.cos(ang) * r * wob, np.sin(ang) * r * wob, np.full(seg, h * t)], axis=1)
            ring[:, :2] += lean * t * t
            verts.append(ring + base)
            c = _flame_colour(np.full(seg, t), warmth)
            cols.append(np.concatenate([c, np.full((seg, 1), 1.0 - t**1.6)], axis=1))
        tip = np.array([[lean[0], lean[1], h]]) + base
        verts.append(tip)
        cols.append(np.concatenate([_flame_colour(np.array([1.0]), warmth), [[0.0]]], axis=1))
        for j in range(rings - 1):
            for i in range(seg):
                a0 = offset + j * seg + i
                a1 = offset + j * seg + (i + 1) % seg
                faces.append([a0, a1, a1 + seg, a0 + seg])
        top = offset + rings * seg
        for i in range(seg):
            faces.append([offset + (rings - 1) * seg + i, offset + (rings - 1) * seg + (i + 1) % seg, top])
        faces.append(list(range(offset + seg - 1, offset - 1, -1)))
        offset += rings * seg + 1
    return np.concatenate(verts), faces, np.concatenate(cols)
