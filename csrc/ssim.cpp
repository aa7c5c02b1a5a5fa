// Fused SSIM forward and backward (see ssim.h).
//
// Each image is cut into bands of rows, and the bands run in parallel with OpenMP through the
// vectorised kernels of ssim_kernels.inc for the CPU's instruction set, on the images as they
// are (channels last).
#include "ssim.h"

#include <omp.h>

#include <algorithm>

#include "kernels.h"

namespace promptgs {

namespace {

// Runs fn(image, o0, o1) over every image's rows, cut into bands so that every thread has a
// few tasks (output rows are independent, so the cut changes no result).
template <typename Fn>
void for_each_band(const SsimShape& s, Fn fn) {
    const int64_t H = s.height;
    const int64_t bands = std::min<int64_t>(H, (4 * omp_get_max_threads() + s.batch - 1) / s.batch);
#pragma omp parallel for schedule(dynamic, 1)
    for (int64_t task = 0; task < s.batch * bands; ++task) {
        const int64_t band = task % bands;
        fn(task / bands, static_cast<int>(H * band / bands), static_cast<int>(H * (band + 1) / bands));
    }
}

}  // namespace

void ssim_forward(const SsimShape& s, const float* img, const float* ref, const float* window, float* ssim,
                  float* partials) {
    const int64_t n = s.batch * s.height * s.width * s.channels, image = s.height * s.width * s.channels;
    const Kernels::SsimForwardBand band = kernels().ssim_forward_band;
    for_each_band(s, [&](int64_t b, int o0, int o1) {
        const int64_t at = b * image;
        band(s, img + at, ref + at, window, o0, o1, ssim + at, partials ? partials + at : nullptr,
             partials ? partials + n + at : nullptr, partials ? partials + 2 * n + at : nullptr, nullptr, nullptr);
    });
}

void ssim_backward(const SsimShape& s, const float* grad, const float* partials, const float* img, const float* ref,
                   const float* window, float* grad_img) {
    const int64_t n = s.batch * s.height * s.width * s.channels, image = s.height * s.width * s.channels;
    const Kernels::SsimBackwardBand band = kernels().ssim_backward_band;
    for_each_band(s, [&](int64_t b, int o0, int o1) {
        const int64_t at = b * image;
        band(s, grad + at, 0.f, partials + at, partials + n + at, partials + 2 * n + at, img + at, ref + at, window, o0,
             o1, false, 0.f, grad_img + at);
    });
}

void photometric_forward(const SsimShape& s, const float* img, const float* ref, const float* window, float* l1,
                         float* dssim, float* partials) {
    const int64_t n = s.batch * s.height * s.width * s.channels, image = s.height * s.width * s.channels;
    const int64_t pixels = s.height * s.width;
    const Kernels::SsimForwardBand band = kernels().ssim_forward_band;
    for_each_band(s, [&](int64_t b, int o0, int o1) {
        const int64_t at = b * image;
        band(s, img + at, ref + at, window, o0, o1, nullptr, partials + at, partials + n + at, partials + 2 * n + at,
             l1 + b * pixels, dssim + b * pixels);
    });
}

void photometric_backward(const SsimShape& s, float ssim_grad, float l1_grad, const float* partials,
                          const float* img, const float* ref, const float* window, float* grad_img) {
    const int64_t n = s.batch * s.height * s.width * s.channels, image = s.height * s.width * s.channels;
    const Kernels::SsimBackwardBand band = kernels().ssim_backward_band;
    for_each_band(s, [&](int64_t b, int o0, int o1) {
        const int64_t at = b * image;
        band(s, nullptr, ssim_grad, partials + at, partials + n + at, partials + 2 * n + at, img + at, ref + at, window,
             o0, o1, true, l1_grad, grad_img + at);
    });
}

}  // namespace promptgs
