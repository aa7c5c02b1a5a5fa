// EWA projection of 3D Gaussians and SH colour evaluation for one camera, forward and
// backward, in plain C++ (parallel over Gaussians with OpenMP).
//
// Same conventions as promptgs_engine/render/projection.py and sh.py (which stay the
// reference): world-to-camera [R|t], pinhole K, the Jacobian evaluated at the mean clamped
// to 1.3x the field of view, the 0.3 low-pass dilation, conic = inverse 2D covariance as
// (a, b, c), opacity-aware integer radii (0 = culled: depth outside (near, far), singular
// covariance, opacity < 1/255, or box outside the image), SH with the 3DGS constants,
// colour = max(SH + 0.5, 0) with the view direction from the camera centre to the mean.
#pragma once

#include <cstdint>

namespace promptgs {

struct Camera {
    float R[9];  // world-to-camera rotation, row-major
    float t[3];
    float fx, fy, cx, cy;
    int width, height;
    float near_plane, far_plane, eps2d;
};

struct ProjectInputs {
    const float* means;      // [N, 3]
    const float* quats;      // [N, 4] wxyz, any norm
    const float* scales;     // [N, 3]
    const float* opacities;  // [N]
    const float* sh;         // [N, K, 3] or nullptr (no colour evaluation); [N, 1, 3] with sh_rest
    const float* sh_rest;    // [N, K - 1, 3]: coefficients 1.. kept apart from the first, or nullptr
    int64_t n;
    int sh_k;                // K, coefficients per Gaussian in sh
    int sh_degree;           // 0..3, uses (degree + 1)^2 of the K coefficients
};

// Outputs: means2d [N,2], conics [N,3], depths [N], radii [N,2]; colors [N,3] when sh is set.
void project_forward(const ProjectInputs& in, const Camera& cam, float* means2d, float* conics, float* depths,
                     int32_t* radii, float* colors);

// Gradients of the projection outputs (v_colors may be nullptr) to means [N,3], quats [N,4],
// scales [N,3] and, when sh is set, the SH coefficients [N,K,3] (with sh_rest: v_sh [N,1,3]
// and v_sh_rest [N,K-1,3]). Outputs are overwritten; culled Gaussians get zeros.
void project_backward(const ProjectInputs& in, const Camera& cam, const int32_t* radii, const float* v_means2d,
                      const float* v_conics, const float* v_depths, const float* v_colors, float* v_means,
                      float* v_quats, float* v_scales, float* v_sh, float* v_sh_rest);

}  // namespace promptgs
