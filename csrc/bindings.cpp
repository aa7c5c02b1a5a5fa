// Python bindings of the CPU rasterizer (module promptgs_engine._C).
//
// Both passes take one image; the Python side (promptgs_engine/render/cpu.py) loops over
// cameras. The forward returns the tile lists it built (tile_offsets, tile_ids of depth
// ranks, tile_order = Gaussian index of each rank) so the backward reuses them.
#include <torch/extension.h>

#include <omp.h>

#include "rasterize.h"

namespace {

using torch::Tensor;

void check(const Tensor& t, const char* name, torch::ScalarType dtype, std::initializer_list<int64_t> shape) {
    TORCH_CHECK(t.device().is_cpu(), name, " must be a CPU tensor");
    TORCH_CHECK(t.scalar_type() == dtype, name, " has dtype ", t.scalar_type(), ", expected ", dtype);
    TORCH_CHECK(t.is_contiguous(), name, " must be contiguous");
    TORCH_CHECK(t.dim() == static_cast<int64_t>(shape.size()), name, " must have ", shape.size(), " dimensions, got ",
                t.sizes());
    int64_t i = 0;
    for (int64_t s : shape) {
        TORCH_CHECK(s < 0 || t.size(i) == s, name, " has shape ", t.sizes(), ", dimension ", i, " should be ", s);
        ++i;
    }
}

promptgs::RasterInputs make_inputs(const Tensor& means2d, const Tensor& conics, const Tensor& colors,
                                   const Tensor& opacities, const Tensor& radii, const Tensor& background,
                                   int64_t width, int64_t height) {
    const int64_t N = means2d.size(0);
    TORCH_CHECK(colors.dim() == 2, "colors must be [N, D]");
    const int64_t D = colors.size(1);
    check(means2d, "means2d", torch::kFloat32, {N, 2});
    check(conics, "conics", torch::kFloat32, {N, 3});
    check(colors, "colors", torch::kFloat32, {N, D});
    check(opacities, "opacities", torch::kFloat32, {N});
    check(radii, "radii", torch::kInt32, {N, 2});
    if (background.numel() > 0) check(background, "background", torch::kFloat32, {D});
    TORCH_CHECK(width > 0 && height > 0 && width <= (1 << 20) && height <= (1 << 20), "bad image size ", width, "x",
                height);
    TORCH_CHECK(N < (int64_t(1) << 31), "too many Gaussians for the CPU rasterizer: ", N);
    promptgs::RasterInputs in;
    in.means2d = means2d.data_ptr<float>();
    in.conics = conics.data_ptr<float>();
    in.colors = colors.data_ptr<float>();
    in.opacities = opacities.data_ptr<float>();
    in.radii = radii.data_ptr<int32_t>();
    in.background = background.numel() > 0 ? background.data_ptr<float>() : nullptr;
    in.n = N;
    in.d = D;
    in.width = static_cast<int>(width);
    in.height = static_cast<int>(height);
    return in;
}

Tensor vector_to_tensor(const std::vector<int32_t>& v) {
    Tensor t = torch::empty({static_cast<int64_t>(v.size())}, torch::TensorOptions().dtype(torch::kInt32));
    if (!v.empty()) std::memcpy(t.data_ptr<int32_t>(), v.data(), v.size() * sizeof(int32_t));
    return t;
}

std::vector<Tensor> forward(Tensor means2d, Tensor conics, Tensor colors, Tensor opacities, Tensor depths,
                            Tensor radii, Tensor background, int64_t width, int64_t height) {
    promptgs::RasterInputs in = make_inputs(means2d, conics, colors, opacities, radii, background, width, height);
    check(depths, "depths", torch::kFloat32, {in.n});
    auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
    Tensor out_colors = torch::empty({height, width, in.d}, f32);
    Tensor out_alphas = torch::empty({height, width, 1}, f32);
    Tensor last_ids = torch::empty({height, width}, torch::TensorOptions().dtype(torch::kInt32));
    promptgs::TileBins bins;
    {
        pybind11::gil_scoped_release no_gil;
        bins = promptgs::bin_gaussians(in, depths.data_ptr<float>());
        promptgs::rasterize_forward(in, bins, out_colors.data_ptr<float>(), out_alphas.data_ptr<float>(),
                                    last_ids.data_ptr<int32_t>());
    }
    return {out_colors, out_alphas, last_ids, vector_to_tensor(bins.offsets), vector_to_tensor(bins.ids),
            vector_to_tensor(bins.order)};
}

std::vector<Tensor> backward(Tensor means2d, Tensor conics, Tensor colors, Tensor opacities, Tensor radii,
                             Tensor background, int64_t width, int64_t height, Tensor tile_offsets, Tensor tile_ids,
                             Tensor tile_order, Tensor out_alphas, Tensor last_ids, Tensor grad_colors, Tensor grad_alphas,
                             bool absgrad) {
    promptgs::RasterInputs in = make_inputs(means2d, conics, colors, opacities, radii, background, width, height);
    const int64_t N = in.n, D = in.d;
    promptgs::TileBins bins;
    bins.tiles_x = static_cast<int>((width + promptgs::kTile - 1) / promptgs::kTile);
    bins.tiles_y = static_cast<int>((height + promptgs::kTile - 1) / promptgs::kTile);
    check(tile_offsets, "tile_offsets", torch::kInt32, {static_cast<int64_t>(bins.tiles_x) * bins.tiles_y + 1});
    check(tile_ids, "tile_ids", torch::kInt32, {-1});
    check(tile_order, "tile_order", torch::kInt32, {-1});
    TORCH_CHECK(tile_order.numel() <= N, "tile_order has more entries than Gaussians");
    check(out_alphas, "out_alphas", torch::kFloat32, {height, width, 1});
    check(last_ids, "last_ids", torch::kInt32, {height, width});
    check(grad_colors, "grad_colors", torch::kFloat32, {height, width, D});
    check(grad_alphas, "grad_alphas", torch::kFloat32, {height, width, 1});
    bins.offsets.assign(tile_offsets.data_ptr<int32_t>(), tile_offsets.data_ptr<int32_t>() + tile_offsets.numel());
    bins.ids.assign(tile_ids.data_ptr<int32_t>(), tile_ids.data_ptr<int32_t>() + tile_ids.numel());
    bins.order.assign(tile_order.data_ptr<int32_t>(), tile_order.data_ptr<int32_t>() + tile_order.numel());
    TORCH_CHECK(bins.offsets.back() == static_cast<int32_t>(bins.ids.size()), "tile_offsets do not match tile_ids");

    auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
    Tensor g_means2d = torch::empty({N, 2}, f32);
    Tensor g_conics = torch::empty({N, 3}, f32);
    Tensor g_colors = torch::empty({N, D}, f32);
    Tensor g_opac = torch::empty({N}, f32);
    Tensor g_abs = absgrad ? torch::empty({N, 2}, f32) : torch::empty({0}, f32);
    {
        pybind11::gil_scoped_release no_gil;
        promptgs::rasterize_backward(in, bins, out_alphas.data_ptr<float>(), last_ids.data_ptr<int32_t>(),
                                     grad_colors.data_ptr<float>(), grad_alphas.data_ptr<float>(),
                                     g_means2d.data_ptr<float>(), g_conics.data_ptr<float>(),
                                     g_colors.data_ptr<float>(), g_opac.data_ptr<float>(),
                                     absgrad ? g_abs.data_ptr<float>() : nullptr);
    }
    return {g_means2d, g_conics, g_colors, g_opac, g_abs};
}

int num_threads() { return omp_get_max_threads(); }

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "PromptGS CPU rasterizer: tile-based 3D Gaussian splatting forward and backward (OpenMP)";
    m.def("rasterize_forward", &forward,
          "Composite one image: (means2d, conics, colors, opacities, depths, radii, background, width, height) -> "
          "[colors HxWxD, alphas HxWx1, last_ids HxW, tile_offsets, tile_ids, tile_order].");
    m.def("rasterize_backward", &backward,
          "Gradients of one image -> [means2d Nx2, conics Nx3, colors NxD, opacities N, absgrad Nx2 or empty].");
    m.def("num_threads", &num_threads, "OpenMP threads the rasterizer uses.");
}
