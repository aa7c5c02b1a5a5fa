// EWA projection and SH colours, forward and backward (see project.h): the threads split the
// Gaussians into contiguous ranges, the same for every camera, and each range runs the
// vectorised kernels of project_kernels.inc for the CPU's instruction set, kVW Gaussians at
// a time.
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

// dst[rows begin..end) += src[the same rows], `width` floats a row.
inline void add_rows(float* dst, const float* src, int64_t begin, int64_t end, int64_t width) {
    for (int64_t i = begin * width; i < end * width; ++i) dst[i] += src[i];
}

}  // namespace

void project_forward(const ProjectInputs& in, const Camera* cams, int64_t n_cams, float* means2d, float* conics,
                     float* depths, int32_t* radii, float* colors) {
    StageTimer timer(kStageProjectForward);
    const Kernels::ProjectForward fn = kernels().project_forward;
    const int64_t n = in.n;
    for_each_range(n, [&](int64_t begin, int64_t end) {
        for (int64_t c = 0; c < n_cams; ++c) {
            float campos[3];
            camera_center(cams[c], campos);
            fn(in, cams[c], campos, begin, end, means2d + 2 * n * c, conics + 3 * n * c, depths + n * c,
               radii + 2 * n * c, colors ? colors + 3 * n * c : nullptr);
        }
    });
}

void project_backward(const ProjectInputs& in, const Camera* cams, int64_t n_cams, const int32_t* radii,
                      const float* v_means2d, const float* v_conics, const float* v_depths, const float* v_colors,
                      const ProjectGrads& out, const ProjectGrads& scratch) {
    StageTimer timer(kStageProjectBackward);
    const Kernels::ProjectBackward fn = kernels().project_backward;
    const int64_t n = in.n;
    const int64_t sh_width = 3 * (in.sh_rest ? 1 : in.sh_k), rest_width = in.sh_rest ? 3 * (in.sh_k - 1) : 0;
    // Each thread takes the same Gaussians for every camera, so a camera's gradients are
    // added to the sums by the thread that computed both: no barrier between cameras.
    for_each_range(n, [&](int64_t begin, int64_t end) {
        for (int64_t c = 0; c < n_cams; ++c) {
            const ProjectGrads& g = c == 0 ? out : scratch;
            float campos[3];
            camera_center(cams[c], campos);
            fn(in, cams[c], campos, begin, end, radii + 2 * n * c, v_means2d + 2 * n * c, v_conics + 3 * n * c,
               v_depths ? v_depths + n * c : nullptr, v_colors ? v_colors + 3 * n * c : nullptr, g.means, g.quats,
               g.scales, g.sh, g.sh_rest);
            if (c == 0) continue;
            add_rows(out.means, g.means, begin, end, 3);
            add_rows(out.quats, g.quats, begin, end, 4);
            add_rows(out.scales, g.scales, begin, end, 3);
            if (out.sh) add_rows(out.sh, g.sh, begin, end, sh_width);
            if (out.sh_rest) add_rows(out.sh_rest, g.sh_rest, begin, end, rest_width);
        }
    });
}

}  // namespace promptgs
