// Tile-based CPU rasterizer for 3D Gaussian Splatting (forward and exact backward).
//
// Plain C++17 + OpenMP, no torch types: bindings.cpp wraps these functions for Python.
//
// Conventions shared with promptgs_engine/render (and gsplat's CUDA rasterizer):
//  - pixel (x, y) is sampled at its centre (x + 0.5, y + 0.5);
//  - a Gaussian seen from a pixel has sigma = 0.5 (a dx^2 + c dy^2) + b dx dy with
//    (dx, dy) = mean2d - pixel and conic (a, b, c); alpha = min(0.999, o exp(-sigma));
//  - it is skipped when sigma < 0 or alpha < 1/255; a pixel stops before the Gaussian
//    that would bring its transmittance T to <= 1e-4; the background is added with the
//    final T; the alpha image is 1 - T;
//  - Gaussians with a zero radius are culled; the others are binned into 16x16 tiles by
//    the box mean2d +- radii and composited in increasing depth order.
#pragma once

// Row vectors are only passed between inlined helpers; the ABI note does not apply.
#pragma GCC diagnostic ignored "-Wpsabi"

#include <cstdint>
#include <cstring>
#include <vector>

namespace promptgs {

constexpr int kTile = 16;
constexpr int kTilePixels = kTile * kTile;
constexpr float kAlphaThreshold = 1.0f / 255.0f;
constexpr float kMaxAlpha = 0.999f;
constexpr float kTransmittanceEps = 1e-4f;

// One tile row (16 pixels) as a vector, with GCC/Clang vector extensions. The compiler
// maps it onto whatever the target has (one AVX-512 register, two AVX2 or four SSE ones),
// so the hot loops are vectorised by construction rather than left to the auto-vectoriser.
typedef float RowF __attribute__((vector_size(kTile * sizeof(float))));
typedef int32_t RowI __attribute__((vector_size(kTile * sizeof(int32_t))));

__attribute__((always_inline)) inline RowF splat_f(float v) { return RowF{} + v; }
__attribute__((always_inline)) inline RowI splat_i(int32_t v) { return RowI{} + v; }
__attribute__((always_inline)) inline RowF load_f(const float* p) {
    RowF v;
    std::memcpy(&v, p, sizeof(v));
    return v;
}
__attribute__((always_inline)) inline RowI load_i(const int32_t* p) {
    RowI v;
    std::memcpy(&v, p, sizeof(v));
    return v;
}
__attribute__((always_inline)) inline void store_f(float* p, RowF v) { std::memcpy(p, &v, sizeof(v)); }
__attribute__((always_inline)) inline void store_i(int32_t* p, RowI v) { std::memcpy(p, &v, sizeof(v)); }
__attribute__((always_inline)) inline RowF select(RowI mask, RowF a, RowF b) { return mask ? a : b; }
__attribute__((always_inline)) inline RowF min_f(RowF a, float b) { return a < b ? a : splat_f(b); }
// Horizontal sums by a shuffle tree (4 steps for 16 lanes) rather than 16 lane extracts.
#if defined(__clang__) || (defined(__GNUC__) && __GNUC__ >= 12)
#define PROMPTGS_HSUM_TREE(v)                                                                              \
    v += __builtin_shufflevector(v, v, 8, 9, 10, 11, 12, 13, 14, 15, 0, 1, 2, 3, 4, 5, 6, 7);            \
    v += __builtin_shufflevector(v, v, 4, 5, 6, 7, 0, 1, 2, 3, 12, 13, 14, 15, 8, 9, 10, 11);            \
    v += __builtin_shufflevector(v, v, 2, 3, 0, 1, 6, 7, 4, 5, 10, 11, 8, 9, 14, 15, 12, 13);            \
    v += __builtin_shufflevector(v, v, 1, 0, 3, 2, 5, 4, 7, 6, 9, 8, 11, 10, 13, 12, 15, 14);            \
    return v[0];
#else
#define PROMPTGS_HSUM_TREE(v)                       \
    auto s = v[0];                                  \
    for (int l = 1; l < kTile; ++l) s += v[l];      \
    return s;
#endif
__attribute__((always_inline)) inline float hsum_f(RowF v) { PROMPTGS_HSUM_TREE(v) }
__attribute__((always_inline)) inline int32_t hsum_i(RowI v) { PROMPTGS_HSUM_TREE(v) }

// exp(x) for x <= 0 on a row, accurate to ~2 ulp. Inputs are clamped to [-87, 0]: callers
// never need exp of a positive number, and exp(-87) is far below the 1/255 alpha cut-off.
__attribute__((always_inline)) inline RowF exp_row(RowF x) {
    x = x < -87.0f ? splat_f(-87.0f) : x;
    x = x > 0.0f ? splat_f(0.0f) : x;
    // n = round(x / ln2) (x <= 0, so truncating x/ln2 - 0.5 rounds to nearest)
    const RowI ni = __builtin_convertvector(x * 1.44269504088896341f - 0.5f, RowI);
    const RowF n = __builtin_convertvector(ni, RowF);
    // Cody-Waite range reduction: r = x - n ln2 in two parts, then a degree-6 polynomial.
    RowF r = x - n * 0.693359375f;
    r = r + n * 2.12194440e-4f;
    RowF p = splat_f(1.9875691500e-4f);
    p = p * r + 1.3981999507e-3f;
    p = p * r + 8.3334519073e-3f;
    p = p * r + 4.1665795894e-2f;
    p = p * r + 1.6666665459e-1f;
    p = p * r + 5.0000001201e-1f;
    p = p * r * r + r + 1.0f;
    const RowI bits = (ni + 127) << 23;
    RowF scale;
    std::memcpy(&scale, &bits, sizeof(scale));
    return p * scale;
}

// Per-Gaussian data the tile loops read, packed into one 32-byte record.
struct alignas(32) Splat {
    float x, y;     // mean2d
    float a, b, c;  // conic
    float opacity;
    float ry;       // vertical radius in pixels: bounds the rows a Gaussian can touch
    float pad;
};

// Depth-sorted Gaussian lists per tile.
//
// Visible Gaussians are numbered by depth rank (0 = nearest) and the tile lists hold these
// ranks, so every tile walks forward through the depth-sorted copies of the Gaussian data
// (sequential, prefetch-friendly memory access instead of random lookups).
struct TileBins {
    int tiles_x = 0, tiles_y = 0;
    std::vector<int32_t> order;    // [M] Gaussian index of each depth rank
    std::vector<int32_t> offsets;  // [tiles + 1]
    std::vector<int32_t> ids;      // [n_isects] depth ranks, increasing (front to back) per tile
};

// Inputs of one image. Arrays are float32 / int32, contiguous, N rows.
struct RasterInputs {
    const float* means2d;    // [N, 2]
    const float* conics;     // [N, 3]
    const float* colors;     // [N, D]
    const float* opacities;  // [N]
    const int32_t* radii;    // [N, 2]
    const float* background; // [D] or nullptr
    int64_t n;
    int64_t d;
    int width, height;
};

// Bins visible Gaussians into tiles, sorted by depth ([N] sort keys).
TileBins bin_gaussians(const RasterInputs& in, const float* depths);

// Composites one image. Outputs: colours [H, W, D], alphas [H, W], last_ids [H, W] (index
// into bins.ids of the last Gaussian composited at each pixel, -1 if none).
void rasterize_forward(const RasterInputs& in, const TileBins& bins, float* out_colors,
                       float* out_alphas, int32_t* last_ids);

// Gradients for one image, given the forward outputs and dL/d(colours [H,W,D], alphas [H,W]).
// Outputs (overwritten): means2d [N,2], conics [N,3], colors [N,D], opacities [N] and,
// when grad_abs_means2d is not null, the per-pixel sums of |dL/dmeans2d| [N,2].
void rasterize_backward(const RasterInputs& in, const TileBins& bins, const float* out_alphas,
                        const int32_t* last_ids, const float* grad_colors, const float* grad_alphas,
                        float* grad_means2d, float* grad_conics, float* grad_colors_out,
                        float* grad_opacities, float* grad_abs_means2d);

// Gaussian data in depth-rank order: splats [M] and colours [M, D].
void gather_sorted(const RasterInputs& in, const TileBins& bins, std::vector<Splat>& splats,
                   std::vector<float>& colors);

}  // namespace promptgs
