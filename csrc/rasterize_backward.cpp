// Exact backward pass of the CPU rasterizer.
//
// Each tile replays its Gaussians back to front, starting from the final transmittance
// saved by the forward pass and the per-pixel index of the last contributor, recovering
// T before each Gaussian as T / (1 - alpha). Gradients are summed per Gaussian within a
// tile (16-lane vector accumulators), then added to a per-thread buffer; the buffers are
// reduced at the end, so no atomics are needed.
#include <omp.h>

#include <algorithm>
#include <cmath>

#include "rasterize.h"
#include "simd_clones.h"

namespace promptgs {

namespace {

// Per-Gaussian record in the thread buffers: mean2d (2), conic (3), opacity (1),
// |mean2d| (2), then the D colour channels.
constexpr int kGradFixed = 8;

PROMPTGS_SIMD_CLONES
void backward_tile(const Splat* __restrict splats, const float* __restrict colors, int64_t D,
                   const int32_t* __restrict ids, int start, int x0, int y0, int rows, int cols,
                   const float* __restrict background, int W, const float* __restrict alpha_img,
                   const int32_t* __restrict last_img, const float* __restrict dcol_img,
                   const float* __restrict dalpha_img, float* __restrict dcol, float* __restrict buf,
                   float* __restrict vcol, float* __restrict G) {
    alignas(64) float T[kTilePixels];
    alignas(64) float tf_term[kTilePixels];
    alignas(64) int32_t last[kTilePixels];
    const int64_t stride = kGradFixed + D;
    RowF px;
    for (int l = 0; l < kTile; ++l) px[l] = static_cast<float>(x0 + l) + 0.5f;

    int max_last = -1;
    for (int p = 0; p < kTilePixels; ++p) {
        const int r = p / kTile, l = p % kTile;
        if (r < rows && l < cols) {
            const int64_t pix = static_cast<int64_t>(y0 + r) * W + (x0 + l);
            const float tf = 1.f - alpha_img[pix];
            T[p] = tf;
            last[p] = last_img[pix];
            max_last = std::max(max_last, last[p]);
            float bgdot = 0.f;
            for (int64_t k = 0; k < D; ++k) {
                const float dk = dcol_img[pix * D + k];
                dcol[k * kTilePixels + p] = dk;
                if (background) bgdot += background[k] * dk;
            }
            // dL/dalpha_i gets T_final / (1 - alpha_i) * (dL/dalpha_img - bg . dL/dcolour)
            tf_term[p] = tf * (dalpha_img[pix] - bgdot);
        } else {
            T[p] = 1.f;
            last[p] = -1;
            tf_term[p] = 0.f;
            for (int64_t k = 0; k < D; ++k) dcol[k * kTilePixels + p] = 0.f;
        }
    }
    std::fill(buf, buf + D * kTilePixels, 0.f);
    const RowF zero = splat_f(0.f);

    for (int i = max_last; i >= start; --i) {
        const int32_t g = ids[i];
        const Splat s = splats[g];
        const int r0 = std::max(0, static_cast<int>(std::floor(s.y - s.ry - 0.5f)) - y0);
        const int r1 = std::min(rows - 1, static_cast<int>(std::ceil(s.y + s.ry)) - y0);
        if (r0 > r1) continue;
        const float* cg = colors + static_cast<int64_t>(g) * D;
        const RowF dx = s.x - px;
        const RowF adx = 0.5f * s.a * dx;

        RowF gx = zero, gy = zero, ga = zero, gb = zero, gc = zero, go = zero, ax = zero, ay = zero;
        bool touched = false;

        for (int r = r0; r <= r1; ++r) {
            const float dy = s.y - (static_cast<float>(y0 + r) + 0.5f);
            const int pr = r * kTile;
            const RowF sigma = (adx + s.b * dy) * dx + 0.5f * s.c * dy * dy;
            const RowF vis = exp_row(-sigma);
            const RowF ov = s.opacity * vis;
            const RowF alpha = min_f(ov, kMaxAlpha);
            const RowI ok = (sigma >= 0.f) & (alpha >= kAlphaThreshold) & (splat_i(i) <= load_i(last + pr));
            if (hsum_i(ok) == 0) continue;
            if (!touched) {
                touched = true;
                std::fill(vcol, vcol + D * kTile, 0.f);
            }
            const RowF ra = 1.f / (1.f - alpha);
            const RowF t_old = load_f(T + pr);
            const RowF tn = t_old * ra;  // transmittance in front of this Gaussian
            store_f(T + pr, select(ok, tn, t_old));
            const RowF fac = select(ok, alpha * tn, zero);  // its blending weight
            RowF va = select(ok, ra * load_f(tf_term + pr), zero);  // dL/dalpha
            for (int64_t k = 0; k < D; ++k) {
                const float ck = cg[k];
                float* B = buf + k * kTilePixels + pr;  // colour composited behind this Gaussian
                const RowF b = load_f(B);
                const RowF dL = load_f(dcol + k * kTilePixels + pr);
                va += select(ok, (ck * tn - b * ra) * dL, zero);
                store_f(B, b + ck * fac);
                float* vc = vcol + k * kTile;
                store_f(vc, load_f(vc) + fac * dL);
            }
            const RowI use = ok & (ov <= kMaxAlpha);  // the 0.999 clamp has no gradient
            const RowF vsig = select(use, -ov * va, zero);
            go += select(use, vis * va, zero);
            ga += 0.5f * vsig * dx * dx;
            gb += vsig * dx * dy;
            gc += 0.5f * vsig * dy * dy;
            const RowF gxl = vsig * (s.a * dx + s.b * dy);
            const RowF gyl = vsig * (s.b * dx + s.c * dy);
            gx += gxl;
            gy += gyl;
            ax += select(gxl < 0.f, -gxl, gxl);
            ay += select(gyl < 0.f, -gyl, gyl);
        }
        if (!touched) continue;
        float* Gg = G + static_cast<int64_t>(g) * stride;
        Gg[0] += hsum_f(gx);
        Gg[1] += hsum_f(gy);
        Gg[2] += hsum_f(ga);
        Gg[3] += hsum_f(gb);
        Gg[4] += hsum_f(gc);
        Gg[5] += hsum_f(go);
        Gg[6] += hsum_f(ax);
        Gg[7] += hsum_f(ay);
        for (int64_t k = 0; k < D; ++k) Gg[kGradFixed + k] += hsum_f(load_f(vcol + k * kTile));
    }
}

}  // namespace

void rasterize_backward(const RasterInputs& in, const TileBins& bins, const float* out_alphas,
                        const int32_t* last_ids, const float* grad_colors, const float* grad_alphas,
                        float* grad_means2d, float* grad_conics, float* grad_colors_out, float* grad_opacities,
                        float* grad_abs_means2d) {
    const int64_t N = in.n, D = in.d;
    std::vector<Splat> splats;
    std::vector<float> colors;
    gather_sorted(in, bins, splats, colors);
    const int64_t M = static_cast<int64_t>(bins.order.size());
    const int n_tiles = bins.tiles_x * bins.tiles_y;
    const int64_t stride = kGradFixed + D;
    const int n_threads = omp_get_max_threads();
    std::vector<std::vector<float>> thread_grads(n_threads);

#pragma omp parallel num_threads(n_threads)
    {
        std::vector<float>& gbuf = thread_grads[omp_get_thread_num()];
        gbuf.assign(static_cast<size_t>(M * stride), 0.f);
        std::vector<float> dcol(static_cast<size_t>(D) * kTilePixels);
        std::vector<float> buf(static_cast<size_t>(D) * kTilePixels);
        std::vector<float> vcol(static_cast<size_t>(D) * kTile);
#pragma omp for schedule(dynamic, 1)
        for (int tile = 0; tile < n_tiles; ++tile) {
            const int start = bins.offsets[tile], end = bins.offsets[tile + 1];
            if (start == end) continue;
            const int x0 = (tile % bins.tiles_x) * kTile;
            const int y0 = (tile / bins.tiles_x) * kTile;
            backward_tile(splats.data(), colors.data(), D, bins.ids.data(), start, x0, y0,
                          std::min(kTile, in.height - y0), std::min(kTile, in.width - x0), in.background,
                          in.width, out_alphas, last_ids, grad_colors, grad_alphas, dcol.data(), buf.data(),
                          vcol.data(), gbuf.data());
        }

#pragma omp for schedule(static)
        for (int64_t i = 0; i < N; ++i) {  // Gaussians that no tile saw get zero gradients
            grad_means2d[2 * i] = grad_means2d[2 * i + 1] = 0.f;
            grad_conics[3 * i] = grad_conics[3 * i + 1] = grad_conics[3 * i + 2] = 0.f;
            grad_opacities[i] = 0.f;
            if (grad_abs_means2d) grad_abs_means2d[2 * i] = grad_abs_means2d[2 * i + 1] = 0.f;
            for (int64_t k = 0; k < D; ++k) grad_colors_out[i * D + k] = 0.f;
        }
#pragma omp for schedule(static)
        for (int64_t j = 0; j < M; ++j) {  // reduce the thread buffers, back to Gaussian order
            const int64_t i = bins.order[j];
            float acc[kGradFixed] = {0.f, 0.f, 0.f, 0.f, 0.f, 0.f, 0.f, 0.f};
            for (int t = 0; t < n_threads; ++t) {
                if (thread_grads[t].empty()) continue;  // a thread the runtime did not start
                const float* Gg = thread_grads[t].data() + j * stride;
                for (int q = 0; q < kGradFixed; ++q) acc[q] += Gg[q];
            }
            grad_means2d[2 * i] = acc[0];
            grad_means2d[2 * i + 1] = acc[1];
            grad_conics[3 * i] = acc[2];
            grad_conics[3 * i + 1] = acc[3];
            grad_conics[3 * i + 2] = acc[4];
            grad_opacities[i] = acc[5];
            if (grad_abs_means2d) {
                grad_abs_means2d[2 * i] = acc[6];
                grad_abs_means2d[2 * i + 1] = acc[7];
            }
            for (int64_t k = 0; k < D; ++k) {
                float s = 0.f;
                for (int t = 0; t < n_threads; ++t)
                    if (!thread_grads[t].empty()) s += thread_grads[t][j * stride + kGradFixed + k];
                grad_colors_out[i * D + k] = s;
            }
        }
    }
}

}  // namespace promptgs
