// torch bindings of the CPU kernels: the SH colours (sh.cpp), the EWA projection (project.cpp), the tile binning
// (bin.cpp), the Gaussian tile rasterizer (kernel.cpp) and the photometric loss (loss.cpp).
#include <torch/extension.h>

#include <vector>

#include "bin.h"
#include "kernel.h"
#include "loss.h"
#include "project.h"
#include "sh.h"

namespace {

RasterInputs make_inputs(const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& opacities,
                         const torch::Tensor& features, const torch::Tensor& offsets, const torch::Tensor& ids,
                         int64_t width, int64_t height) {
  for (const auto* t : {&means2d, &conics, &opacities, &features}) {
    TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == torch::kFloat32 && t->is_contiguous(),
                "rasterizer inputs must be contiguous float32 CPU tensors");
  }
  const int64_t n = means2d.size(0);
  TORCH_CHECK(means2d.sizes() == torch::IntArrayRef({n, 2}) && conics.sizes() == torch::IntArrayRef({n, 3}) &&
                  opacities.sizes() == torch::IntArrayRef({n}) &&
                  features.sizes() == torch::IntArrayRef({n, kRasterFeatures}),
              "expected means2d [N,2], conics [N,3], opacities [N], features [N,", kRasterFeatures, "]");
  TORCH_CHECK(offsets.scalar_type() == torch::kInt32 && ids.scalar_type() == torch::kInt32 &&
                  offsets.is_contiguous() && ids.is_contiguous(),
              "tile offsets and Gaussian ids must be contiguous int32");
  const int64_t num_tiles = ((width + 15) / 16) * ((height + 15) / 16);
  TORCH_CHECK(offsets.numel() == num_tiles + 1, "tile offsets must have num_tiles + 1 entries");
  return {means2d.data_ptr<float>(), conics.data_ptr<float>(), opacities.data_ptr<float>(), features.data_ptr<float>(),
          offsets.data_ptr<int32_t>(), ids.data_ptr<int32_t>(), n, static_cast<int>(width), static_cast<int>(height)};
}

ProjectInputs make_project_inputs(const torch::Tensor& means, const torch::Tensor& quats, const torch::Tensor& scales,
                                  const torch::Tensor& opacities, const torch::Tensor& viewmat, const torch::Tensor& k,
                                  int64_t width, int64_t height, double eps2d, double near) {
  for (const auto* t : {&means, &quats, &scales, &opacities, &viewmat, &k}) {
    TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == torch::kFloat32 && t->is_contiguous(),
                "projection inputs must be contiguous float32 CPU tensors");
  }
  const int64_t n = means.size(0);
  TORCH_CHECK(means.sizes() == torch::IntArrayRef({n, 3}) && quats.sizes() == torch::IntArrayRef({n, 4}) &&
                  scales.sizes() == torch::IntArrayRef({n, 3}) && opacities.sizes() == torch::IntArrayRef({n}) &&
                  viewmat.sizes() == torch::IntArrayRef({4, 4}) && k.sizes() == torch::IntArrayRef({3, 3}),
              "expected means [N,3], quats [N,4], scales [N,3], opacities [N], viewmat [4,4], K [3,3]");
  return {means.data_ptr<float>(), quats.data_ptr<float>(), scales.data_ptr<float>(), opacities.data_ptr<float>(),
          viewmat.data_ptr<float>(), k.data_ptr<float>(), n, static_cast<int>(width), static_cast<int>(height),
          static_cast<float>(eps2d), static_cast<float>(near)};
}

}  // namespace

// Returns {means2d [N, 2], conics [N, 3], depths [N], radii [N] int32, extents [N, 2]}.
std::vector<torch::Tensor> project_forward_binding(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                                   torch::Tensor opacities, torch::Tensor viewmat, torch::Tensor k,
                                                   int64_t width, int64_t height, double eps2d, double near,
                                                   int64_t num_threads) {
  const ProjectInputs in = make_project_inputs(means, quats, scales, opacities, viewmat, k, width, height, eps2d, near);
  const int64_t n = in.num_gaussians;
  auto means2d = torch::empty({n, 2}, means.options());
  auto conics = torch::empty({n, 3}, means.options());
  auto depths = torch::empty({n}, means.options());
  auto radii = torch::empty({n}, means.options().dtype(torch::kInt32));
  auto extents = torch::empty({n, 2}, means.options());
  project_forward(in, means2d.data_ptr<float>(), conics.data_ptr<float>(), depths.data_ptr<float>(),
                  radii.data_ptr<int32_t>(), extents.data_ptr<float>(), static_cast<int>(num_threads));
  return {means2d, conics, depths, radii, extents};
}

// Returns the gradients {means [N, 3], quats [N, 4], scales [N, 3]}.
std::vector<torch::Tensor> project_backward_binding(torch::Tensor means, torch::Tensor quats, torch::Tensor scales,
                                                    torch::Tensor opacities, torch::Tensor viewmat, torch::Tensor k,
                                                    int64_t width, int64_t height, double eps2d, double near,
                                                    torch::Tensor grad_means2d, torch::Tensor grad_conics,
                                                    torch::Tensor grad_depths, int64_t num_threads) {
  const ProjectInputs in = make_project_inputs(means, quats, scales, opacities, viewmat, k, width, height, eps2d, near);
  grad_means2d = grad_means2d.to(torch::kFloat32).contiguous();
  grad_conics = grad_conics.to(torch::kFloat32).contiguous();
  grad_depths = grad_depths.to(torch::kFloat32).contiguous();
  auto grad_means = torch::empty_like(means), grad_quats = torch::empty_like(quats);
  auto grad_scales = torch::empty_like(scales);
  project_backward(in, grad_means2d.data_ptr<float>(), grad_conics.data_ptr<float>(), grad_depths.data_ptr<float>(),
                   grad_means.data_ptr<float>(), grad_quats.data_ptr<float>(), grad_scales.data_ptr<float>(),
                   static_cast<int>(num_threads));
  return {grad_means, grad_quats, grad_scales};
}

namespace {

void check_sh_inputs(const torch::Tensor& sh, const torch::Tensor& means, const torch::Tensor& campos, int64_t degree) {
  for (const auto* t : {&sh, &means, &campos}) {
    TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == torch::kFloat32 && t->is_contiguous(),
                "SH colour inputs must be contiguous float32 CPU tensors");
  }
  const int64_t n = means.size(0);
  TORCH_CHECK(sh.dim() == 3 && sh.size(0) == n && sh.size(2) == 3 && means.sizes() == torch::IntArrayRef({n, 3}) &&
                  campos.numel() == 3, "expected sh [N,K,3], means [N,3], campos [3]");
  TORCH_CHECK(degree >= 0 && degree <= 3 && sh.size(1) >= (degree + 1) * (degree + 1),
              "SH degree must be 0..3 with (degree + 1)^2 coefficients");
}

}  // namespace

// Returns colors [N, 3].
torch::Tensor sh_colors_forward_binding(torch::Tensor sh, torch::Tensor means, torch::Tensor campos, int64_t degree,
                                        int64_t num_threads) {
  check_sh_inputs(sh, means, campos, degree);
  auto colors = torch::empty_like(means);
  sh_colors_forward(sh.data_ptr<float>(), means.data_ptr<float>(), campos.data_ptr<float>(), means.size(0),
                    static_cast<int>(sh.size(1)), static_cast<int>(degree), colors.data_ptr<float>(),
                    static_cast<int>(num_threads));
  return colors;
}

// Returns the gradients {sh [N, K, 3], means [N, 3]}.
std::vector<torch::Tensor> sh_colors_backward_binding(torch::Tensor sh, torch::Tensor means, torch::Tensor campos,
                                                      int64_t degree, torch::Tensor grad_colors, int64_t num_threads) {
  check_sh_inputs(sh, means, campos, degree);
  grad_colors = grad_colors.to(torch::kFloat32).contiguous();
  auto grad_sh = torch::empty_like(sh), grad_means = torch::empty_like(means);
  sh_colors_backward(sh.data_ptr<float>(), means.data_ptr<float>(), campos.data_ptr<float>(), means.size(0),
                     static_cast<int>(sh.size(1)), static_cast<int>(degree), grad_colors.data_ptr<float>(),
                     grad_sh.data_ptr<float>(), grad_means.data_ptr<float>(), static_cast<int>(num_threads));
  return {grad_sh, grad_means};
}

// Returns {offsets [num_tiles + 1] int32, Gaussian ids [P] int32}: binning.py's TileBins.
std::vector<torch::Tensor> bin_forward(torch::Tensor means2d, torch::Tensor extents, torch::Tensor depths,
                                       torch::Tensor radii, int64_t width, int64_t height) {
  for (const auto* t : {&means2d, &extents, &depths}) {
    TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == torch::kFloat32 && t->is_contiguous(),
                "binning inputs must be contiguous float32 CPU tensors");
  }
  TORCH_CHECK(radii.scalar_type() == torch::kInt32 && radii.is_contiguous(), "radii must be contiguous int32");
  const int64_t n = means2d.size(0);
  TORCH_CHECK(extents.sizes() == means2d.sizes() && depths.numel() == n && radii.numel() == n,
              "expected means2d [N,2], extents [N,2], depths [N], radii [N]");
  std::vector<int32_t> offsets, ids;
  bin_tiles(means2d.data_ptr<float>(), extents.data_ptr<float>(), depths.data_ptr<float>(), radii.data_ptr<int32_t>(),
            n, static_cast<int>(width), static_cast<int>(height), offsets, ids);
  auto options = torch::TensorOptions().dtype(torch::kInt32);
  return {torch::from_blob(offsets.data(), {static_cast<int64_t>(offsets.size())}, options).clone(),
          torch::from_blob(ids.data(), {static_cast<int64_t>(ids.size())}, options).clone()};
}

// Returns {features [H, W, 4] (no background), transmittance [H, W], walked [H, W] int32}.
std::vector<torch::Tensor> rasterize_forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                             torch::Tensor features, torch::Tensor offsets, torch::Tensor ids,
                                             int64_t width, int64_t height, int64_t num_threads) {
  const RasterInputs in = make_inputs(means2d, conics, opacities, features, offsets, ids, width, height);
  auto image = torch::empty({height, width, kRasterFeatures}, means2d.options());  // the kernel writes every pixel
  auto trans = torch::empty({height, width}, means2d.options());
  auto walked = torch::empty({height, width}, offsets.options());
  raster_forward(in, image.data_ptr<float>(), trans.data_ptr<float>(), walked.data_ptr<int32_t>(),
                 static_cast<int>(num_threads));
  return {image, trans, walked};
}

// Returns the gradients {means2d [N, 2], conics [N, 3], opacities [N], features [N, 4]}.
std::vector<torch::Tensor> rasterize_backward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                              torch::Tensor features, torch::Tensor offsets, torch::Tensor ids,
                                              torch::Tensor trans, torch::Tensor walked, torch::Tensor grad_image,
                                              torch::Tensor grad_trans, int64_t width, int64_t height,
                                              int64_t num_threads) {
  const RasterInputs in = make_inputs(means2d, conics, opacities, features, offsets, ids, width, height);
  grad_image = grad_image.to(torch::kFloat32).contiguous();
  grad_trans = grad_trans.to(torch::kFloat32).contiguous();
  auto total = torch::empty({in.num_gaussians, kRasterGradStride}, means2d.options());
  raster_backward(in, trans.data_ptr<float>(), walked.data_ptr<int32_t>(), grad_image.data_ptr<float>(),
                  grad_trans.data_ptr<float>(), total.data_ptr<float>(), static_cast<int>(num_threads));
  return {total.slice(1, 0, 2).contiguous(), total.slice(1, 2, 5).contiguous(), total.select(1, 5).contiguous(),
          total.slice(1, 6, 6 + kRasterFeatures).contiguous()};
}

// Returns {loss (float64 scalar), d loss / d prediction [H, W, C]} of two float32 images [H, W, C].
std::vector<torch::Tensor> photometric_loss_forward(torch::Tensor prediction, torch::Tensor target, torch::Tensor window,
                                                    double lambda, int64_t num_threads) {
  for (const auto* t : {&prediction, &target, &window}) {
    TORCH_CHECK(t->device().is_cpu() && t->scalar_type() == torch::kFloat32 && t->is_contiguous(),
                "photometric loss inputs must be contiguous float32 CPU tensors");
  }
  TORCH_CHECK(prediction.dim() == 3 && prediction.sizes() == target.sizes(), "expected two images [H, W, C]");
  TORCH_CHECK(window.dim() == 1 && window.size(0) % 2 == 1, "the window must be 1-D with an odd length");
  const int64_t radius = window.size(0) / 2;
  TORCH_CHECK(prediction.size(0) > radius && prediction.size(1) > radius,
              "reflect padding needs images larger than the window's radius");
  auto grad = torch::empty_like(prediction);
  const double loss = photometric_loss(prediction.data_ptr<float>(), target.data_ptr<float>(),
                                       static_cast<int>(prediction.size(0)), static_cast<int>(prediction.size(1)),
                                       static_cast<int>(prediction.size(2)), window.data_ptr<float>(),
                                       static_cast<int>(radius), static_cast<float>(lambda), grad.data_ptr<float>(),
                                       static_cast<int>(num_threads));
  return {torch::tensor(loss, torch::kFloat64), grad};
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("sh_colors_forward", &sh_colors_forward_binding, "view-dependent SH colours (CPU)");
  m.def("sh_colors_backward", &sh_colors_backward_binding, "view-dependent SH colours backward (CPU)");
  m.def("project_forward", &project_forward_binding, "EWA projection of 3D Gaussians (CPU)");
  m.def("project_backward", &project_backward_binding, "EWA projection backward (CPU)");
  m.def("bin", &bin_forward, "tile binning of projected Gaussians (CPU)");
  m.def("forward", &rasterize_forward, "Gaussian tile rasterizer forward (CPU)");
  m.def("backward", &rasterize_backward, "Gaussian tile rasterizer backward (CPU)");
  m.def("photometric_loss", &photometric_loss_forward, "(1 - lambda) L1 + lambda D-SSIM and its gradient (CPU)");
}
