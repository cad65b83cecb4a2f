// torch bindings of the CPU Gaussian tile rasterizer kernels (kernel.cpp).
#include <torch/extension.h>

#include <vector>

#include "kernel.h"

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

}  // namespace

// Returns {features [H, W, 4] (no background), transmittance [H, W], walked [H, W] int32}.
std::vector<torch::Tensor> rasterize_forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opacities,
                                             torch::Tensor features, torch::Tensor offsets, torch::Tensor ids,
                                             int64_t width, int64_t height, int64_t num_threads) {
  const RasterInputs in = make_inputs(means2d, conics, opacities, features, offsets, ids, width, height);
  auto image = torch::zeros({height, width, kRasterFeatures}, means2d.options());
  auto trans = torch::ones({height, width}, means2d.options());
  auto walked = torch::zeros({height, width}, offsets.options());
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

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &rasterize_forward, "Gaussian tile rasterizer forward (CPU)");
  m.def("backward", &rasterize_backward, "Gaussian tile rasterizer backward (CPU)");
}
