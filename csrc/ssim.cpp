// Fused SSIM forward and backward (see ssim.h).
//
// Images are read once into planes (one per batch item and channel); every blurred map is
// a horizontal pass over rows padded with zeros, then a vertical pass of whole rows, both
// loops that the compiler vectorises (compiled for AVX-512, AVX2 and the baseline, picked
// at load time). Tasks (plane, map) run in parallel with OpenMP.
#include "ssim.h"

#include <omp.h>

#include <algorithm>
#include <vector>

namespace promptgs {

namespace {

constexpr float kC1 = 1e-4f;  // 0.01^2
constexpr float kC2 = 9e-4f;  // 0.03^2

#if defined(__GNUC__) && !defined(__clang__) && defined(__x86_64__)
#define PROMPTGS_CLONES __attribute__((target_clones("arch=x86-64-v4", "arch=x86-64-v3", "default")))
#else
#define PROMPTGS_CLONES
#endif

// out[j] = sum_k w[k] * padded[j + k], j < width (padded has width + taps - 1 values).
PROMPTGS_CLONES void blur_row(const float* __restrict padded, const float* __restrict w, int taps, int width,
                              float* __restrict out) {
    for (int j = 0; j < width; ++j) out[j] = 0.f;
    for (int k = 0; k < taps; ++k) {
        const float wk = w[k];
        const float* p = padded + k;
        for (int j = 0; j < width; ++j) out[j] += wk * p[j];
    }
}

// out += w * row
PROMPTGS_CLONES void axpy_row(const float* __restrict row, float w, int width, float* __restrict out) {
    for (int j = 0; j < width; ++j) out[j] += w * row[j];
}

// SSIM and, when p0 is not null, its partials dSSIM/d(mu_x, E[x^2], E[xy]) for n pixels.
PROMPTGS_CLONES void combine(const float* __restrict mx, const float* __restrict my, const float* __restrict sxx,
                             const float* __restrict syy, const float* __restrict sxy, int64_t n,
                             float* __restrict value, float* __restrict p0, float* __restrict p1,
                             float* __restrict p2) {
    for (int64_t e = 0; e < n; ++e) {
        const float mux = mx[e], muy = my[e];
        const float vx = sxx[e] - mux * mux, vy = syy[e] - muy * muy, cxy = sxy[e] - mux * muy;
        const float a1 = 2.f * mux * muy + kC1, a2 = 2.f * cxy + kC2;
        const float b1 = mux * mux + muy * muy + kC1, b2 = vx + vy + kC2;
        value[e] = (a1 * a2) / (b1 * b2);
    }
    if (!p0) return;
    for (int64_t e = 0; e < n; ++e) {
        // var_x = E[x^2] - mu_x^2 and cov = E[xy] - mu_x mu_y
        const float mux = mx[e], muy = my[e], v = value[e];
        const float vx = sxx[e] - mux * mux, vy = syy[e] - muy * muy, cxy = sxy[e] - mux * muy;
        const float a1 = 2.f * mux * muy + kC1, a2 = 2.f * cxy + kC2;
        const float b1 = mux * mux + muy * muy + kC1, b2 = vx + vy + kC2;
        // No division by a1 or a2: v / a2 is 0 / 0 where the covariance is exactly
        // -C2 / 2 (it happened on a training crop), while a1 / (b1 b2) is finite.
        const float inv_b = 1.f / (b1 * b2);
        const float d_b2 = -v / b2;
        p0[e] = 2.f * muy * (a2 - a1) * inv_b - 2.f * mux * v / b1 - 2.f * mux * d_b2;
        p1[e] = d_b2;
        p2[e] = 2.f * a1 * inv_b;
    }
}

// Blurs one H x W map given row by row by fill(i, dst) (dst: width floats), into out.
template <typename Fill>
void blur_map(const SsimShape& s, const float* w, Fill fill, std::vector<float>& padded, std::vector<float>& tmp,
              float* out) {
    const int H = static_cast<int>(s.height), W = static_cast<int>(s.width), R = s.radius, taps = 2 * s.radius + 1;
    padded.assign(static_cast<size_t>(W + 2 * R), 0.f);
    tmp.resize(static_cast<size_t>(H) * W);
    for (int i = 0; i < H; ++i) {
        fill(i, padded.data() + R);
        blur_row(padded.data(), w, taps, W, tmp.data() + static_cast<size_t>(i) * W);
    }
    for (int i = 0; i < H; ++i) {
        float* o = out + static_cast<size_t>(i) * W;
        std::fill(o, o + W, 0.f);
        for (int k = 0; k < taps; ++k) {
            const int r = i + k - R;
            if (r >= 0 && r < H) axpy_row(tmp.data() + static_cast<size_t>(r) * W, w[k], W, o);
        }
    }
}

// [B,H,W,C] -> planes [B*C][H*W]
void to_planes(const SsimShape& s, const float* src, float* planes) {
    const int64_t HW = s.height * s.width, C = s.channels;
#pragma omp parallel for schedule(static)
    for (int64_t b = 0; b < s.batch; ++b)
        for (int64_t p = 0; p < HW; ++p)
            for (int64_t c = 0; c < C; ++c) planes[(b * C + c) * HW + p] = src[(b * HW + p) * C + c];
}

}  // namespace

void ssim_forward(const SsimShape& s, const float* img, const float* ref, const float* window, float* ssim,
                  float* partials) {
    const int64_t HW = s.height * s.width, P = s.batch * s.channels, C = s.channels, W = s.width;
    std::vector<float> x(static_cast<size_t>(P * HW)), y(static_cast<size_t>(P * HW));
    to_planes(s, img, x.data());
    to_planes(s, ref, y.data());
    // blurred statistics: [5][P][HW] = mu_x, mu_y, E[x^2], E[y^2], E[xy]
    std::vector<float> stats(static_cast<size_t>(5 * P * HW));
#pragma omp parallel
    {
        std::vector<float> padded, tmp;
#pragma omp for schedule(dynamic, 1)
        for (int64_t task = 0; task < 5 * P; ++task) {
            const int64_t map = task / P, plane = task % P;
            const float* xs = x.data() + plane * HW;
            const float* ys = y.data() + plane * HW;
            auto fill = [&](int i, float* dst) {
                const float* xr = xs + i * W;
                const float* yr = ys + i * W;
                switch (map) {
                    case 0: std::copy(xr, xr + W, dst); break;
                    case 1: std::copy(yr, yr + W, dst); break;
                    case 2: for (int64_t j = 0; j < W; ++j) dst[j] = xr[j] * xr[j]; break;
                    case 3: for (int64_t j = 0; j < W; ++j) dst[j] = yr[j] * yr[j]; break;
                    default: for (int64_t j = 0; j < W; ++j) dst[j] = xr[j] * yr[j]; break;
                }
            };
            blur_map(s, window, fill, padded, tmp, stats.data() + (map * P + plane) * HW);
        }
    }
    const float* mx = stats.data();
    std::vector<float> value(static_cast<size_t>(P * HW));
    const int64_t chunk = 4096;
#pragma omp parallel for schedule(static)
    for (int64_t e0 = 0; e0 < P * HW; e0 += chunk) {
        const int64_t n = std::min(chunk, P * HW - e0);
        combine(mx + e0, mx + P * HW + e0, mx + 2 * P * HW + e0, mx + 3 * P * HW + e0, mx + 4 * P * HW + e0, n,
                value.data() + e0, partials ? partials + e0 : nullptr, partials ? partials + P * HW + e0 : nullptr,
                partials ? partials + 2 * P * HW + e0 : nullptr);
    }
#pragma omp parallel for schedule(static)
    for (int64_t b = 0; b < s.batch; ++b)  // planes -> [B, H, W, C]
        for (int64_t p = 0; p < HW; ++p)
            for (int64_t c = 0; c < C; ++c) ssim[(b * HW + p) * C + c] = value[(b * C + c) * HW + p];
}

void ssim_backward(const SsimShape& s, const float* grad, const float* partials, const float* img, const float* ref,
                   const float* window, float* grad_img) {
    const int64_t HW = s.height * s.width, P = s.batch * s.channels, C = s.channels, W = s.width;
    std::vector<float> g(static_cast<size_t>(P * HW));
    to_planes(s, grad, g.data());
    // the window is symmetric and zero-padded, so the blur is its own transpose:
    // dL/dx = blur(g dS/dmu_x) + 2 x blur(g dS/dE[x^2]) + y blur(g dS/dE[xy])
    std::vector<float> blurred(static_cast<size_t>(3 * P * HW));
#pragma omp parallel
    {
        std::vector<float> padded, tmp;
#pragma omp for schedule(dynamic, 1)
        for (int64_t task = 0; task < 3 * P; ++task) {
            const int64_t map = task / P, plane = task % P;
            const float* gs = g.data() + plane * HW;
            const float* ps = partials + (map * P + plane) * HW;
            auto fill = [&](int i, float* dst) {
                for (int64_t j = 0; j < W; ++j) dst[j] = gs[i * W + j] * ps[i * W + j];
            };
            blur_map(s, window, fill, padded, tmp, blurred.data() + (map * P + plane) * HW);
        }
    }
#pragma omp parallel for schedule(static)
    for (int64_t b = 0; b < s.batch; ++b)
        for (int64_t p = 0; p < HW; ++p)
            for (int64_t c = 0; c < C; ++c) {
                const int64_t e = (b * C + c) * HW + p, o = (b * HW + p) * C + c;
                grad_img[o] = blurred[e] + 2.f * img[o] * blurred[P * HW + e] + ref[o] * blurred[2 * P * HW + e];
            }
}

}  // namespace promptgs
