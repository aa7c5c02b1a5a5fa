// Forward pass of the CPU rasterizer: tile binning, depth sort, front-to-back compositing.
//
// Inside a tile the loops run Gaussian by Gaussian (front to back) and, for each one, over
// the tile rows its box touches, with the 16 pixels of a row as one vector.
#include <omp.h>

#include <algorithm>
#include <cmath>

#include "rasterize.h"
#include "simd_clones.h"

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

PROMPTGS_SIMD_CLONES
void forward_tile(const Splat* __restrict splats, const float* __restrict colors, int64_t D,
                  const int32_t* __restrict ids, int start, int end, int x0, int y0, int rows, int cols,
                  const float* __restrict background, int W, float* __restrict acc, float* __restrict out_colors,
                  float* __restrict out_alphas, int32_t* __restrict last_ids) {
    alignas(64) float T[kTilePixels];
    alignas(64) int32_t active[kTilePixels];  // -1 while the pixel still composites, else 0
    alignas(64) int32_t last[kTilePixels];
    RowF px;
    for (int l = 0; l < kTile; ++l) px[l] = static_cast<float>(x0 + l) + 0.5f;
    std::fill(acc, acc + D * kTilePixels, 0.f);
    for (int p = 0; p < kTilePixels; ++p) {
        T[p] = 1.f;
        last[p] = -1;
        active[p] = ((p / kTile) < rows && (p % kTile) < cols) ? -1 : 0;
    }
    int alive = rows * cols;
    for (int i = start; i < end && alive > 0; ++i) {
        const int32_t g = ids[i];
        const Splat s = splats[g];
        const int r0 = std::max(0, static_cast<int>(std::floor(s.y - s.ry - 0.5f)) - y0);
        const int r1 = std::min(rows - 1, static_cast<int>(std::ceil(s.y + s.ry)) - y0);
        const float* cg = colors + static_cast<int64_t>(g) * D;
        const RowF dx = s.x - px;
        const RowF adx = 0.5f * s.a * dx;
        for (int r = r0; r <= r1; ++r) {
            const float dy = s.y - (static_cast<float>(y0 + r) + 0.5f);
            const RowF sigma = (adx + s.b * dy) * dx + 0.5f * s.c * dy * dy;
            const RowF alpha = min_f(s.opacity * exp_row(-sigma), kMaxAlpha);
            const RowF t = load_f(T + r * kTile);
            const RowF nt = t - t * alpha;
            const RowI ok = (sigma >= 0.f) & (alpha >= kAlphaThreshold) & load_i(active + r * kTile);
            const RowI use = ok & (nt > kTransmittanceEps);
            const RowI stop = ok & (nt <= kTransmittanceEps);
            // lane counts of composited (low half) and finished (high half) pixels
            const int32_t counts = hsum_i((use & 1) | (stop & 0x10000));
            if (counts == 0) continue;
            alive -= counts >> 16;
            store_f(T + r * kTile, select(use, nt, t));
            store_i(last + r * kTile, use ? splat_i(i) : load_i(last + r * kTile));
            store_i(active + r * kTile, load_i(active + r * kTile) & ~stop);
            if ((counts & 0xffff) == 0) continue;
            const RowF w = select(use, alpha * t, splat_f(0.f));
            for (int64_t k = 0; k < D; ++k) {
                float* A = acc + k * kTilePixels + r * kTile;
                store_f(A, load_f(A) + cg[k] * w);
            }
        }
    }
    for (int r = 0; r < rows; ++r) {
        for (int l = 0; l < cols; ++l) {
            const int p = r * kTile + l;
            const int64_t pix = static_cast<int64_t>(y0 + r) * W + (x0 + l);
            for (int64_t k = 0; k < D; ++k)
                out_colors[pix * D + k] = acc[k * kTilePixels + p] + (background ? T[p] * background[k] : 0.f);
            out_alphas[pix] = 1.f - T[p];
            last_ids[pix] = last[p];
        }
    }
}

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
    const int32_t* ids = bins.ids.data();
    const int32_t* offs = bins.offsets.data();
#pragma omp parallel
    {
        std::vector<float> acc(static_cast<size_t>(in.d) * kTilePixels);
#pragma omp for schedule(dynamic, 1)
        for (int tile = 0; tile < n_tiles; ++tile) {
            const int x0 = (tile % bins.tiles_x) * kTile;
            const int y0 = (tile / bins.tiles_x) * kTile;
            forward_tile(splats.data(), colors.data(), in.d, ids, offs[tile], offs[tile + 1], x0, y0,
                         std::min(kTile, in.height - y0), std::min(kTile, in.width - x0), in.background,
                         in.width, acc.data(), out_colors, out_alphas, last_ids);
        }
    }
}

}  // namespace promptgs
