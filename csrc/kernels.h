// The vectorised kernels of the CPU backend for one instruction set, picked once at load time
// from what the CPU supports (AVX-512, AVX2+FMA or the baseline SSE2; see kernels.cpp):
// the rasterizer's per-tile passes (tile_kernels.inc), the projection of Gaussians
// (project_kernels.inc), SSIM (ssim_kernels.inc) and resampling's vote (carve_kernels.inc).
#pragma once

#include "project.h"
#include "rasterize.h"
#include "ssim.h"

namespace promptgs {

struct Kernels {
    // Composites tile (x0, y0) from ranks ids[start, end).
    using Forward = void (*)(const TileArgs& a, const Splat* splats, const float* colors, int start, int end, int x0,
                             int y0, TileScratch& scratch);
    // Backward for tile (x0, y0); scratch dcol is D*256 floats, vcol D*16 floats; adds
    // per-rank gradients into G (stride kGradFixed + D). backward_abs also sums |dL/dmean2d|.
    using Backward = void (*)(const TileArgs& a, const Splat* splats, const float* colors, int start, int x0, int y0,
                              float* dcol, float* vcol, float* G);
    // Projection of Gaussians [begin, end) (see project.h for the outputs).
    using ProjectForward = void (*)(const ProjectInputs& in, const Camera& cam, const float campos[3], int64_t begin,
                                    int64_t end, float* means2d, float* conics, float* depths, int32_t* radii,
                                    float* colors);
    using ProjectBackward = void (*)(const ProjectInputs& in, const Camera& cam, const float campos[3], int64_t begin,
                                     int64_t end, const int32_t* radii, const float* v_means2d, const float* v_conics,
                                     const float* v_depths, const float* v_colors, float* v_means, float* v_quats,
                                     float* v_scales, float* v_sh, float* v_sh_rest);
    // SSIM of output rows [o0, o1) of one image, and the loss's per-pixel maps (see
    // ssim_kernels.inc).
    using SsimForwardBand = void (*)(const SsimShape& s, const float* x, const float* y, const float* w, int o0, int o1,
                                     float* value, float* p0, float* p1, float* p2, float* l1, float* dssim);
    using SsimBackwardBand = void (*)(const SsimShape& s, const float* g, float g_all, const float* p0,
                                      const float* p1, const float* p2, const float* x, const float* y,
                                      const float* w, int o0, int o1, bool with_l1, float l1_coef, float* grad);
    // Resampling's vote: the pixel of each of n points in one view, or -1 (carve_kernels.inc).
    using CarvePixels = void (*)(int64_t n, const float* points, const float* world_to_camera, const float* K,
                                 int64_t width, int64_t height, int32_t* pixel);
    // Entry c of forward/backward is specialised for c channels (c = 1..kMaxChannelsFixed);
    // entry 0 takes any channel count. Use kernel_for() to pick.
    Forward forward[kMaxChannelsFixed + 1];
    Backward backward[kMaxChannelsFixed + 1];
    Backward backward_abs[kMaxChannelsFixed + 1];
    ProjectForward project_forward;
    ProjectBackward project_backward;
    SsimForwardBand ssim_forward_band;
    SsimBackwardBand ssim_backward_band;
    CarvePixels carve_pixels;
    const char* name;
};
const Kernels& kernels();

}  // namespace promptgs
