// Resampling's vote in one view, for promptgs_engine/strategies/promptgs.py (`carve_prompt`,
// whose torch expression `view_votes_torch` stays the reference).
//
// A grid point is projected with the view's world-to-camera [R | t] and intrinsics K term
// by term, each product and sum rounded to float in this order (as the reference's torch
// operations round them): camera coordinate c = ((R[c,0] x + R[c,1] y) + R[c,2] z) + t[c],
// u = x_cam / max(z_cam, 1e-6) * fx + cx, v likewise. It is seen by the view when
// z_cam > 1e-3 and 0 <= u < width, 0 <= v < height, and hits when the dilated error at its
// pixel (floor(v) * width + floor(u)) is over the threshold. The comparisons are in float,
// as torch makes them between a float32 tensor and a Python number.
#pragma once

#include <cstdint>
#include <vector>

namespace promptgs {

// The view's projection: world_to_camera row-major [4, 4], K row-major [3, 3].
struct CarveView {
    const float* world_to_camera;
    const float* K;
    int64_t width, height;
};

// Adds 1 to seen[i] for every point (points: [n, 3] row-major) the view sees and to
// hits[i] for every point that hits, and returns the hits in point order: their indices and
// worst[pixel], the pixel the colour is read at.
void carve_votes(int64_t n, const float* points, const CarveView& view, const float* err, float threshold,
                 const int64_t* worst, float* seen, float* hits, std::vector<int64_t>& hit_index,
                 std::vector<int64_t>& hit_pixel);

}  // namespace promptgs
