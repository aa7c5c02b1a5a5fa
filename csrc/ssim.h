// Per-pixel SSIM with a separable Gaussian window, forward and backward, fused in C++.
//
// Same definition as promptgs_engine/losses.py (`ssim_map_torch`, which stays the
// reference): per channel, the five local statistics mu_x, mu_y, E[x^2], E[y^2], E[xy] are
// blurred with the window (zero padding, output the size of the input), and
// SSIM = (2 mu_x mu_y + C1)(2 cov_xy + C2) / ((mu_x^2 + mu_y^2 + C1)(var_x + var_y + C2)).
// The backward gives the gradient with respect to the first image only.
#pragma once

#include <cstdint>

namespace promptgs {

struct SsimShape {
    int64_t batch, height, width, channels;  // images are [B, H, W, C], channels last
    int radius;                              // window of 2 * radius + 1 taps
};

// ssim [B,H,W,C]; when partials is not null, also dSSIM/d(mu_x, E[x^2], E[xy]) per pixel and
// channel, [3][B,H,W,C], for ssim_backward.
void ssim_forward(const SsimShape& s, const float* img, const float* ref, const float* window, float* ssim,
                  float* partials);

// dL/dimg [B,H,W,C] from dL/dssim [B,H,W,C] and the forward's partials.
void ssim_backward(const SsimShape& s, const float* grad, const float* partials, const float* img, const float* ref,
                   const float* window, float* grad_img);

// The per-pixel maps of the 3DGS loss in one pass: the channel means of |img - ref| (l1
// [B,H,W]) and of 1 - SSIM (dssim [B,H,W]), each summed in channel order and divided by C,
// and the partials of ssim_forward (not null); the SSIM image itself is not kept.
void photometric_forward(const SsimShape& s, const float* img, const float* ref, const float* window, float* l1,
                         float* dssim, float* partials);

// dL/dimg [B,H,W,C] of the loss a * mean(l1) + b * mean(dssim) from the two per-element
// factors autograd would give it: ssim_grad, dL/dSSIM, the same at every pixel and channel,
// and l1_grad, which multiplies sgn(img - ref) and is added last.
void photometric_backward(const SsimShape& s, float ssim_grad, float l1_grad, const float* partials,
                          const float* img, const float* ref, const float* window, float* grad_img);

}  // namespace promptgs
