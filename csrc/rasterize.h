// Tile-based CPU rasterizer for 3D Gaussian Splatting (forward and exact backward).
//
// Conventions shared with promptgs_engine/render (and gsplat's CUDA rasterizer):
//  - pixel (x, y) is sampled at its centre (x + 0.5, y + 0.5);
//  - a Gaussian i seen from a pixel has sigma = 0.5 (a dx^2 + c dy^2) + b dx dy with
//    (dx, dy) = mean2d - pixel and conic (a, b, c); alpha = min(0.999, o exp(-sigma));
//  - it is skipped when sigma < 0 or alpha < 1/255; a pixel stops before the Gaussian
//    that would bring its transmittance T to <= 1e-4; background is added with the
//    final T; the alpha image is 1 - T.
//  - Gaussians with radii (rx, ry) == 0 are culled; the others are binned into 16x16
//    tiles by the box mean2d +- radii and composited in increasing depth order.
#pragma once

#include <torch/extension.h>

#include <cstdint>
#include <cstring>
#include <vector>

namespace promptgs {

constexpr int kTile = 16;
constexpr int kTilePixels = kTile * kTile;
constexpr float kAlphaThreshold = 1.0f / 255.0f;
constexpr float kMaxAlpha = 0.999f;
constexpr float kTransmittanceEps = 1e-4f;

// exp(x) for x <= 0, accurate to ~2 ulp, written so loops that call it vectorise
// (no libm call). Inputs below -87 return a value that underflows to ~0.
// Positive inputs are clamped to 0 (callers never use exp of a positive number).
inline float fast_exp(float x) {
    x = x < -87.0f ? -87.0f : x;
    x = x > 0.0f ? 0.0f : x;
    const float log2e = 1.44269504088896341f;
    // round to nearest for a non-positive argument, without a libm call
    float n = static_cast<float>(static_cast<int32_t>(x * log2e - 0.5f));
    // Cody-Waite range reduction: r = x - n ln2 in two parts.
    float r = x - n * 0.693359375f;
    r = r + n * 2.12194440e-4f;
    float p = 1.9875691500e-4f;
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * r * r + r + 1.0f;
    int32_t e = (static_cast<int32_t>(n) + 127) << 23;
    float scale;
    std::memcpy(&scale, &e, sizeof(float));
    return p * scale;
}

// Per-Gaussian data the tile loops read, packed into one 32-byte record.
struct alignas(32) Splat {
    float x, y;      // mean2d
    float a, b, c;   // conic
    float opacity;
    float ry;        // vertical radius (pixels), bounds the rows a Gaussian can touch
    float pad;
};

// Depth-sorted Gaussian lists per tile.
struct TileBins {
    int tiles_x = 0, tiles_y = 0;
    std::vector<int32_t> offsets;  // [tiles + 1]
    std::vector<int32_t> ids;      // [n_isects] Gaussian indices, front to back per tile
};

TileBins bin_gaussians(const float* means2d, const int32_t* radii, const float* depths, int64_t n,
                       int width, int height);

std::vector<torch::Tensor> rasterize_forward(torch::Tensor means2d, torch::Tensor conics,
                                             torch::Tensor colors, torch::Tensor opacities,
                                             torch::Tensor depths, torch::Tensor radii,
                                             torch::Tensor background, int64_t width,
                                             int64_t height);

std::vector<torch::Tensor> rasterize_backward(
    torch::Tensor means2d, torch::Tensor conics, torch::Tensor colors, torch::Tensor opacities,
    torch::Tensor radii, torch::Tensor background, int64_t width, int64_t height,
    torch::Tensor tile_offsets, torch::Tensor tile_ids, torch::Tensor out_alphas,
    torch::Tensor last_ids, torch::Tensor grad_colors, torch::Tensor grad_alphas, bool absgrad);

}  // namespace promptgs
