// Exact backward pass of the CPU rasterizer.
//
// Each tile replays its Gaussians back to front, starting from the final transmittance
// saved by the forward pass and the per-pixel index of the last contributor, recovering
// T before each Gaussian as T / (1 - alpha). Gradients are summed per Gaussian within a
// tile (vector accumulators, see tile_kernels.inc), then added to a per-thread buffer
// indexed by depth rank; the buffers are reduced (and mapped back to Gaussian order) at
// the end, so no atomics are needed. Tiles go to threads in a fixed round-robin order, so
// each buffer adds the same tiles in the same order on every call: for a given number of
// threads the gradients are bit-for-bit reproducible (a dynamic schedule made them differ
// in the last bits between identical calls, and training runs of one seed diverge from that).
#include <omp.h>

#include <algorithm>
#include <cmath>

#include "kernels.h"
#include "rasterize.h"
#include "stage_times.h"

namespace promptgs {

void rasterize_backward(const RasterInputs& in, const TileBinsView& bins, const float* out_alphas,
                        const int32_t* last_ids, const uint32_t* rows, const float* grad_colors,
                        const float* grad_alphas,
                        float* grad_means2d, float* grad_conics, float* grad_colors_out, float* grad_opacities,
                        float* grad_abs_means2d) {
    const int64_t N = in.n, D = in.d;
    const int64_t M = bins.m;
    const int n_tiles = bins.tiles_x * bins.tiles_y;
    const int64_t stride = kGradFixed + D;
    const int n_threads = omp_get_max_threads();
    std::vector<std::vector<float>> thread_grads(n_threads);
    TileArgs args;
    args.ids = bins.ids;
    args.d = D;
    args.width = in.width;
    args.height = in.height;
    args.background = in.background;
    args.alphas = out_alphas;
    args.last_ids = last_ids;
    args.rows = rows;
    args.grad_colors = grad_colors;
    args.grad_alphas = grad_alphas;
    const Kernels::Backward backward =
        grad_abs_means2d ? kernels().backward_abs[kernel_for(D)] : kernels().backward[kernel_for(D)];

    StageTimer blend_timer(kStageBlendBackward);
#pragma omp parallel num_threads(n_threads)
    {
        std::vector<float>& gbuf = thread_grads[omp_get_thread_num()];
        gbuf.assign(static_cast<size_t>(M * stride), 0.f);
        std::vector<float> dcol(static_cast<size_t>(D) * kTilePixels);
        std::vector<float> vcol(static_cast<size_t>(D) * kTile);  // D * (lanes <= 16)
#pragma omp for schedule(static, 1)
        for (int tile = 0; tile < n_tiles; ++tile) {
            const int start = bins.offsets[tile], end = bins.offsets[tile + 1];
            if (start == end) continue;
            backward(args, bins.splats, bins.colors, start, (tile % bins.tiles_x) * kTile,
                             (tile / bins.tiles_x) * kTile, dcol.data(), vcol.data(), gbuf.data());
        }
    }
    blend_timer.stop();
    StageTimer reduce_timer(kStageReduce);
#pragma omp parallel num_threads(n_threads)
    {
#pragma omp for schedule(static)
        for (int64_t i = 0; i < N; ++i) {  // Gaussians that no tile saw get zero gradients
            grad_means2d[2 * i] = grad_means2d[2 * i + 1] = 0.f;
            grad_conics[3 * i] = grad_conics[3 * i + 1] = grad_conics[3 * i + 2] = 0.f;
            grad_opacities[i] = 0.f;
            if (grad_abs_means2d) grad_abs_means2d[2 * i] = grad_abs_means2d[2 * i + 1] = 0.f;
            for (int64_t k = 0; k < D; ++k) grad_colors_out[i * D + k] = 0.f;
        }
#pragma omp for schedule(static)
        for (int64_t j = 0; j < M; ++j) {  // reduce the thread buffers, back to Gaussian order
            const int64_t i = bins.order[j];
            float acc[kGradFixed] = {0.f, 0.f, 0.f, 0.f, 0.f, 0.f, 0.f, 0.f};
            for (int t = 0; t < n_threads; ++t) {
                if (thread_grads[t].empty()) continue;  // a thread the runtime did not start
                const float* Gg = thread_grads[t].data() + j * stride;
                for (int q = 0; q < kGradFixed; ++q) acc[q] += Gg[q];
            }
            grad_means2d[2 * i] = acc[0];
            grad_means2d[2 * i + 1] = acc[1];
            grad_conics[3 * i] = acc[2];
            grad_conics[3 * i + 1] = acc[3];
            grad_conics[3 * i + 2] = acc[4];
            grad_opacities[i] = acc[5];
            if (grad_abs_means2d) {
                grad_abs_means2d[2 * i] = acc[6];
                grad_abs_means2d[2 * i + 1] = acc[7];
            }
            for (int64_t k = 0; k < D; ++k) {
                float s = 0.f;
                for (int t = 0; t < n_threads; ++t)
                    if (!thread_grads[t].empty()) s += thread_grads[t][j * stride + kGradFixed + k];
                grad_colors_out[i * D + k] = s;
            }
        }
    }
}

}  // namespace promptgs
