// Resampling's vote in one view (see carve.h): the projection and the vote in one pass over
// the points instead of the score of tensor operations their torch expression takes, in
// point chunks over the OpenMP threads, whose hits are joined in chunk order.
#include "carve.h"

#include <omp.h>

#include <cmath>

// Every product and sum is rounded on its own, as the torch reference's operations round
// them: no fused multiply-add, whatever the build's -ffp-contract.
#if defined(__clang__)
#pragma clang fp contract(off)
#elif defined(__GNUC__)
#pragma GCC optimize("fp-contract=off")
#endif

namespace promptgs {

void carve_votes(int64_t n, const float* points, const CarveView& view, const float* err, float threshold,
                 const int64_t* worst, float* seen, float* hits, std::vector<int64_t>& hit_index,
                 std::vector<int64_t>& hit_pixel) {
    const float* m = view.world_to_camera;
    const float fx = view.K[0], cx = view.K[2], fy = view.K[4], cy = view.K[5];
    const int64_t width = view.width;
    const float w = static_cast<float>(view.width), h = static_cast<float>(view.height);
    const int chunks = omp_get_max_threads();
    std::vector<std::vector<int64_t>> index(chunks), pixel(chunks);
#pragma omp parallel for schedule(static, 1)
    for (int c = 0; c < chunks; ++c) {
        const int64_t i0 = n * c / chunks, i1 = n * (c + 1) / chunks;
        for (int64_t i = i0; i < i1; ++i) {
            const float x = points[3 * i], y = points[3 * i + 1], zw = points[3 * i + 2];
            const float z = m[8] * x + m[9] * y + m[10] * zw + m[11];
            const float zd = z < 1e-6f ? 1e-6f : z;  // torch's clamp_min: NaN stays NaN
            const float u = (m[0] * x + m[1] * y + m[2] * zw + m[3]) / zd * fx + cx;
            const float v = (m[4] * x + m[5] * y + m[6] * zw + m[7]) / zd * fy + cy;
            if (!(z > 1e-3f && u >= 0.f && u < w && v >= 0.f && v < h)) continue;
            seen[i] += 1.f;
            const int64_t p = static_cast<int64_t>(std::floor(v)) * width + static_cast<int64_t>(std::floor(u));
            if (err[p] > threshold) {
                hits[i] += 1.f;
                index[c].push_back(i);
                pixel[c].push_back(worst[p]);
            }
        }
    }
    for (int c = 0; c < chunks; ++c) {
        hit_index.insert(hit_index.end(), index[c].begin(), index[c].end());
        hit_pixel.insert(hit_pixel.end(), pixel[c].begin(), pixel[c].end());
    }
}

}  // namespace promptgs
