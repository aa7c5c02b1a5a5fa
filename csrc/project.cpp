// EWA projection and SH colours, forward and backward (see project.h): the threads split the
// Gaussians into contiguous ranges, and each range runs the vectorised kernels of
// project_kernels.inc for the CPU's instruction set, kVW Gaussians at a time.
#include "project.h"

#include <omp.h>

#include <algorithm>

#include "kernels.h"
#include "stage_times.h"

namespace promptgs {

namespace {

inline void camera_center(const Camera& cam, float c[3]) {
    for (int j = 0; j < 3; ++j) c[j] = -(cam.R[j] * cam.t[0] + cam.R[3 + j] * cam.t[1] + cam.R[6 + j] * cam.t[2]);
}

// Thread t of n gets Gaussians [n_total * t / n, n_total * (t + 1) / n), rounded to whole
// blocks of 16 so that every vector but the last is full.
template <typename Fn>
void for_each_range(int64_t n_total, Fn fn) {
#pragma omp parallel
    {
        const int64_t t = omp_get_thread_num(), n = omp_get_num_threads();
        const int64_t blocks = (n_total + 15) / 16;
        const int64_t begin = std::min(n_total, blocks * t / n * 16), end = std::min(n_total, blocks * (t + 1) / n * 16);
        if (begin < end) fn(begin, end);
    }
}

}  // namespace

void project_forward(const ProjectInputs& in, const Camera& cam, float* means2d, float* conics, float* depths,
                     int32_t* radii, float* colors) {
    StageTimer timer(kStageProjectForward);
    float campos[3];
    camera_center(cam, campos);
    const Kernels::ProjectForward fn = kernels().project_forward;
    for_each_range(in.n, [&](int64_t begin, int64_t end) {
        fn(in, cam, campos, begin, end, means2d, conics, depths, radii, colors);
    });
}

void project_backward(const ProjectInputs& in, const Camera& cam, const int32_t* radii, const float* v_means2d,
                      const float* v_conics, const float* v_depths, const float* v_colors, float* v_means,
                      float* v_quats, float* v_scales, float* v_sh, float* v_sh_rest) {
    StageTimer timer(kStageProjectBackward);
    float campos[3];
    camera_center(cam, campos);
    const Kernels::ProjectBackward fn = kernels().project_backward;
    for_each_range(in.n, [&](int64_t begin, int64_t end) {
        fn(in, cam, campos, begin, end, radii, v_means2d, v_conics, v_depths, v_colors, v_means, v_quats, v_scales,
           v_sh, v_sh_rest);
    });
}

}  // namespace promptgs
