// EWA projection of 3D Gaussians and SH colour evaluation for C cameras, forward and
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

// Gradients of the projection, one array per parameter (see project_backward).
struct ProjectGrads {
    float* means;    // [N, 3]
    float* quats;    // [N, 4]
    float* scales;   // [N, 3]
    float* sh;       // [N, K, 3] ([N, 1, 3] with sh_rest), or nullptr: no colour gradients
    float* sh_rest;  // [N, K - 1, 3] or nullptr
};

// For cams[0..n_cams): outputs of camera c at c·N rows: means2d [C,N,2], conics [C,N,3],
// depths [C,N], radii [C,N,2]; colors [C,N,3] when sh is set.
void project_forward(const ProjectInputs& in, const Camera* cams, int64_t n_cams, float* means2d, float* conics,
                     float* depths, int32_t* radii, float* colors);

// Gradients of the projection outputs of cams[0..n_cams) (inputs laid out as
// project_forward's outputs; v_colors may be nullptr) to means, quats, scales and, when
// out.sh is set, the SH coefficients, summed over the cameras in camera order (camera 0's,
// then each next camera's added). Outputs are overwritten; culled Gaussians add zeros.
// With more than one camera, `scratch` holds one camera's gradients (the same layout as
// `out`) before they are added.
void project_backward(const ProjectInputs& in, const Camera* cams, int64_t n_cams, const int32_t* radii,
                      const float* v_means2d, const float* v_conics, const float* v_depths, const float* v_colors,
                      const ProjectGrads& out, const ProjectGrads& scratch);

}  // namespace promptgs
