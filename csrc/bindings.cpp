// Python bindings of the CPU rasterizer (module promptgs_engine._C).
#include <omp.h>

#include "rasterize.h"

namespace {

void check_input(const torch::Tensor& t, const char* name, torch::ScalarType dtype, int64_t rows, int64_t cols) {
    TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
    TORCH_CHECK(t.scalar_type() == dtype, name, " has dtype ", t.scalar_type(), ", expected ", dtype);
    TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
    if (rows >= 0) TORCH_CHECK(t.size(0) == rows, name, " has ", t.size(0), " rows, expected ", rows);
    if (cols >= 0) {
        TORCH_CHECK(t.dim() == 2 && t.size(1) == cols, name, " must have shape [", rows, ", ", cols, "]");
    }
}

std::vector<torch::Tensor> forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor colors,
                                   torch::Tensor opacities, torch::Tensor depths, torch::Tensor radii,
                                   torch::Tensor background, int64_t width, int64_t height) {
    const int64_t N = means2d.size(0);
    TORCH_CHECK(colors.dim() == 2, "colors must be [N, D]");
    const int64_t D = colors.size(1);
    check_input(means2d, "means2d", torch::kFloat32, N, 2);
    check_input(conics, "conics", torch::kFloat32, N, 3);
    check_input(colors, "colors", torch::kFloat32, N, D);
    check_input(opacities, "opacities", torch::kFloat32, N, -1);
    check_input(depths, "depths", torch::kFloat32, N, -1);
    check_input(radii, "radii", torch::kInt32, N, 2);
    if (background.numel() > 0) {
        check_input(background, "background", torch::kFloat32, D, -1);
    }
    TORCH_CHECK(width > 0 && height > 0 && width < 32768 * 16 && height < 32768 * 16, "bad image size");
    TORCH_CHECK(N < (int64_t(1) << 31), "too many Gaussians");
    return promptgs::rasterize_forward(means2d, conics, colors, opacities, depths, radii, background, width,
                                       height);
}

std::vector<torch::Tensor> backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor colors,
                                    torch::Tensor opacities, torch::Tensor radii, torch::Tensor background,
                                    int64_t width, int64_t height, torch::Tensor tile_offsets,
                                    torch::Tensor tile_ids, torch::Tensor out_alphas, torch::Tensor last_ids,
                                    torch::Tensor grad_colors, torch::Tensor grad_alphas, bool absgrad) {
    const int64_t N = means2d.size(0);
    const int64_t D = colors.size(1);
    check_input(means2d, "means2d", torch::kFloat32, N, 2);
    check_input(conics, "conics", torch::kFloat32, N, 3);
    check_input(colors, "colors", torch::kFloat32, N, D);
    check_input(opacities, "opacities", torch::kFloat32, N, -1);
    check_input(radii, "radii", torch::kInt32, N, 2);
    check_input(tile_offsets, "tile_offsets", torch::kInt32, -1, -1);
    check_input(tile_ids, "tile_ids", torch::kInt32, -1, -1);
    check_input(out_alphas, "out_alphas", torch::kFloat32, height, -1);
    check_input(last_ids, "last_ids", torch::kInt32, height, -1);
    check_input(grad_colors, "grad_colors", torch::kFloat32, height, -1);
    check_input(grad_alphas, "grad_alphas", torch::kFloat32, height, -1);
    TORCH_CHECK(grad_colors.numel() == height * width * D, "grad_colors must be [H, W, D]");
    TORCH_CHECK(grad_alphas.numel() == height * width, "grad_alphas must be [H, W, 1]");
    if (background.numel() > 0) {
        check_input(background, "background", torch::kFloat32, D, -1);
    }
    return promptgs::rasterize_backward(means2d, conics, colors, opacities, radii, background, width, height,
                                        tile_offsets, tile_ids, out_alphas, last_ids, grad_colors, grad_alphas,
                                        absgrad);
}

int num_threads() { return omp_get_max_threads(); }

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "PromptGS CPU rasterizer: tile-based 3D Gaussian splatting forward and backward (OpenMP)";
    m.def("rasterize_forward", &forward,
          "Composite one image. Returns [colors H×W×D, alphas H×W×1, last_ids H×W, tile_offsets, tile_ids].");
    m.def("rasterize_backward", &backward,
          "Gradients [means2d N×2, conics N×3, colors N×D, opacities N, absgrad N×2 or empty].");
    m.def("num_threads", &num_threads, "OpenMP threads the rasterizer uses.");
}
