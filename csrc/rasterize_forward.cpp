// Forward pass of the CPU rasterizer: tile binning, depth sort, front-to-back compositing.
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
    int16_t x0, y0, x1, y1;  // tiles [x0, x1) x [y0, y1)
};

}  // namespace

TileBins bin_gaussians(const float* means2d, const int32_t* radii, const float* depths, int64_t n,
                       int width, int height) {
    TileBins bins;
    bins.tiles_x = (width + kTile - 1) / kTile;
    bins.tiles_y = (height + kTile - 1) / kTile;
    const int n_tiles = bins.tiles_x * bins.tiles_y;

    // Visible Gaussians as (depth key, index), sorted front to back. Filling the tile
    // lists in this order leaves every list sorted without a per-tile sort.
    std::vector<uint64_t> keys;
    keys.reserve(static_cast<size_t>(n));
    for (int64_t i = 0; i < n; ++i) {
        if (radii[2 * i] > 0 && radii[2 * i + 1] > 0) {
            keys.push_back((static_cast<uint64_t>(float_key(depths[i])) << 32) |
                           static_cast<uint32_t>(i));
        }
    }
    std::sort(keys.begin(), keys.end());

    const size_t m = keys.size();
    std::vector<TileRect> rects(m);
    std::vector<int32_t> counts(n_tiles + 1, 0);
    for (size_t j = 0; j < m; ++j) {
        const int64_t i = static_cast<int64_t>(keys[j] & 0xffffffffu);
        const float x = means2d[2 * i], y = means2d[2 * i + 1];
        const float rx = static_cast<float>(radii[2 * i]), ry = static_cast<float>(radii[2 * i + 1]);
        TileRect r;
        r.x0 = static_cast<int16_t>(std::clamp(static_cast<int>(std::floor((x - rx) / kTile)), 0, bins.tiles_x));
        r.x1 = static_cast<int16_t>(std::clamp(static_cast<int>(std::ceil((x + rx) / kTile)), 0, bins.tiles_x));
        r.y0 = static_cast<int16_t>(std::clamp(static_cast<int>(std::floor((y - ry) / kTile)), 0, bins.tiles_y));
        r.y1 = static_cast<int16_t>(std::clamp(static_cast<int>(std::ceil((y + ry) / kTile)), 0, bins.tiles_y));
        rects[j] = r;
        for (int ty = r.y0; ty < r.y1; ++ty)
            for (int tx = r.x0; tx < r.x1; ++tx) counts[ty * bins.tiles_x + tx + 1]++;
    }
    bins.offsets.assign(n_tiles + 1, 0);
    for (int t = 0; t < n_tiles; ++t) bins.offsets[t + 1] = bins.offsets[t] + counts[t + 1];
    bins.ids.resize(static_cast<size_t>(bins.offsets[n_tiles]));
    std::vector<int32_t> cursor(bins.offsets.begin(), bins.offsets.end() - 1);
    for (size_t j = 0; j < m; ++j) {
        const int32_t i = static_cast<int32_t>(keys[j] & 0xffffffffu);
        const TileRect& r = rects[j];
        for (int ty = r.y0; ty < r.y1; ++ty)
            for (int tx = r.x0; tx < r.x1; ++tx) bins.ids[cursor[ty * bins.tiles_x + tx]++] = i;
    }
    return bins;
}

std::vector<torch::Tensor> rasterize_forward(torch::Tensor means2d, torch::Tensor conics,
                                             torch::Tensor colors, torch::Tensor opacities,
                                             torch::Tensor depths, torch::Tensor radii,
                                             torch::Tensor background, int64_t width,
                                             int64_t height) {
    const int64_t N = means2d.size(0);
    const int64_t D = colors.size(1);
    const int W = static_cast<int>(width), H = static_cast<int>(height);
    const float* m2 = means2d.data_ptr<float>();
    const float* cn = conics.data_ptr<float>();
    const float* col = colors.data_ptr<float>();
    const float* op = opacities.data_ptr<float>();
    const int32_t* rad = radii.data_ptr<int32_t>();
    const bool has_bg = background.numel() > 0;
    const float* bg = has_bg ? background.data_ptr<float>() : nullptr;

    TileBins bins = bin_gaussians(m2, rad, depths.data_ptr<float>(), N, W, H);
    const int n_tiles = bins.tiles_x * bins.tiles_y;

    std::vector<Splat> splats(static_cast<size_t>(N));
#pragma omp parallel for schedule(static)
    for (int64_t i = 0; i < N; ++i) {
        Splat s;
        s.x = m2[2 * i];
        s.y = m2[2 * i + 1];
        s.a = cn[3 * i];
        s.b = cn[3 * i + 1];
        s.c = cn[3 * i + 2];
        s.opacity = op[i];
        s.ry = static_cast<float>(rad[2 * i + 1]);
        s.pad = 0.f;
        splats[i] = s;
    }

    auto fopts = torch::TensorOptions().dtype(torch::kFloat32);
    torch::Tensor out_colors = torch::empty({H, W, D}, fopts);
    torch::Tensor out_alphas = torch::empty({H, W, 1}, fopts);
    torch::Tensor last_ids = torch::empty({H, W}, torch::TensorOptions().dtype(torch::kInt32));
    float* oc = out_colors.data_ptr<float>();
    float* oa = out_alphas.data_ptr<float>();
    int32_t* ol = last_ids.data_ptr<int32_t>();
    const int32_t* ids = bins.ids.data();
    const int32_t* offs = bins.offsets.data();

#pragma omp parallel
    {
        std::vector<float> acc_v(static_cast<size_t>(D) * kTilePixels);
        float* acc = acc_v.data();
        alignas(64) float T[kTilePixels];
        alignas(64) int32_t active[kTilePixels];
        alignas(64) int32_t last[kTilePixels];
        alignas(64) float w[kTile];

#pragma omp for schedule(dynamic, 1)
        for (int tile = 0; tile < n_tiles; ++tile) {
            const int x0 = (tile % bins.tiles_x) * kTile;
            const int y0 = (tile / bins.tiles_x) * kTile;
            const int rows = std::min(kTile, H - y0);
            const int cols = std::min(kTile, W - x0);
            std::fill(acc, acc + D * kTilePixels, 0.f);
            for (int p = 0; p < kTilePixels; ++p) {
                T[p] = 1.f;
                last[p] = -1;
                active[p] = ((p / kTile) < rows && (p % kTile) < cols) ? 1 : 0;
            }
            int alive = rows * cols;
            const int start = offs[tile], end = offs[tile + 1];
            for (int i = start; i < end && alive > 0; ++i) {
                const int32_t g = ids[i];
                const Splat s = splats[g];
                const int r0 = std::max(0, static_cast<int>(std::floor(s.y - s.ry - 0.5f)) - y0);
                const int r1 = std::min(rows - 1, static_cast<int>(std::ceil(s.y + s.ry)) - y0);
                const float* cg = col + static_cast<int64_t>(g) * D;
                for (int r = r0; r <= r1; ++r) {
                    const float dy = s.y - (static_cast<float>(y0 + r) + 0.5f);
                    float* Tr = T + r * kTile;
                    int32_t* ar = active + r * kTile;
                    int32_t* lr = last + r * kTile;
                    int n_stop = 0;
                    float any = 0.f;
#pragma omp simd reduction(+ : n_stop) reduction(+ : any)
                    for (int l = 0; l < kTile; ++l) {
                        const float dx = s.x - (static_cast<float>(x0 + l) + 0.5f);
                        const float sigma = 0.5f * (s.a * dx * dx + s.c * dy * dy) + s.b * dx * dy;
                        const float alpha = std::min(kMaxAlpha, s.opacity * fast_exp(-sigma));
                        const bool ok = (sigma >= 0.f) & (alpha >= kAlphaThreshold) & (ar[l] != 0);
                        const float t = Tr[l];
                        const float nt = t * (1.f - alpha);
                        const bool stop = ok & (nt <= kTransmittanceEps);
                        const bool use = ok & !stop;
                        const float wl = use ? alpha * t : 0.f;
                        w[l] = wl;
                        any += wl;
                        Tr[l] = use ? nt : t;
                        lr[l] = use ? i : lr[l];
                        ar[l] = stop ? 0 : ar[l];
                        n_stop += stop ? 1 : 0;
                    }
                    alive -= n_stop;
                    if (any == 0.f) continue;
                    for (int64_t k = 0; k < D; ++k) {
                        const float ck = cg[k];
                        float* A = acc + k * kTilePixels + r * kTile;
#pragma omp simd
                        for (int l = 0; l < kTile; ++l) A[l] += ck * w[l];
                    }
                }
            }
            for (int r = 0; r < rows; ++r) {
                for (int l = 0; l < cols; ++l) {
                    const int p = r * kTile + l;
                    const int64_t pix = static_cast<int64_t>(y0 + r) * W + (x0 + l);
                    for (int64_t k = 0; k < D; ++k)
                        oc[pix * D + k] = acc[k * kTilePixels + p] + (has_bg ? T[p] * bg[k] : 0.f);
                    oa[pix] = 1.f - T[p];
                    ol[pix] = last[p];
                }
            }
        }
    }

    torch::Tensor tile_offsets = torch::from_blob(bins.offsets.data(), {n_tiles + 1},
                                                  torch::TensorOptions().dtype(torch::kInt32))
                                     .clone();
    torch::Tensor tile_ids = torch::from_blob(bins.ids.data(), {static_cast<int64_t>(bins.ids.size())},
                                              torch::TensorOptions().dtype(torch::kInt32))
                                 .clone();
    return {out_colors, out_alphas, last_ids, tile_offsets, tile_ids};
}

}  // namespace promptgs
