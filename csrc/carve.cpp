// Resampling's vote in one view (see carve.h): the projection and the vote in one pass over
// the points instead of the score of tensor operations their torch expression takes, in
// point chunks over the OpenMP threads, whose hits are joined in chunk order. The
// projection runs kVW points at a time in the CPU's vector kernels (carve_kernels.inc).
#include "carve.h"

#include <omp.h>

#include <algorithm>

#include "kernels.h"

namespace promptgs {

void carve_votes(int64_t n, const float* points, const CarveView& view, const float* err, float threshold,
                 const int64_t* worst, float* seen, float* hits, std::vector<int64_t>& hit_index,
                 std::vector<int64_t>& hit_pixel) {
    const Kernels::CarvePixels project = kernels().carve_pixels;
    constexpr int64_t kBlock = 4096;  // points projected at a time, their pixels kept in cache for the vote
    const int chunks = omp_get_max_threads();
    std::vector<std::vector<int64_t>> index(chunks), pixel(chunks);
#pragma omp parallel for schedule(static, 1)
    for (int c = 0; c < chunks; ++c) {
        const int64_t i0 = n * c / chunks, i1 = n * (c + 1) / chunks;
        std::vector<int32_t> at(kBlock);
        for (int64_t b = i0; b < i1; b += kBlock) {
            const int64_t count = std::min(kBlock, i1 - b);
            project(count, points + 3 * b, view.world_to_camera, view.K, view.width, view.height, at.data());
            for (int64_t j = 0; j < count; ++j) {
                const int32_t p = at[j];
                if (p < 0) continue;
                const int64_t i = b + j;
                seen[i] += 1.f;
                if (err[p] > threshold) {
                    hits[i] += 1.f;
                    index[c].push_back(i);
                    pixel[c].push_back(worst[p]);
                }
            }
        }
    }
    for (int c = 0; c < chunks; ++c) {
        hit_index.insert(hit_index.end(), index[c].begin(), index[c].end());
        hit_pixel.insert(hit_pixel.end(), pixel[c].begin(), pixel[c].end());
    }
}

}  // namespace promptgs
