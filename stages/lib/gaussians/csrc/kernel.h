// Interface of the CPU Gaussian tile rasterizer kernels (plain C++, raw float32/int32 arrays).
#pragma once

#include <cstdint>

constexpr int kRasterFeatures = 4;  // RGB + camera depth
constexpr int kRasterGradStride = 2 + 3 + 1 + kRasterFeatures;  // d means2d, conic, opacity, features

struct RasterInputs {
  const float* means2d;    // [N, 2] pixel positions
  const float* conics;     // [N, 3] (a, b, c): q = a dx^2 + 2 b dx dy + c dy^2
  const float* opacities;  // [N]
  const float* features;   // [N, 4]
  const int32_t* offsets;  // [num_tiles + 1] per-tile ranges into ids
  const int32_t* ids;      // [P] Gaussian indices, front to back within a tile
  int64_t num_gaussians;
  int width, height;
};

// o_feat [H, W, 4] (no background), o_trans [H, W] final transmittance, o_last [H, W] number of
// tile-list entries walked up to the last contributing Gaussian.
void raster_forward(const RasterInputs& in, float* o_feat, float* o_trans, int32_t* o_last, int num_threads);

// grad_out [N, 10] = d loss / (means2d, conics, opacities, features), given the forward's
// transmittance and walk lengths and d loss / (features image [H, W, 4], transmittance [H, W]).
void raster_backward(const RasterInputs& in, const float* trans_final, const int32_t* last_walked,
                     const float* grad_feat, const float* grad_trans, float* grad_out, int num_threads);
