// Tile-based CPU rasterizer for 3D Gaussian Splatting (forward and exact backward).
//
// Plain C++17 + OpenMP, no torch types: bindings.cpp wraps these functions for Python.
//
// Conventions shared with promptgs_engine/render (and gsplat's CUDA rasterizer):
//  - pixel (x, y) is sampled at its centre (x + 0.5, y + 0.5);
//  - a Gaussian seen from a pixel has sigma = 0.5 (a dx^2 + c dy^2) + b dx dy with
//    (dx, dy) = mean2d - pixel and conic (a, b, c); alpha = min(0.999, o exp(-sigma));
//  - it is skipped when sigma < 0 or alpha < 1/255; a pixel stops before the Gaussian that
//    would bring its transmittance T to <= 1e-4; the background is added with the final
//    T; the alpha image is 1 - T;
//  - Gaussians with a zero radius are culled; the others are composited in increasing
//    depth order in every 16x16 tile that their ellipse alpha >= 1/255 reaches (which tiles
//    and rows a Gaussian visits only decides where work is spent: every pixel applies the
//    exact test above, so the image does not depend on it).
#pragma once


#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

namespace promptgs {

constexpr int kTile = 16;
constexpr int kTilePixels = kTile * kTile;
constexpr float kAlphaThreshold = 1.0f / 255.0f;
constexpr float kMaxAlpha = 0.999f;
constexpr float kTransmittanceEps = 1e-4f;

// A Gaussian of opacity o can only reach alpha >= 1/255 where sigma <= ln(255 o); the small
// margin keeps the exact cut-offs below (rows, tiles) conservative against rounding.
inline float sigma_cutoff(float opacity) { return std::log(opacity * 255.f) + 1e-3f; }

// Half-extents (x, y) of the ellipse sigma <= L for the conic (a, b, c); false if degenerate.
inline bool ellipse_extent(float a, float b, float c, float L, float& ex, float& ey) {
    const float det = a * c - b * b;
    if (!(det > 0.f) || !(L > 0.f)) return false;
    ex = std::sqrt(2.f * L * c / det);
    ey = std::sqrt(2.f * L * a / det);
    return std::isfinite(ex) && std::isfinite(ey);
}

// Per-Gaussian data the tile loops read, packed into one 32-byte record.
struct alignas(32) Splat {
    float x, y;     // mean2d
    float a, b, c;  // conic
    float opacity;
    float ry;       // half-height of the ellipse where alpha can reach 1/255 (rows it can touch)
    float cutoff;   // sigma_cutoff(opacity)
};
constexpr int kSplatFloats = 8;
static_assert(sizeof(Splat) == kSplatFloats * sizeof(float), "Splat is 8 floats");

// Depth-sorted Gaussian lists per tile.
//
// Visible Gaussians are numbered by depth rank (0 = nearest) and the tile lists hold these
// ranks, so every tile walks forward through the depth-sorted copies of the Gaussian data
// (sequential, prefetch-friendly memory access instead of random lookups). The forward
// pass builds the copies once; the backward pass reuses them.
struct TileBins {
    int tiles_x = 0, tiles_y = 0;
    std::vector<int32_t> order;    // [M] Gaussian index of each depth rank
    std::vector<int32_t> offsets;  // [tiles + 1]
    std::vector<int32_t> ids;      // [n_isects] depth ranks, increasing (front to back) per tile
    std::vector<Splat> splats;     // [M] Gaussian data by depth rank
    std::vector<float> colors;     // [M, D] colours by depth rank
};

// The same arrays as views (what the backward reads; they may live in tensors).
struct TileBinsView {
    int tiles_x = 0, tiles_y = 0;
    int64_t m = 0;                   // visible Gaussians (depth ranks)
    const int32_t* order = nullptr;  // [M]
    const int32_t* offsets = nullptr;
    const int32_t* ids = nullptr;
    const Splat* splats = nullptr;   // [M]
    const float* colors = nullptr;   // [M, D]
};

// What the per-tile kernels read and write (one image).
struct TileArgs {
    const int32_t* ids = nullptr;  // tile lists of depth ranks (TileBins::ids)
    int64_t d = 0;                 // channels
    int width = 0, height = 0;
    const float* background = nullptr;  // [D] or nullptr
    // forward outputs
    float* out_colors = nullptr;  // [H, W, D]
    float* out_alphas = nullptr;  // [H, W]
    int32_t* out_last = nullptr;  // [H, W]
    uint32_t* out_rows = nullptr;  // [n_isects] where the Gaussian composited a pixel (see kRowParts)
    // backward inputs
    const float* alphas = nullptr;       // [H, W] forward alphas
    const int32_t* last_ids = nullptr;   // [H, W] forward last contributors
    const uint32_t* rows = nullptr;      // [n_isects] forward out_rows
    const float* grad_colors = nullptr;  // [H, W, D]
    const float* grad_alphas = nullptr;  // [H, W], or null for zeros
};

// Per-Gaussian record in the backward gradient buffers: mean2d (2), conic (3),
// opacity (1), |mean2d| (2), then the D colour channels.
constexpr int kGradFixed = 8;

// Per-thread scratch of the forward tile kernel; grows to the longest tile list it meets.
struct TileScratch {
    std::vector<Splat> splats;      // the tile's Gaussians in list order
    std::vector<float> colors;      // [n, D] their colours
    std::vector<float> ys, rys;     // [n] their mean2d y and Splat::ry, for the row masks
    std::vector<float> half_a;      // [n] 0.5 * conic a
    std::vector<float> row_terms;   // [n, 2, kTile] per tile row: b dy and 0.5 c dy^2 (dy = y - row centre)
    std::vector<uint32_t> masks;    // [n] tile rows (and row halves) each one reaches
    std::vector<int32_t> row_list;  // [2 kTile, row_stride] per tile row (half), the list positions of those reaching it
    int row_stride = 0;             // room per row: the list length plus a vector of slack
    std::vector<float> acc;         // D * kTile floats (colour sums for any channel count)
    void reserve(int n, int64_t d) {
        const size_t un = static_cast<size_t>(n);
        if (splats.size() < un) {
            const size_t padded = (un + 15) / 16 * 16;  // whole vectors for the row-mask loop
            splats.resize(un);
            ys.resize(padded);
            rys.resize(padded);
            half_a.resize(un);
            row_terms.resize(un * 2 * kTile);
            masks.resize(padded);
            row_stride = static_cast<int>(padded) + 16;
            row_list.resize(static_cast<size_t>(row_stride) * 2 * kTile);
        }
        if (colors.size() < un * static_cast<size_t>(d)) colors.resize(un * static_cast<size_t>(d));
        if (acc.size() < static_cast<size_t>(d) * kTile) acc.resize(static_cast<size_t>(d) * kTile);
    }
};

// Per-tile kernels come in one version per channel count c = 1..kMaxChannelsFixed (loops
// over channels unrolled, accumulators in registers) and one for any count (kernels.h).
constexpr int kMaxChannelsFixed = 5;
inline int kernel_for(int64_t channels) { return channels <= kMaxChannelsFixed ? static_cast<int>(channels) : 0; }

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

// Sorts the visible Gaussians by depth, makes their depth-ranked copies and bins them into
// tiles ([N] sort keys).
TileBins bin_gaussians(const RasterInputs& in, const float* depths);

// Composites one image. Outputs: colours [H, W, D], alphas [H, W], last_ids [H, W] (index
// into bins.ids of the last Gaussian composited at each pixel, -1 if none), rows
// [n_isects] (per tile-list entry, the tile rows, or with kernels narrower than a tile row the
// row halves, where it composited a pixel; the backward visits only those).
void rasterize_forward(const RasterInputs& in, const TileBins& bins, float* out_colors,
                       float* out_alphas, int32_t* last_ids, uint32_t* rows);

// Gradients for one image, given the forward outputs and dL/d(colours [H,W,D], alphas [H,W]).
// Outputs (overwritten): means2d [N,2], conics [N,3], colors [N,D], opacities [N] and,
// when grad_abs_means2d is not null, the per-pixel sums of |dL/dmeans2d| [N,2].
void rasterize_backward(const RasterInputs& in, const TileBinsView& bins, const float* out_alphas,
                        const int32_t* last_ids, const uint32_t* rows, const float* grad_colors,
                        const float* grad_alphas,
                        float* grad_means2d, float* grad_conics, float* grad_colors_out,
                        float* grad_opacities, float* grad_abs_means2d);

}  // namespace promptgs
