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

namespace promptgs {

std::vector<torch::Tensor> rasterize_backward(
    torch::Tensor means2d, torch::Tensor conics, torch::Tensor colors, torch::Tensor opacities,
    torch::Tensor radii, torch::Tensor background, int64_t width, int64_t height,
    torch::Tensor tile_offsets, torch::Tensor tile_ids, torch::Tensor out_alphas,
    torch::Tensor last_ids, torch::Tensor grad_colors, torch::Tensor grad_alphas, bool absgrad) {
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
    const int32_t* offs = tile_offsets.data_ptr<int32_t>();
    const int32_t* ids = tile_ids.data_ptr<int32_t>();
    const float* alpha_img = out_alphas.data_ptr<float>();
    const int32_t* last_img = last_ids.data_ptr<int32_t>();
    const float* dcol_img = grad_colors.data_ptr<float>();
    const float* dalpha_img = grad_alphas.data_ptr<float>();

    const int tiles_x = (W + kTile - 1) / kTile;
    const int tiles_y = (H + kTile - 1) / kTile;
    const int n_tiles = tiles_x * tiles_y;

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

    // Per-Gaussian gradient record in the thread buffers: mean2d (2), conic (3),
    // opacity (1), |mean2d| (2), colours (D).
    const int64_t stride = 8 + D;
    const int n_threads = omp_get_max_threads();
    std::vector<std::vector<float>> thread_grads(n_threads);

#pragma omp parallel num_threads(n_threads)
    {
        const int tid = omp_get_thread_num();
        std::vector<float>& gbuf = thread_grads[tid];
        gbuf.assign(static_cast<size_t>(N * stride), 0.f);
        float* G = gbuf.data();

        std::vector<float> dcol_v(static_cast<size_t>(D) * kTilePixels);
        std::vector<float> buf_v(static_cast<size_t>(D) * kTilePixels);
        std::vector<float> vcol_v(static_cast<size_t>(D) * kTile);
        float* dcol = dcol_v.data();
        float* buf = buf_v.data();
        float* vcol = vcol_v.data();
        alignas(64) float T[kTilePixels];
        alignas(64) float tf_term[kTilePixels];
        alignas(64) int32_t last[kTilePixels];
        alignas(64) float fac[kTile], ra_[kTile], tn_[kTile], vis_[kTile], va[kTile];
        alignas(64) int32_t valid[kTile];

#pragma omp for schedule(dynamic, 1)
        for (int tile = 0; tile < n_tiles; ++tile) {
            const int start = offs[tile], end = offs[tile + 1];
            if (start == end) continue;
            const int x0 = (tile % tiles_x) * kTile;
            const int y0 = (tile / tiles_x) * kTile;
            const int rows = std::min(kTile, H - y0);
            const int cols = std::min(kTile, W - x0);
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
                        if (has_bg) bgdot += bg[k] * dk;
                    }
                    tf_term[p] = tf * (dalpha_img[pix] - bgdot);
                } else {
                    T[p] = 1.f;
                    last[p] = -1;
                    tf_term[p] = 0.f;
                    for (int64_t k = 0; k < D; ++k) dcol[k * kTilePixels + p] = 0.f;
                }
            }
            std::fill(buf, buf + D * kTilePixels, 0.f);

            for (int i = max_last; i >= start; --i) {
                const int32_t g = ids[i];
                const Splat s = splats[g];
                const int r0 = std::max(0, static_cast<int>(std::floor(s.y - s.ry - 0.5f)) - y0);
                const int r1 = std::min(rows - 1, static_cast<int>(std::ceil(s.y + s.ry)) - y0);
                if (r0 > r1) continue;
                const float* cg = col + static_cast<int64_t>(g) * D;

                alignas(64) float gx[kTile] = {}, gy[kTile] = {}, ga[kTile] = {}, gb[kTile] = {},
                                  gc[kTile] = {}, go[kTile] = {}, ax[kTile] = {}, ay[kTile] = {};
                std::fill(vcol, vcol + D * kTile, 0.f);
                bool touched = false;

                for (int r = r0; r <= r1; ++r) {
                    const float dy = s.y - (static_cast<float>(y0 + r) + 0.5f);
                    const int pr = r * kTile;
                    int n_valid = 0;
#pragma omp simd reduction(+ : n_valid)
                    for (int l = 0; l < kTile; ++l) {
                        const float dx = s.x - (static_cast<float>(x0 + l) + 0.5f);
                        const float sigma = 0.5f * (s.a * dx * dx + s.c * dy * dy) + s.b * dx * dy;
                        const float vis = fast_exp(-sigma);
                        const float alpha = std::min(kMaxAlpha, s.opacity * vis);
                        const bool ok = (sigma >= 0.f) & (alpha >= kAlphaThreshold) & (i <= last[pr + l]);
                        const float ra = 1.f / (1.f - alpha);
                        const float tn = T[pr + l] * ra;
                        valid[l] = ok ? 1 : 0;
                        vis_[l] = vis;
                        ra_[l] = ra;
                        tn_[l] = tn;
                        fac[l] = ok ? alpha * tn : 0.f;
                        va[l] = ok ? ra * tf_term[pr + l] : 0.f;
                        n_valid += ok ? 1 : 0;
                    }
                    if (n_valid == 0) continue;
                    touched = true;
                    for (int64_t k = 0; k < D; ++k) {
                        const float ck = cg[k];
                        float* B = buf + k * kTilePixels + pr;
                        const float* dL = dcol + k * kTilePixels + pr;
                        float* vc = vcol + k * kTile;
#pragma omp simd
                        for (int l = 0; l < kTile; ++l) {
                            const float term = (ck * tn_[l] - B[l] * ra_[l]) * dL[l];
                            va[l] += valid[l] ? term : 0.f;
                            B[l] += ck * fac[l];
                            vc[l] += fac[l] * dL[l];
                        }
                    }
#pragma omp simd
                    for (int l = 0; l < kTile; ++l) {
                        const float dx = s.x - (static_cast<float>(x0 + l) + 0.5f);
                        const bool ok = valid[l] != 0;
                        T[pr + l] = ok ? tn_[l] : T[pr + l];
                        const float ov = s.opacity * vis_[l];
                        const bool use = ok & (ov <= kMaxAlpha);
                        const float vsig = use ? -ov * va[l] : 0.f;
                        go[l] += use ? vis_[l] * va[l] : 0.f;
                        ga[l] += 0.5f * vsig * dx * dx;
                        gb[l] += vsig * dx * dy;
                        gc[l] += 0.5f * vsig * dy * dy;
                        const float px = vsig * (s.a * dx + s.b * dy);
                        const float py = vsig * (s.b * dx + s.c * dy);
                        gx[l] += px;
                        gy[l] += py;
                        ax[l] += std::fabs(px);
                        ay[l] += std::fabs(py);
                    }
                }
                if (!touched) continue;
                float sx = 0.f, sy = 0.f, sa = 0.f, sb = 0.f, sc = 0.f, so = 0.f, sax = 0.f, say = 0.f;
                for (int l = 0; l < kTile; ++l) {
                    sx += gx[l];
                    sy += gy[l];
                    sa += ga[l];
                    sb += gb[l];
                    sc += gc[l];
                    so += go[l];
                    sax += ax[l];
                    say += ay[l];
                }
                float* Gg = G + static_cast<int64_t>(g) * stride;
                Gg[0] += sx;
                Gg[1] += sy;
                Gg[2] += sa;
                Gg[3] += sb;
                Gg[4] += sc;
                Gg[5] += so;
                Gg[6] += sax;
                Gg[7] += say;
                for (int64_t k = 0; k < D; ++k) {
                    float sk = 0.f;
                    const float* vc = vcol + k * kTile;
                    for (int l = 0; l < kTile; ++l) sk += vc[l];
                    Gg[8 + k] += sk;
                }
            }
        }
    }

    auto fopts = torch::TensorOptions().dtype(torch::kFloat32);
    torch::Tensor g_means2d = torch::empty({N, 2}, fopts);
    torch::Tensor g_conics = torch::empty({N, 3}, fopts);
    torch::Tensor g_opac = torch::empty({N}, fopts);
    torch::Tensor g_colors = torch::empty({N, D}, fopts);
    torch::Tensor g_abs = absgrad ? torch::empty({N, 2}, fopts) : torch::empty({0}, fopts);
    float* gm = g_means2d.data_ptr<float>();
    float* gcn = g_conics.data_ptr<float>();
    float* gop = g_opac.data_ptr<float>();
    float* gcol = g_colors.data_ptr<float>();
    float* gab = absgrad ? g_abs.data_ptr<float>() : nullptr;

#pragma omp parallel for schedule(static)
    for (int64_t i = 0; i < N; ++i) {
        float acc[8] = {0.f, 0.f, 0.f, 0.f, 0.f, 0.f, 0.f, 0.f};
        for (int t = 0; t < n_threads; ++t) {
            const float* Gg = thread_grads[t].data() + i * stride;
            for (int j = 0; j < 8; ++j) acc[j] += Gg[j];
        }
        gm[2 * i] = acc[0];
        gm[2 * i + 1] = acc[1];
        gcn[3 * i] = acc[2];
        gcn[3 * i + 1] = acc[3];
        gcn[3 * i + 2] = acc[4];
        gop[i] = acc[5];
        if (gab) {
            gab[2 * i] = acc[6];
            gab[2 * i + 1] = acc[7];
        }
        for (int64_t k = 0; k < D; ++k) {
            float s = 0.f;
            for (int t = 0; t < n_threads; ++t) s += thread_grads[t][i * stride + 8 + k];
            gcol[i * D + k] = s;
        }
    }
    return {g_means2d, g_conics, g_colors, g_opac, g_abs};
}

}  // namespace promptgs
