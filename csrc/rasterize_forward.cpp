// Forward pass of the CPU rasterizer: depth sort, tile binning (exact ellipse/tile test),
// depth-ranked copies of the Gaussian data, then the per-tile compositing kernels of
// tile_kernels.inc in parallel over tiles.
#include <omp.h>

#include <algorithm>
#include <cmath>

#include "rasterize.h"

namespace promptgs {

namespace {

// Order-preserving map of a float to uint32 (so depths sort as integers).
inline uint32_t float_key(float f) {
    uint32_t u;
    std::memcpy(&u, &f, sizeof(u));
    return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}

struct TileRect {
    int32_t x0, y0, x1, y1;  // tiles [x0, x1) x [y0, y1)
};

}  // namespace

void gather_sorted(const RasterInputs& in, const TileBins& bins, std::vector<Splat>& splats,
                   std::vector<float>& colors) {
    const int64_t M = static_cast<int64_t>(bins.order.size());
    const int64_t D = in.d;
    splats.resize(static_cast<size_t>(M));
    colors.resize(static_cast<size_t>(M * D));
#pragma omp parallel for schedule(static)
    for (int64_t j = 0; j < M; ++j) {
        const int64_t i = bins.order[j];
        Splat s;
        s.x = in.means2d[2 * i];
        s.y = in.means2d[2 * i + 1];
        s.a = in.conics[3 * i];
        s.b = in.conics[3 * i + 1];
        s.c = in.conics[3 * i + 2];
        s.opacity = in.opacities[i];
        float ex, ey;
        s.ry = ellipse_extent(s.a, s.b, s.c, sigma_cutoff(s.opacity), ex, ey) ? ey + 1e-3f
                                                                              : static_cast<float>(in.radii[2 * i + 1]);
        s.pad = 0.f;
        splats[j] = s;
        for (int64_t k = 0; k < D; ++k) colors[j * D + k] = in.colors[i * D + k];
    }
}

namespace {

// Minimum of q(dx, dy) = 0.5 a dx^2 + b dx dy + 0.5 c dy^2 (a, c > 0) over a rectangle.
inline float min_over_rect(float a, float b, float c, float dx0, float dx1, float dy0, float dy1) {
    if (dx0 <= 0.f && dx1 >= 0.f && dy0 <= 0.f && dy1 >= 0.f) return 0.f;
    auto q = [&](float dx, float dy) { return 0.5f * a * dx * dx + b * dx * dy + 0.5f * c * dy * dy; };
    float best = q(dx0, std::clamp(-b * dx0 / c, dy0, dy1));
    best = std::min(best, q(dx1, std::clamp(-b * dx1 / c, dy0, dy1)));
    best = std::min(best, q(std::clamp(-b * dy0 / a, dx0, dx1), dy0));
    best = std::min(best, q(std::clamp(-b * dy1 / a, dx0, dx1), dy1));
    return best;
}

// LSD radix sort of (key, value) pairs by key, stable (3 passes of 11 bits).
void radix_sort(std::vector<uint32_t>& keys, std::vector<int32_t>& values) {
    const size_t n = keys.size();
    std::vector<uint32_t> k2(n);
    std::vector<int32_t> v2(n);
    for (int shift = 0; shift < 32; shift += 11) {
        std::vector<uint32_t> count(2049, 0);
        for (size_t i = 0; i < n; ++i) count[((keys[i] >> shift) & 2047u) + 1]++;
        for (int b = 0; b < 2048; ++b) count[b + 1] += count[b];
        for (size_t i = 0; i < n; ++i) {
            const uint32_t dst = count[(keys[i] >> shift) & 2047u]++;
            k2[dst] = keys[i];
            v2[dst] = values[i];
        }
        keys.swap(k2);
        values.swap(v2);
    }
}

}  // namespace

TileBins bin_gaussians(const RasterInputs& in, const float* depths) {
    TileBins bins;
    bins.tiles_x = (in.width + kTile - 1) / kTile;
    bins.tiles_y = (in.height + kTile - 1) / kTile;
    const int n_tiles = bins.tiles_x * bins.tiles_y;
    const int32_t* radii = in.radii;
    const float* m2 = in.means2d;
    const float* cn = in.conics;

    // Visible Gaussians sorted front to back (stable, so ties keep index order). Filling
    // the tile lists in this order leaves every list sorted without a per-tile sort.
    std::vector<uint32_t> keys;
    std::vector<int32_t> order;
    keys.reserve(static_cast<size_t>(in.n));
    order.reserve(static_cast<size_t>(in.n));
    for (int64_t i = 0; i < in.n; ++i) {
        if (radii[2 * i] > 0 && radii[2 * i + 1] > 0) {
            keys.push_back(float_key(depths[i]));
            order.push_back(static_cast<int32_t>(i));
        }
    }
    radix_sort(keys, order);
    const int64_t m = static_cast<int64_t>(order.size());

    // Tile range of each Gaussian: the pixels whose centres lie in the box of the ellipse
    // where its alpha can reach 1/255 (tighter than the integer radii), clipped to the image.
    std::vector<TileRect> rects(static_cast<size_t>(m));
#pragma omp parallel for schedule(static)
    for (int64_t j = 0; j < m; ++j) {
        const int64_t i = order[j];
        const float x = m2[2 * i], y = m2[2 * i + 1];
        float ex, ey;
        if (!ellipse_extent(cn[3 * i], cn[3 * i + 1], cn[3 * i + 2], sigma_cutoff(in.opacities[i]), ex, ey)) {
            ex = static_cast<float>(radii[2 * i]);
            ey = static_cast<float>(radii[2 * i + 1]);
        }
        const int px0 = std::max(0, static_cast<int>(std::ceil(std::max(x - ex - 0.5f, -1.f))));
        const int px1 = std::min(in.width - 1, static_cast<int>(std::floor(std::min(x + ex - 0.5f, 1e9f))));
        const int py0 = std::max(0, static_cast<int>(std::ceil(std::max(y - ey - 0.5f, -1.f))));
        const int py1 = std::min(in.height - 1, static_cast<int>(std::floor(std::min(y + ey - 0.5f, 1e9f))));
        TileRect r;
        if (px0 > px1 || py0 > py1) {
            r.x0 = r.x1 = r.y0 = r.y1 = 0;
        } else {
            r.x0 = px0 / kTile;
            r.x1 = px1 / kTile + 1;
            r.y0 = py0 / kTile;
            r.y1 = py1 / kTile + 1;
        }
        rects[j] = r;
    }

    // Whether Gaussian j's ellipse reaches tile (tx, ty); only tested when its box spans
    // several tiles (a diagonal or elongated ellipse misses some of them).
    auto hits = [&](int64_t j, const TileRect& r, int tx, int ty) {
        if (r.x1 - r.x0 == 1 && r.y1 - r.y0 == 1) return true;
        const int64_t i = order[j];
        const float x = m2[2 * i], y = m2[2 * i + 1];
        const float X0 = tx * kTile + 0.5f, X1 = std::min(tx * kTile + kTile, in.width) - 0.5f;
        const float Y0 = ty * kTile + 0.5f, Y1 = std::min(ty * kTile + kTile, in.height) - 0.5f;
        return min_over_rect(cn[3 * i], cn[3 * i + 1], cn[3 * i + 2], X0 - x, X1 - x, Y0 - y, Y1 - y) <=
               sigma_cutoff(in.opacities[i]);
    };

    // Count and fill in parallel: each thread takes a contiguous slice of the depth order,
    // and its entries go after those of the threads before it in every tile.
    const int n_threads = omp_get_max_threads();
    std::vector<std::vector<int32_t>> counts(n_threads, std::vector<int32_t>(n_tiles, 0));
    bins.offsets.assign(n_tiles + 1, 0);
#pragma omp parallel num_threads(n_threads)
    {
        const int tid = omp_get_thread_num();
        const int nt = omp_get_num_threads();
        const int64_t j0 = m * tid / nt, j1 = m * (tid + 1) / nt;
        std::vector<int32_t>& cnt = counts[tid];
        for (int64_t j = j0; j < j1; ++j) {
            const TileRect& r = rects[j];
            for (int ty = r.y0; ty < r.y1; ++ty)
                for (int tx = r.x0; tx < r.x1; ++tx)
                    if (hits(j, r, tx, ty)) cnt[ty * bins.tiles_x + tx]++;
        }
#pragma omp barrier
#pragma omp single
        {
            int32_t total = 0;
            for (int t = 0; t < n_tiles; ++t) {
                bins.offsets[t] = total;
                for (int k = 0; k < nt; ++k) {
                    const int32_t c = counts[k][t];
                    counts[k][t] = total;  // becomes thread k's write cursor in tile t
                    total += c;
                }
            }
            bins.offsets[n_tiles] = total;
            bins.ids.resize(static_cast<size_t>(total));
        }
        for (int64_t j = j0; j < j1; ++j) {
            const TileRect& r = rects[j];
            for (int ty = r.y0; ty < r.y1; ++ty)
                for (int tx = r.x0; tx < r.x1; ++tx)
                    if (hits(j, r, tx, ty)) bins.ids[cnt[ty * bins.tiles_x + tx]++] = static_cast<int32_t>(j);
        }
    }
    bins.order = std::move(order);
    return bins;
}

void rasterize_forward(const RasterInputs& in, const TileBins& bins, float* out_colors, float* out_alphas,
                       int32_t* last_ids, uint8_t* contrib) {
    std::vector<Splat> splats;
    std::vector<float> colors;
    gather_sorted(in, bins, splats, colors);
    const int n_tiles = bins.tiles_x * bins.tiles_y;
    TileArgs args;
    args.ids = bins.ids.data();
    args.d = in.d;
    args.width = in.width;
    args.height = in.height;
    args.background = in.background;
    args.out_colors = out_colors;
    args.out_alphas = out_alphas;
    args.out_last = last_ids;
    args.out_contrib = contrib;
    const TileKernels::Forward forward = tile_kernels().forward[kernel_for(in.d)];
#pragma omp parallel
    {
        std::vector<float> acc(static_cast<size_t>(in.d) * kTilePixels);
#pragma omp for schedule(dynamic, 1)
        for (int tile = 0; tile < n_tiles; ++tile) {
            forward(args, splats.data(), colors.data(), bins.offsets[tile], bins.offsets[tile + 1],
                            (tile % bins.tiles_x) * kTile, (tile / bins.tiles_x) * kTile, acc.data());
        }
    }
}

}  // namespace promptgs
