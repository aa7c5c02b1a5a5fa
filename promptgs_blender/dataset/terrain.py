"""Procedural mountain terrain as a numpy heightfield (no bpy).

The terrain is a valley ringed by ridged peaks: a bowl that rises towards the border,
ridged fractal noise whose amplitude grows with the distance from the centre, and gentle
hills on the valley floor. Vertex colours follow slope and height (grass, dry grass,
rock, snow), with scorched ground around flames.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


def _smoothstep(e0: float, e1: float, x: np.ndarray) -> np.ndarray:
    t = np.clip((x - e0) / (e1 - e0), 0.0, 1.0)
    return t * t * (3.0 - 2.0 * t)


def _lattice_noise(rng: np.random.Generator, n: int, cells: int) -> np.ndarray:
    """Value noise in [0, 1] on an n×n grid from a random (cells+1)² lattice, smoothly interpolated."""
    lattice = rng.random((cells + 1, cells + 1))
    t = np.linspace(0.0, cells, n, endpoint=False) + cells / (2.0 * n)
    i0 = np.floor(t).astype(int)
    f = t - i0
    f = f * f * (3.0 - 2.0 * f)
    i1 = np.minimum(i0 + 1, cells)
    a = lattice[np.ix_(i0, i0)]
    b = lattice[np.ix_(i0, i1)]
    c = lattice[np.ix_(i1, i0)]
    d = lattice[np.ix_(i1, i1)]
    fy = f[:, None]
    fx = f[None, :]
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def _fractal(rng: np.random.Generator, n: int, base_cells: int, octaves: int, ridged: bool) -> np.ndarray:
    total = np.zeros((n, n))
    amp, norm, cells = 1.0, 0.0, base_cells
    for _ in range(octaves):
        v = _lattice_noise(rng, n, cells)
        if ridged:
            v = 1.0 - np.abs(2.0 * v - 1.0)
            v = v * v
        total += amp * v
        norm += amp
        amp *= 0.5
        cells *= 2
    return total / norm


@dataclass
class Terrain:
    """A square heightfield centred on the origin; row index = y, column index = x."""

    size: float  # edge length in metres (world units)
    heights: np.ndarray  # [n, n] float64, z of each grid vertex

    @property
    def n(self) -> int:
        return int(self.heights.shape[0])

    @property
    def coords(self) -> np.ndarray:
        """The 1D grid coordinates shared by x (columns) and y (rows)."""
        return np.linspace(-self.size / 2.0, self.size / 2.0, self.n)

    def height_at(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear terrain height at world (x, y); clamps outside the grid."""
        x = np.asarray(x, dtype=np.float64)
        y = np.asarray(y, dtype=np.float64)
        step = self.size / (self.n - 1)
        gx = np.clip((x + self.size / 2.0) / step, 0.0, self.n - 1.000001)
        gy = np.clip((y + self.size / 2.0) / step, 0.0, self.n - 1.000001)
        ix, iy = np.floor(gx).astype(int), np.floor(gy).astype(int)
        fx, fy = gx - ix, gy - iy
        h = self.heights
        top = h[iy, ix] * (1 - fx) + h[iy, ix + 1] * fx
        bottom = h[iy + 1, ix] * (1 - fx) + h[iy + 1, ix + 1] * fx
        return top * (1 - fy) + bottom * fy

    def normals_z(self) -> np.ndarray:
        """z component of the unit surface normal at every vertex (1 = flat, 0 = vertical)."""
        step = self.size / (self.n - 1)
        gy, gx = np.gradient(self.heights, step)
        return 1.0 / np.sqrt(1.0 + gx * gx + gy * gy)

    def vertices(self) -> np.ndarray:
        """[n*n, 3] vertex positions, row-major (y outer, x inner)."""
        c = self.coords
        xx, yy = np.meshgrid(c, c)
        return np.stack([xx, yy, self.heights], axis=-1).reshape(-1, 3)

    def quads(self) -> np.ndarray:
        """[(n-1)², 4] vertex indices of the grid quads, counter-clockwise seen from above."""
        idx = np.arange(self.n * self.n).reshape(self.n, self.n)
        return np.stack([idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]], axis=-1).reshape(-1, 4)


def make_terrain(
    rng: np.random.Generator,
    size: float,
    resolution: int,
    rim_height: float,
    ridge_octaves: int = 6,
    ridge_amplitude: float = 1.0,
    hill_octaves: int = 4,
) -> Terrain:
    """A valley ringed by ridged peaks, ``rim_height`` metres high at the border on average.

    ``ridge_octaves`` / ``hill_octaves``: octaves of the ridged and the rolling noise
    (fewer: smoother ground); ``ridge_amplitude`` scales the ridges (the defaults give the
    mountain of the ``tiny``/``small``/``paper`` presets)."""
    n = resolution
    c = np.linspace(-size / 2.0, size / 2.0, n)
    xx, yy = np.meshgrid(c, c)
    r = np.sqrt(xx * xx + yy * yy) / (size / 2.0)  # 0 at the centre, 1 at the middle of an edge
    angle = np.arctan2(yy, xx)
    phase = rng.uniform(0, 2 * np.pi, size=3)
    wobble = 0.08 * np.sin(3 * angle + phase[0]) + 0.05 * np.sin(5 * angle + phase[1])
    bowl = rim_height * _smoothstep(0.3 + wobble, 1.0 + wobble, r)
    ridges = _fractal(rng, n, base_cells=4, octaves=ridge_octaves, ridged=True)
    hills = _fractal(rng, n, base_cells=3, octaves=hill_octaves, ridged=False)
    ridge_amp = ridge_amplitude * rim_height * (0.22 + 0.7 * _smoothstep(0.2, 0.9, r))
    heights = bowl + ridge_amp * ridges + 0.15 * rim_height * (hills - 0.5)
    heights -= heights[n // 2, n // 2]
    return Terrain(size=size, heights=heights)


GRASS = np.array([0.10, 0.19, 0.05])
DRY_GRASS = np.array([0.26, 0.23, 0.10])
ROCK = np.array([0.16, 0.145, 0.13])
DARK_ROCK = np.array([0.07, 0.065, 0.06])
SNOW = np.array([0.80, 0.82, 0.86])
SCORCHED = np.array([0.035, 0.03, 0.025])


def terrain_colors(
    rng: np.random.Generator,
    terrain: Terrain,
    snow_line: float,
    scorch_centres: list[tuple[float, float]],
    scorch_radius: float,
    colour_jitter: float = 0.2,
) -> np.ndarray:
    """[n*n, 3] linear RGB vertex colours by slope and height, with per-vertex brightness
    variation of ±``colour_jitter``."""
    n = terrain.n
    nz = terrain.normals_z()
    h = terrain.heights
    patch = _fractal(rng, n, base_cells=12, octaves=4, ridged=False)
    grass = GRASS[None, None] * (1 - patch[..., None]) + DRY_GRASS[None, None] * patch[..., None]
    strata = 0.5 + 0.5 * np.sin(h * 1.7 + 3.0 * patch)
    rock = ROCK[None, None] * (1 - strata[..., None] * 0.5) + DARK_ROCK[None, None] * (strata[..., None] * 0.5)
    steep = _smoothstep(0.88, 0.72, nz)  # 0 on flat ground, 1 on steep slopes
    col = grass * (1 - steep[..., None]) + rock * steep[..., None]
    snow_noise = (patch - 0.5) * 0.25 * snow_line
    snow = _smoothstep(snow_line - 2.0, snow_line + 2.0, h + snow_noise) * _smoothstep(0.45, 0.7, nz)
    col = col * (1 - snow[..., None]) + SNOW[None, None] * snow[..., None]
    c = terrain.coords
    xx, yy = np.meshgrid(c, c)
    for cx, cy in scorch_centres:
        d = np.sqrt((xx - cx) ** 2 + (yy - cy) ** 2)
        burnt = _smoothstep(scorch_radius, 0.4 * scorch_radius, d + 0.6 * scorch_radius * (patch - 0.5))
        col = col * (1 - burnt[..., None]) + SCORCHED[None, None] * burnt[..., None]
    jitter = rng.uniform(0.8, 1.2, size=(n, n, 1))  # drawn at every setting: the same random stream
    col *= jitter if colour_jitter == 0.2 else 1.0 + (jitter - 1.0) * (colour_jitter / 0.2)
    return np.clip(col, 0.0, 1.0).reshape(-1, 3)
