// Resampling's vote in one view (see carve.h): one pass over the points instead of the
// score of tensor operations its torch expression takes, in point chunks over the OpenMP
// threads, whose hits are joined in chunk order.
#include "carve.h"

#include <omp.h>

#include <cmath>

namespace promptgs {

void carve_votes(int64_t n, const float* u, const float* v, const float* z, int64_t width, int64_t height,
                 const float* err, float threshold, const int64_t* worst, float* seen, float* hits,
                 std::vector<int64_t>& hit_index, std::vector<int64_t>& hit_pixel) {
    const float w = static_cast<float>(width), h = static_cast<float>(height);
    const int chunks = omp_get_max_threads();
    std::vector<std::vector<int64_t>> index(chunks), pixel(chunks);
#pragma omp parallel for schedule(static, 1)
    for (int c = 0; c < chunks; ++c) {
        const int64_t i0 = n * c / chunks, i1 = n * (c + 1) / chunks;
        for (int64_t i = i0; i < i1; ++i) {
            if (!(z[i] > 1e-3f && u[i] >= 0.f && u[i] < w && v[i] >= 0.f && v[i] < h)) continue;
            seen[i] += 1.f;
            const int64_t p = static_cast<int64_t>(std::floor(v[i])) * width + static_cast<int64_t>(std::floor(u[i]));
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
