// Forward pass of the CPU rasterizer: depth sort, depth-ranked copies of the Gaussian data,
// tile binning (exact ellipse/tile test), then the per-tile compositing kernels of
// tile_kernels.inc in parallel over tiles.
#include <omp.h>

#include <algorithm>
#include <cmath>

#include "kernels.h"
#include "rasterize.h"
#include "stage_times.h"

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

// Pixel columns [k0, k1] (clipped to [0, width)) whose centres lie within the ellipse
// q(u, v) = 0.5 a u^2 + b u v + 0.5 c v^2 <= L for some v in [va, vb] (u, v: offsets of a
// pixel centre from the mean). This is the exact x-extent of the ellipse inside a band
// of pixel rows, as Speedy-Splat's AccuTile computes it per tile row: along the ellipse
// the right edge u(v) = (-b v + sqrt(2 a L - det v^2)) / a is concave, largest at the
// ellipse's x-extreme (v = -b ex / c) and otherwise at the band end nearer to it; the left
// edge mirrors it. Computed in double and widened by 1e-3 px, so it can only include
// more columns than the per-pixel test in float needs, never fewer.
inline void band_columns(double x, double a, double b, double c, double L, double ex, double va, double vb,
                         int width, int& k0, int& k1) {
    const double det = a * c - b * b;
    auto right = [&](double v) { return (-b * v + std::sqrt(std::max(2.0 * a * L - det * v * v, 0.0))) / a; };
    auto left = [&](double v) { return (-b * v - std::sqrt(std::max(2.0 * a * L - det * v * v, 0.0))) / a; };
    const double v_right = -b * ex / c, v_left = b * ex / c;  // where the ellipse reaches u = +ex and -ex
    const double umax = (v_right < va) ? right(va) : (v_right > vb) ? right(vb) : ex;
    const double umin = (v_left < va) ? left(va) : (v_left > vb) ? left(vb) : -ex;
    // pixel k has its centre at k + 0.5, i.e. u = k + 0.5 - x
    const double lo = std::ceil(std::max(x + umin - 0.5 - 1e-3, -1.0));
    const double hi = std::floor(std::min(x + umax - 0.5 + 1e-3, static_cast<double>(width)));
    k0 = std::max(0, static_cast<int>(lo));
    k1 = std::min(width - 1, static_cast<int>(hi));
}

}  // namespace

TileBins bin_gaussians(const RasterInputs& in, const float* depths) {
    TileBins bins;
    bins.tiles_x = (in.width + kTile - 1) / kTile;
    bins.tiles_y = (in.height + kTile - 1) / kTile;
    const int n_tiles = bins.tiles_x * bins.tiles_y;
    const int64_t N = in.n, D = in.d;
    const int32_t* radii = in.radii;
    const float* m2 = in.means2d;
    const float* cn = in.conics;

    // 1. Per Gaussian, in index order (sequential reads): its record for the tile loops and
    // the box of pixel centres where its alpha can reach 1/255 (the exact ellipse, tighter
    // than the integer radii), as tiles. An empty box (or a zero radius) leaves it out.
    StageTimer sort_timer(kStageSort);
    struct Prepared {
        Splat s;
        TileRect r;
    };
    std::vector<Prepared> prep(static_cast<size_t>(N));
#pragma omp parallel for schedule(static)
    for (int64_t i = 0; i < N; ++i) {
        Prepared& p = prep[i];
        p.r = TileRect{0, 0, 0, 0};
        if (!(radii[2 * i] > 0 && radii[2 * i + 1] > 0)) continue;
        Splat& s = p.s;
        s.x = m2[2 * i];
        s.y = m2[2 * i + 1];
        s.a = cn[3 * i];
        s.b = cn[3 * i + 1];
        s.c = cn[3 * i + 2];
        s.opacity = in.opacities[i];
        s.cutoff = sigma_cutoff(s.opacity);
        float ex, ey;
        if (ellipse_extent(s.a, s.b, s.c, s.cutoff, ex, ey)) {
            s.ry = ey + 1e-3f;
        } else {
            ex = static_cast<float>(radii[2 * i]);
            ey = s.ry = static_cast<float>(radii[2 * i + 1]);
        }
        const int px0 = std::max(0, static_cast<int>(std::ceil(std::max(s.x - ex - 0.5f, -1.f))));
        const int px1 = std::min(in.width - 1, static_cast<int>(std::floor(std::min(s.x + ex - 0.5f, 1e9f))));
        const int py0 = std::max(0, static_cast<int>(std::ceil(std::max(s.y - ey - 0.5f, -1.f))));
        const int py1 = std::min(in.height - 1, static_cast<int>(std::floor(std::min(s.y + ey - 0.5f, 1e9f))));
        if (px0 <= px1 && py0 <= py1) p.r = TileRect{px0 / kTile, py0 / kTile, px1 / kTile + 1, py1 / kTile + 1};
    }

    // 2. Those that reach a tile, sorted front to back (stable, so ties keep index order).
    // Filling the tile lists in this order leaves every list sorted without a per-tile sort.
    std::vector<uint32_t> keys;
    std::vector<int32_t> order;
    keys.reserve(static_cast<size_t>(N));
    order.reserve(static_cast<size_t>(N));
    for (int64_t i = 0; i < N; ++i) {
        if (prep[i].r.x1 > prep[i].r.x0) {
            keys.push_back(float_key(depths[i]));
            order.push_back(static_cast<int32_t>(i));
        }
    }
    radix_sort(keys, order);
    const int64_t m = static_cast<int64_t>(order.size());
    sort_timer.stop();

    // 3. Depth-ranked copies of what the tile loops and the binning below read.
    StageTimer gather_timer(kStageGather);
    bins.splats.resize(static_cast<size_t>(m));
    bins.colors.resize(static_cast<size_t>(m * D));
    std::vector<TileRect> rects(static_cast<size_t>(m));
#pragma omp parallel for schedule(static)
    for (int64_t j = 0; j < m; ++j) {
        const int64_t i = order[j];
        bins.splats[j] = prep[i].s;
        rects[j] = prep[i].r;
        for (int64_t k = 0; k < D; ++k) bins.colors[j * D + k] = in.colors[i * D + k];
    }
    gather_timer.stop();

    // 4. Tile lists. The depth order is cut into chunks of about equal work (several per
    // thread; the work of a Gaussian is its box of tiles: near Gaussians, and the far
    // background shell, reach many more tiles than the rest). One pass finds each chunk's
    // (tile, rank) pairs (a Gaussian whose box spans several tiles gets, per tile row, only
    // the tiles its ellipse reaches) and counts them per tile; the pairs are then scattered,
    // each chunk's after those of the chunks before it in every tile, so every tile list
    // keeps the depth order whichever thread made which chunk.
    StageTimer bin_timer(kStageBin);
    const int n_chunks = static_cast<int>(std::max<int64_t>(1, std::min<int64_t>(m / 256, 4 * omp_get_max_threads())));
    std::vector<int64_t> work(static_cast<size_t>(m) + 1, 0);  // work[j]: tiles in the boxes of ranks < j
    for (int64_t j = 0; j < m; ++j)
        work[j + 1] = work[j] + int64_t{rects[j].x1 - rects[j].x0} * (rects[j].y1 - rects[j].y0);
    std::vector<int64_t> cut(static_cast<size_t>(n_chunks) + 1, m);  // chunk c is ranks [cut[c], cut[c + 1])
    for (int c = 0; c < n_chunks; ++c)
        cut[c] = std::lower_bound(work.begin(), work.end(), work[m] * c / n_chunks) - work.begin();
    cut[0] = 0;
    std::vector<std::vector<int32_t>> counts(n_chunks), pair_tiles(n_chunks), pair_ranks(n_chunks);
    bins.offsets.assign(n_tiles + 1, 0);
#pragma omp parallel for schedule(dynamic, 1)
    for (int chunk = 0; chunk < n_chunks; ++chunk) {
        const int64_t j0 = cut[chunk], j1 = cut[chunk + 1];
        // Filled as locals and moved out at the end: the vectors' headers sit side by side
        // in counts / pair_tiles / pair_ranks, and writing them on every pair from two threads
        // made the cores pass one cache line back and forth (the pass took twice as long).
        std::vector<int32_t> cnt(static_cast<size_t>(n_tiles), 0), tiles, ranks;
        tiles.reserve(static_cast<size_t>(work[j1] - work[j0]));  // at most the boxes' tiles
        ranks.reserve(static_cast<size_t>(work[j1] - work[j0]));
        auto emit = [&](int tile, int64_t j) {
            cnt[tile]++;
            tiles.push_back(tile);
            ranks.push_back(static_cast<int32_t>(j));
        };
        for (int64_t j = j0; j < j1; ++j) {
            const TileRect& r = rects[j];
            if (r.x1 - r.x0 == 1) {  // one column of tiles: every tile of the box is reached
                for (int ty = r.y0; ty < r.y1; ++ty) emit(ty * bins.tiles_x + r.x0, j);
                continue;
            }
            const Splat& s = bins.splats[j];
            const double a = s.a, b = s.b, c = s.c, L = s.cutoff;
            const double ex = std::sqrt(2.0 * L * c / (a * c - b * b));
            const bool ellipse = a > 0.0 && c > 0.0 && std::isfinite(ex);  // else the box came from the radii
            for (int ty = r.y0; ty < r.y1; ++ty) {
                if (r.y1 - r.y0 == 1 || !ellipse) {  // one row of tiles (the box is exact), or no ellipse
                    for (int tx = r.x0; tx < r.x1; ++tx) emit(ty * bins.tiles_x + tx, j);
                    continue;
                }
                const double va = ty * kTile + 0.5 - s.y;
                const double vb = std::min(ty * kTile + kTile, in.height) - 0.5 - s.y;
                int k0, k1;
                band_columns(s.x, a, b, c, L, ex, va, vb, in.width, k0, k1);
                const int tx0 = std::max(r.x0, k0 / kTile), tx1 = std::min(r.x1 - 1, k1 / kTile);
                for (int tx = tx0; tx <= tx1 && k0 <= k1; ++tx) emit(ty * bins.tiles_x + tx, j);
            }
        }
        counts[chunk] = std::move(cnt);
        pair_tiles[chunk] = std::move(tiles);
        pair_ranks[chunk] = std::move(ranks);
    }
    int32_t total = 0;
    for (int t = 0; t < n_tiles; ++t) {
        bins.offsets[t] = total;
        for (int k = 0; k < n_chunks; ++k) {
            const int32_t c = counts[k][t];
            counts[k][t] = total;  // becomes chunk k's write cursor in tile t
            total += c;
        }
    }
    bins.offsets[n_tiles] = total;
    bins.ids.resize(static_cast<size_t>(total));
#pragma omp parallel for schedule(dynamic, 1)
    for (int chunk = 0; chunk < n_chunks; ++chunk) {
        std::vector<int32_t>& cursor = counts[chunk];
        const std::vector<int32_t>& tiles = pair_tiles[chunk];
        const std::vector<int32_t>& ranks = pair_ranks[chunk];
        for (size_t p = 0; p < tiles.size(); ++p) bins.ids[cursor[tiles[p]]++] = ranks[p];
    }
    bins.order = std::move(order);
    return bins;
}

void rasterize_forward(const RasterInputs& in, const TileBins& bins, float* out_colors, float* out_alphas,
                       int32_t* last_ids, uint32_t* rows) {
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
    args.out_rows = rows;
    const Kernels::Forward forward = kernels().forward[kernel_for(in.d)];
    StageTimer timer(kStageBlendForward);
#pragma omp parallel
    {
        TileScratch scratch;
#pragma omp for schedule(dynamic, 1)
        for (int tile = 0; tile < n_tiles; ++tile) {
            forward(args, bins.splats.data(), bins.colors.data(), bins.offsets[tile], bins.offsets[tile + 1],
                    (tile % bins.tiles_x) * kTile, (tile / bins.tiles_x) * kTile, scratch);
        }
    }
}

}  // namespace promptgs
