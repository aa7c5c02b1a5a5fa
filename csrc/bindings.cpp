// Python bindings of the CPU rasterizer (module promptgs_engine._C).
//
// Both passes take one image; the Python side (promptgs_engine/render/cpu.py) loops over
// cameras. The forward returns what it built (tile_offsets, tile_ids of depth ranks,
// tile_order = Gaussian index of each rank, tile_rows = the tile rows each entry composited,
// the depth-ranked Gaussian data and colours) so the backward reuses it.
#include <torch/extension.h>

#include <omp.h>

#include <map>
#include <string>

#include "carve.h"
#include "project.h"
#include "kernels.h"
#include "rasterize.h"
#include "ssim.h"
#include "stage_times.h"

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

// A tensor that takes over a vector's memory (no copy).
template <typename T>
Tensor vector_to_tensor(std::vector<T>&& v, std::vector<int64_t> shape, torch::ScalarType dtype) {
    auto* owned = new std::vector<T>(std::move(v));
    if (owned->empty()) {
        delete owned;
        return torch::empty(shape, torch::TensorOptions().dtype(dtype));
    }
    return torch::from_blob(
        owned->data(), shape, [owned](void*) { delete owned; }, torch::TensorOptions().dtype(dtype));
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
    Tensor rows;
    {
        pybind11::gil_scoped_release no_gil;
        bins = promptgs::bin_gaussians(in, depths.data_ptr<float>());
    }
    rows = torch::empty({static_cast<int64_t>(bins.ids.size())}, torch::TensorOptions().dtype(torch::kInt32));
    {
        pybind11::gil_scoped_release no_gil;
        promptgs::rasterize_forward(in, bins, out_colors.data_ptr<float>(), out_alphas.data_ptr<float>(),
                                    last_ids.data_ptr<int32_t>(), reinterpret_cast<uint32_t*>(rows.data_ptr<int32_t>()));
    }
    const int64_t m = static_cast<int64_t>(bins.order.size()), n_isects = static_cast<int64_t>(bins.ids.size());
    const int64_t n_offsets = static_cast<int64_t>(bins.offsets.size());
    return {out_colors,
            out_alphas,
            last_ids,
            vector_to_tensor(std::move(bins.offsets), {n_offsets}, torch::kInt32),
            vector_to_tensor(std::move(bins.ids), {n_isects}, torch::kInt32),
            vector_to_tensor(std::move(bins.order), {m}, torch::kInt32),
            rows,
            vector_to_tensor(std::move(bins.splats), {m, promptgs::kSplatFloats}, torch::kFloat32),
            vector_to_tensor(std::move(bins.colors), {m, in.d}, torch::kFloat32)};
}

std::vector<Tensor> backward(int64_t n, Tensor background, int64_t width, int64_t height, Tensor tile_offsets,
                             Tensor tile_ids, Tensor tile_order, Tensor tile_rows, Tensor splats, Tensor sorted_colors,
                             Tensor out_alphas, Tensor last_ids, Tensor grad_colors, Tensor grad_alphas, bool absgrad) {
    TORCH_CHECK(sorted_colors.dim() == 2, "sorted_colors must be [M, D]");
    const int64_t N = n, D = sorted_colors.size(1), M = tile_order.numel();
    promptgs::TileBinsView bins;
    bins.tiles_x = static_cast<int>((width + promptgs::kTile - 1) / promptgs::kTile);
    bins.tiles_y = static_cast<int>((height + promptgs::kTile - 1) / promptgs::kTile);
    check(tile_offsets, "tile_offsets", torch::kInt32, {static_cast<int64_t>(bins.tiles_x) * bins.tiles_y + 1});
    check(tile_ids, "tile_ids", torch::kInt32, {-1});
    check(tile_order, "tile_order", torch::kInt32, {M});
    TORCH_CHECK(M <= N, "tile_order has more entries than Gaussians");
    check(tile_rows, "tile_rows", torch::kInt32, {tile_ids.numel()});
    check(splats, "splats", torch::kFloat32, {M, promptgs::kSplatFloats});
    check(sorted_colors, "sorted_colors", torch::kFloat32, {M, D});
    if (background.numel() > 0) check(background, "background", torch::kFloat32, {D});
    check(out_alphas, "out_alphas", torch::kFloat32, {height, width, 1});
    check(last_ids, "last_ids", torch::kInt32, {height, width});
    check(grad_colors, "grad_colors", torch::kFloat32, {height, width, D});
    // empty: no gradient reached the alphas (zeros)
    if (grad_alphas.numel() > 0) check(grad_alphas, "grad_alphas", torch::kFloat32, {height, width, 1});
    TORCH_CHECK(tile_offsets.data_ptr<int32_t>()[tile_offsets.numel() - 1] == tile_ids.numel(),
                "tile_offsets do not match tile_ids");
    bins.m = M;
    bins.offsets = tile_offsets.data_ptr<int32_t>();
    bins.ids = tile_ids.data_ptr<int32_t>();
    bins.order = tile_order.data_ptr<int32_t>();
    bins.splats = reinterpret_cast<const promptgs::Splat*>(splats.data_ptr<float>());
    bins.colors = sorted_colors.data_ptr<float>();
    promptgs::RasterInputs in{};
    in.background = background.numel() > 0 ? background.data_ptr<float>() : nullptr;
    in.n = N;
    in.d = D;
    in.width = static_cast<int>(width);
    in.height = static_cast<int>(height);

    auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
    Tensor g_means2d = torch::empty({N, 2}, f32);
    Tensor g_conics = torch::empty({N, 3}, f32);
    Tensor g_colors = torch::empty({N, D}, f32);
    Tensor g_opac = torch::empty({N}, f32);
    Tensor g_abs = absgrad ? torch::empty({N, 2}, f32) : torch::empty({0}, f32);
    {
        pybind11::gil_scoped_release no_gil;
        promptgs::rasterize_backward(in, bins, out_alphas.data_ptr<float>(), last_ids.data_ptr<int32_t>(),
                                     reinterpret_cast<const uint32_t*>(tile_rows.data_ptr<int32_t>()),
                                     grad_colors.data_ptr<float>(),
                                     grad_alphas.numel() > 0 ? grad_alphas.data_ptr<float>() : nullptr,
                                     g_means2d.data_ptr<float>(), g_conics.data_ptr<float>(),
                                     g_colors.data_ptr<float>(), g_opac.data_ptr<float>(),
                                     absgrad ? g_abs.data_ptr<float>() : nullptr);
    }
    return {g_means2d, g_conics, g_colors, g_opac, g_abs};
}

promptgs::Camera make_camera(const Tensor& viewmat, const Tensor& K, int64_t width, int64_t height, double near_plane,
                             double far_plane, double eps2d) {
    check(viewmat, "viewmat", torch::kFloat32, {4, 4});
    check(K, "K", torch::kFloat32, {3, 3});
    const float* v = viewmat.data_ptr<float>();
    const float* k = K.data_ptr<float>();
    promptgs::Camera cam;
    for (int r = 0; r < 3; ++r) {
        for (int c = 0; c < 3; ++c) cam.R[3 * r + c] = v[4 * r + c];
        cam.t[r] = v[4 * r + 3];
    }
    cam.fx = k[0];
    cam.fy = k[4];
    cam.cx = k[2];
    cam.cy = k[5];
    cam.width = static_cast<int>(width);
    cam.height = static_cast<int>(height);
    cam.near_plane = static_cast<float>(near_plane);
    cam.far_plane = static_cast<float>(far_plane);
    cam.eps2d = static_cast<float>(eps2d);
    return cam;
}

promptgs::ProjectInputs make_project_inputs(const Tensor& means, const Tensor& quats, const Tensor& scales,
                                            const Tensor& opacities, const Tensor& sh, const Tensor& sh_rest,
                                            int64_t sh_degree) {
    const int64_t N = means.size(0);
    check(means, "means", torch::kFloat32, {N, 3});
    check(quats, "quats", torch::kFloat32, {N, 4});
    check(scales, "scales", torch::kFloat32, {N, 3});
    check(opacities, "opacities", torch::kFloat32, {N});
    promptgs::ProjectInputs in;
    in.means = means.data_ptr<float>();
    in.quats = quats.data_ptr<float>();
    in.scales = scales.data_ptr<float>();
    in.opacities = opacities.data_ptr<float>();
    in.n = N;
    in.sh = nullptr;
    in.sh_rest = nullptr;
    in.sh_k = 0;
    in.sh_degree = 0;
    if (sh.numel() > 0 || sh.dim() == 3) {
        TORCH_CHECK(sh_degree >= 0 && sh_degree <= 3, "sh_degree must be in 0..3, got ", sh_degree);
        check(sh, "sh", torch::kFloat32, {N, -1, 3});
        in.sh = sh.data_ptr<float>();
        in.sh_k = static_cast<int>(sh.size(1));
        in.sh_degree = static_cast<int>(sh_degree);
        if (sh_rest.numel() > 0) {  // sh holds the first coefficient, sh_rest the others
            check(sh, "sh", torch::kFloat32, {N, 1, 3});
            check(sh_rest, "sh_rest", torch::kFloat32, {N, -1, 3});
            in.sh_rest = sh_rest.data_ptr<float>();
            in.sh_k = static_cast<int>(1 + sh_rest.size(1));
        }
        TORCH_CHECK(in.sh_k >= (sh_degree + 1) * (sh_degree + 1), "sh_degree ", sh_degree, " needs ",
                    (sh_degree + 1) * (sh_degree + 1), " SH coefficients, got ", in.sh_k);
    }
    return in;
}

// One Camera per row of viewmats [C,4,4] and Ks [C,3,3].
std::vector<promptgs::Camera> make_cameras(const Tensor& viewmats, const Tensor& Ks, int64_t width, int64_t height,
                                           double near_plane, double far_plane, double eps2d) {
    TORCH_CHECK(viewmats.dim() == 3 && viewmats.size(0) > 0, "viewmats must be [C, 4, 4], got ", viewmats.sizes());
    TORCH_CHECK(Ks.dim() == 3 && Ks.size(0) == viewmats.size(0), "Ks must be [C, 3, 3] with viewmats' C, got ",
                Ks.sizes());
    std::vector<promptgs::Camera> cams;
    for (int64_t c = 0; c < viewmats.size(0); ++c)
        cams.push_back(make_camera(viewmats[c], Ks[c], width, height, near_plane, far_plane, eps2d));
    return cams;
}

std::vector<Tensor> project_fwd(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor sh,
                                int64_t sh_degree, Tensor viewmats, Tensor Ks, int64_t width, int64_t height,
                                double near_plane, double far_plane, double eps2d, Tensor sh_rest) {
    promptgs::ProjectInputs in = make_project_inputs(means, quats, scales, opacities, sh, sh_rest, sh_degree);
    const std::vector<promptgs::Camera> cams = make_cameras(viewmats, Ks, width, height, near_plane, far_plane, eps2d);
    const int64_t N = in.n, C = static_cast<int64_t>(cams.size());
    auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
    Tensor means2d = torch::empty({C, N, 2}, f32);
    Tensor conics = torch::empty({C, N, 3}, f32);
    Tensor depths = torch::empty({C, N}, f32);
    Tensor radii = torch::empty({C, N, 2}, torch::TensorOptions().dtype(torch::kInt32));
    Tensor colors = in.sh ? torch::empty({C, N, 3}, f32) : torch::empty({0}, f32);
    {
        pybind11::gil_scoped_release no_gil;
        promptgs::project_forward(in, cams.data(), C, means2d.data_ptr<float>(), conics.data_ptr<float>(),
                                  depths.data_ptr<float>(), radii.data_ptr<int32_t>(),
                                  in.sh ? colors.data_ptr<float>() : nullptr);
    }
    return {means2d, conics, depths, radii, colors};
}

std::vector<Tensor> project_bwd(Tensor means, Tensor quats, Tensor scales, Tensor opacities, Tensor sh,
                                int64_t sh_degree, Tensor viewmats, Tensor Ks, int64_t width, int64_t height,
                                double near_plane, double far_plane, double eps2d, Tensor radii, Tensor v_means2d,
                                Tensor v_conics, Tensor v_depths, Tensor v_colors, Tensor sh_rest) {
    promptgs::ProjectInputs in = make_project_inputs(means, quats, scales, opacities, sh, sh_rest, sh_degree);
    const std::vector<promptgs::Camera> cams = make_cameras(viewmats, Ks, width, height, near_plane, far_plane, eps2d);
    const int64_t N = in.n, C = static_cast<int64_t>(cams.size());
    check(radii, "radii", torch::kInt32, {C, N, 2});
    check(v_means2d, "v_means2d", torch::kFloat32, {C, N, 2});
    check(v_conics, "v_conics", torch::kFloat32, {C, N, 3});
    check(v_depths, "v_depths", torch::kFloat32, {C, N});
    const bool has_vc = in.sh && v_colors.numel() > 0;
    if (has_vc) check(v_colors, "v_colors", torch::kFloat32, {C, N, 3});
    auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
    // The sums, and (with several cameras) one camera's gradients before they are added.
    auto grads = [&](int64_t n) {
        return std::vector<Tensor>{
            torch::empty({n, 3}, f32), torch::empty({n, 4}, f32), torch::empty({n, 3}, f32),
            in.sh ? torch::empty({n, in.sh_rest ? 1 : in.sh_k, 3}, f32) : torch::empty({0}, f32),
            in.sh_rest ? torch::empty({n, in.sh_k - 1, 3}, f32) : torch::empty({0}, f32)};
    };
    auto pointers = [&](std::vector<Tensor>& g) {
        return promptgs::ProjectGrads{g[0].data_ptr<float>(), g[1].data_ptr<float>(), g[2].data_ptr<float>(),
                                      has_vc ? g[3].data_ptr<float>() : nullptr,
                                      has_vc && in.sh_rest ? g[4].data_ptr<float>() : nullptr};
    };
    std::vector<Tensor> out = grads(N), scratch = grads(C > 1 ? N : 0);
    if (in.sh && !has_vc) {
        out[3].zero_();
        out[4].zero_();
    }
    {
        pybind11::gil_scoped_release no_gil;
        promptgs::project_backward(in, cams.data(), C, radii.data_ptr<int32_t>(), v_means2d.data_ptr<float>(),
                                   v_conics.data_ptr<float>(), v_depths.data_ptr<float>(),
                                   has_vc ? v_colors.data_ptr<float>() : nullptr, pointers(out),
                                   C > 1 ? pointers(scratch) : promptgs::ProjectGrads{});
    }
    return out;
}

promptgs::SsimShape ssim_shape(const Tensor& img, const Tensor& ref, const Tensor& window) {
    TORCH_CHECK(img.dim() == 4, "img must be [B, H, W, C], got ", img.sizes());
    check(img, "img", torch::kFloat32, {img.size(0), img.size(1), img.size(2), img.size(3)});
    check(ref, "ref", torch::kFloat32, {img.size(0), img.size(1), img.size(2), img.size(3)});
    check(window, "window", torch::kFloat32, {-1});
    TORCH_CHECK(window.numel() % 2 == 1, "the SSIM window needs an odd number of taps");
    return {img.size(0), img.size(1), img.size(2), img.size(3), static_cast<int>(window.numel() / 2)};
}

std::vector<Tensor> ssim_fwd(Tensor img, Tensor ref, Tensor window, bool need_grad) {
    const promptgs::SsimShape s = ssim_shape(img, ref, window);
    auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
    Tensor ssim = torch::empty_like(img);
    Tensor partials =
        need_grad ? torch::empty({3, s.batch, s.height, s.width, s.channels}, f32) : torch::empty({0}, f32);
    {
        pybind11::gil_scoped_release no_gil;
        promptgs::ssim_forward(s, img.data_ptr<float>(), ref.data_ptr<float>(), window.data_ptr<float>(),
                               ssim.data_ptr<float>(), need_grad ? partials.data_ptr<float>() : nullptr);
    }
    return {ssim, partials};
}

Tensor ssim_bwd(Tensor grad, Tensor partials, Tensor img, Tensor ref, Tensor window) {
    const promptgs::SsimShape s = ssim_shape(img, ref, window);
    check(grad, "grad", torch::kFloat32, {s.batch, s.height, s.width, s.channels});
    check(partials, "partials", torch::kFloat32, {3, s.batch, s.height, s.width, s.channels});
    Tensor grad_img = torch::empty_like(img);
    {
        pybind11::gil_scoped_release no_gil;
        promptgs::ssim_backward(s, grad.data_ptr<float>(), partials.data_ptr<float>(), img.data_ptr<float>(),
                                ref.data_ptr<float>(), window.data_ptr<float>(), grad_img.data_ptr<float>());
    }
    return grad_img;
}

std::vector<Tensor> photometric_fwd(Tensor img, Tensor ref, Tensor window) {
    const promptgs::SsimShape s = ssim_shape(img, ref, window);
    auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
    Tensor l1 = torch::empty({s.batch, s.height, s.width}, f32);
    Tensor dssim = torch::empty({s.batch, s.height, s.width}, f32);
    Tensor partials = torch::empty({3, s.batch, s.height, s.width, s.channels}, f32);
    {
        pybind11::gil_scoped_release no_gil;
        promptgs::photometric_forward(s, img.data_ptr<float>(), ref.data_ptr<float>(), window.data_ptr<float>(),
                                      l1.data_ptr<float>(), dssim.data_ptr<float>(), partials.data_ptr<float>());
    }
    return {l1, dssim, partials};
}

Tensor photometric_bwd(double ssim_grad, double l1_grad, Tensor partials, Tensor img, Tensor ref, Tensor window) {
    const promptgs::SsimShape s = ssim_shape(img, ref, window);
    check(partials, "partials", torch::kFloat32, {3, s.batch, s.height, s.width, s.channels});
    Tensor grad_img = torch::empty_like(img);
    {
        pybind11::gil_scoped_release no_gil;
        promptgs::photometric_backward(s, static_cast<float>(ssim_grad), static_cast<float>(l1_grad),
                                       partials.data_ptr<float>(), img.data_ptr<float>(), ref.data_ptr<float>(),
                                       window.data_ptr<float>(), grad_img.data_ptr<float>());
    }
    return grad_img;
}

std::vector<Tensor> carve_votes(Tensor points, Tensor world_to_camera, Tensor K, Tensor err, double threshold,
                                Tensor worst, Tensor seen, Tensor hits) {
    const int64_t n = points.size(0);
    check(points, "points", torch::kFloat32, {n, 3});
    check(world_to_camera, "world_to_camera", torch::kFloat32, {4, 4});
    check(K, "K", torch::kFloat32, {3, 3});
    check(err, "err", torch::kFloat32, {-1, -1});
    check(worst, "worst", torch::kInt64, {err.size(0), err.size(1)});
    check(seen, "seen", torch::kFloat32, {n});
    check(hits, "hits", torch::kFloat32, {n});
    const promptgs::CarveView view{world_to_camera.data_ptr<float>(), K.data_ptr<float>(), err.size(1), err.size(0)};
    std::vector<int64_t> index, pixel;
    {
        pybind11::gil_scoped_release no_gil;
        promptgs::carve_votes(n, points.data_ptr<float>(), view, err.data_ptr<float>(), static_cast<float>(threshold),
                              worst.data_ptr<int64_t>(), seen.data_ptr<float>(), hits.data_ptr<float>(), index,
                              pixel);
    }
    auto i64 = torch::TensorOptions().dtype(torch::kInt64);
    const int64_t k = static_cast<int64_t>(index.size());
    return {torch::from_blob(index.data(), {k}, i64).clone(), torch::from_blob(pixel.data(), {k}, i64).clone()};
}

int num_threads() { return omp_get_max_threads(); }

std::map<std::string, double> stage_times(bool reset, bool cpu) {
    std::map<std::string, double> out;
    double(*seconds)[promptgs::kStageCount] = promptgs::stage_seconds();
    for (int s = 0; s < promptgs::kStageCount; ++s) {
        out[promptgs::stage_name(s)] = seconds[cpu ? 1 : 0][s];
        if (reset) seconds[0][s] = seconds[1][s] = 0.0;
    }
    return out;
}

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
    m.doc() = "PromptGS CPU rasterizer: tile-based 3D Gaussian splatting forward and backward (OpenMP)";
    m.def("rasterize_forward", &forward,
          "Composite one image: (means2d, conics, colors, opacities, depths, radii, background, width, height) -> "
          "[colors HxWxD, alphas HxWx1, last_ids HxW, tile_offsets, tile_ids, tile_order, tile_rows int32, "
          "splats Mx8, sorted_colors MxD].");
    m.def("rasterize_backward", &backward,
          "Gradients of one image: (n_gaussians, background, width, height, then the forward's tile_offsets, "
          "tile_ids, tile_order, tile_rows, splats, sorted_colors, alphas, last_ids, then dL/dcolors, dL/dalphas "
          "(empty for zeros), absgrad) -> [means2d Nx2, conics Nx3, colors NxD, opacities N, absgrad Nx2 or empty].");
    m.def("project_forward", &project_fwd,
          "EWA projection (+ SH colours) for C cameras: (means, quats, scales, opacities, sh or empty, sh_degree, "
          "viewmats Cx4x4, Ks Cx3x3, width, height, near, far, eps2d, sh_rest or empty) -> [means2d CxNx2, "
          "conics CxNx3, depths CxN, radii CxNx2 int32, colors CxNx3 or empty]; with sh_rest [N,K-1,3], sh [N,1,3] "
          "holds only the first SH coefficient.");
    m.def("project_backward", &project_bwd,
          "Gradients of project_forward's outputs (its arguments, radii, v_means2d, v_conics, v_depths, v_colors, "
          "sh_rest), summed over the C cameras in camera order -> [v_means, v_quats, v_scales, v_sh or empty, "
          "v_sh_rest or empty].");
    m.def("stage_times", &stage_times, pybind11::arg("reset") = false, pybind11::arg("cpu") = false,
          "Seconds spent in each stage of the C++ passes since the last reset, {stage: seconds}: wall time, or "
          "with cpu=True the CPU time of the calling thread (resetting clears both).");
    m.def("ssim_forward", &ssim_fwd,
          "Per-pixel SSIM of img against ref ([B,H,W,C] float32) with a separable window (odd taps, zero "
          "padding): (img, ref, window, need_grad) -> [ssim BxHxWxC, partials for ssim_backward or empty].");
    m.def("ssim_backward", &ssim_bwd,
          "dL/dimg from (dL/dssim, partials, img, ref, window) of ssim_forward.");
    m.def("photometric_forward", &photometric_fwd,
          "The 3DGS loss's per-pixel maps of img against ref ([B,H,W,C] float32): (img, ref, window) -> "
          "[channel mean of |img - ref| BxHxW, channel mean of 1 - SSIM BxHxW, partials for photometric_backward].");
    m.def("photometric_backward", &photometric_bwd,
          "dL/dimg from (dL/dSSIM at every element, the factor of sgn(img - ref), partials, img, ref, window): the "
          "SSIM part as ssim_backward gives it for that constant gradient, plus the L1 part.");
    m.def("carve_votes", &carve_votes,
          "Resampling's vote in one view: (points [N,3], world_to_camera [4,4], K [3,3] float32, dilated error [H,W] "
          "float32, threshold, worst pixel [H,W] int64, seen [N], hits [N] float32, both added to) -> [indices of the "
          "points that hit, their worst pixels], in point order.");
    m.def("num_threads", &num_threads, "OpenMP threads the rasterizer uses.");
    m.def("simd_variant", [] { return std::string(promptgs::kernels().name); },
          "Instruction set of the kernels picked for this CPU (avx512, avx2, sse2 or native; PROMPTGS_SIMD caps it).");
}
