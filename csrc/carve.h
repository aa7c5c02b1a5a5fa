// Resampling's vote in one view, for promptgs_engine/strategies/promptgs.py (`carve_prompt`,
// whose torch expression `view_votes_torch` stays the reference).
//
// A grid point at continuous pixel (u, v) and depth z is seen by the view when
// z > 1e-3 and 0 <= u < width, 0 <= v < height, and hits when the dilated error at its
// pixel (floor(v) * width + floor(u)) is over the threshold. The comparisons are in float,
// as torch makes them between a float32 tensor and a Python number.
#pragma once

#include <cstdint>
#include <vector>

namespace promptgs {

// Adds 1 to seen[i] for every point the view sees and to hits[i] for every point that hits,
// and returns the hits in point order: their indices and worst[pixel], the pixel the
// colour is read at.
void carve_votes(int64_t n, const float* u, const float* v, const float* z, int64_t width, int64_t height,
                 const float* err, float threshold, const int64_t* worst, float* seen, float* hits,
                 std::vector<int64_t>& hit_index, std::vector<int64_t>& hit_pixel);

}  // namespace promptgs
