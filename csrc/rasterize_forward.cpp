// Forward pass of the CPU rasterizer: tile binning, depth sort, front-to-back compositing.
//
// Inside a tile the loops run Gaussian by Gaussian (front to back) and, for each one, over
// the tile rows its box touches, with the 16 pixels of a row as one vector.
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
        s.ry = static_cast<float>(in.radii[2 * i + 1]);
        s.pad = 0.f;
        splats[j] = s;
        for (int64_t k = 0; k < D; ++k) colors[j * D + k] = in.colors[i * D + k];
    }
}

TileBins bin_gaussians(const RasterInputs& in, const float* depths) {
    TileBins bins;
    bins.tiles_x = (in.width + kTile - 1) / kTile;
    bins.tiles_y = (in.height + kTile - 1) / kTile;
    const int n_tiles = bins.tiles_x * bins.tiles_y;
    const int32_t* radii = in.radii;
    const float* m2 = in.means2d;

    // Visible Gaussians as (depth key, index), sorted front to back. Filling the tile
    // lists in this order leaves every list sorted without a per-tile sort.
    std::vector<uint64_t> keys;
    keys.reserve(static_cast<size_t>(in.n));
    for (int64_t i = 0; i < in.n; ++i) {
        if (radii[2 * i] > 0 && radii[2 * i + 1] > 0) {
            keys.push_back((static_cast<uint64_t>(float_key(depths[i])) << 32) | static_cast<uint32_t>(i));
        }
    }
    std::sort(keys.begin(), keys.end());

    const size_t m = keys.size();
    bins.order.resize(m);
    std::vector<TileRect> rects(m);
    std::vector<int32_t> counts(n_tiles + 1, 0);
    for (size_t j = 0; j < m; ++j) {
        const int64_t i = static_cast<int64_t>(keys[j] & 0xffffffffu);
        bins.order[j] = static_cast<int32_t>(i);
        const float x = m2[2 * i], y = m2[2 * i + 1];
        const float rx = static_cast<float>(radii[2 * i]), ry = static_cast<float>(radii[2 * i + 1]);
        TileRect r;
        r.x0 = std::clamp(static_cast<int>(std::floor((x - rx) / kTile)), 0, bins.tiles_x);
        r.x1 = std::clamp(static_cast<int>(std::ceil((x + rx) / kTile)), 0, bins.tiles_x);
        r.y0 = std::clamp(static_cast<int>(std::floor((y - ry) / kTile)), 0, bins.tiles_y);
        r.y1 = std::clamp(static_cast<int>(std::ceil((y + ry) / kTile)), 0, bins.tiles_y);
        rects[j] = r;
        for (int ty = r.y0; ty < r.y1; ++ty)
            for (int tx = r.x0; tx < r.x1; ++tx) counts[ty * bins.tiles_x + tx + 1]++;
    }
    bins.offsets.assign(n_tiles + 1, 0);
    for (int t = 0; t < n_tiles; ++t) bins.offsets[t + 1] = bins.offsets[t] + counts[t + 1];
    bins.ids.resize(static_cast<size_t>(bins.offsets[n_tiles]));
    std::vector<int32_t> cursor(bins.offsets.begin(), bins.offsets.end() - 1);
    for (size_t j = 0; j < m; ++j) {
        const TileRect& r = rects[j];
        for (int ty = r.y0; ty < r.y1; ++ty)
            for (int tx = r.x0; tx < r.x1; ++tx) bins.ids[cursor[ty * bins.tiles_x + tx]++] = static_cast<int32_t>(j);
    }
    return bins;
}

void rasterize_forward(const RasterInputs& in, const TileBins& bins, float* out_colors, float* out_alphas,
                       int32_t* last_ids) {
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
    const TileKernels& kernels = tile_kernels();
#pragma omp parallel
    {
        std::vector<float> acc(static_cast<size_t>(in.d) * kTilePixels);
#pragma omp for schedule(dynamic, 1)
        for (int tile = 0; tile < n_tiles; ++tile) {
            kernels.forward(args, splats.data(), colors.data(), bins.offsets[tile], bins.offsets[tile + 1],
                            (tile % bins.tiles_x) * kTile, (tile / bins.tiles_x) * kTile, acc.data());
        }
    }
}

}  // namespace promptgs
