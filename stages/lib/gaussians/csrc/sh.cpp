// View-dependent colours of 3D Gaussians on the CPU, forward and backward: sh.py's real spherical harmonics
// (3DGS's basis and signs, degree <= 3) evaluated at the direction from the camera to each Gaussian, plus 0.5,
// clamped at 0 (rasterize.py's gaussian_colors). The gradient reaches the coefficients and, through the
// direction, the means. One Gaussian per loop iteration: the bits do not depend on the thread count.
#include "sh.h"

#include <omp.h>

#include <algorithm>
#include <cmath>

namespace {

constexpr float kC0 = 0.28209479177387814f;
constexpr float kC1 = 0.4886025119029199f;
constexpr float kC2[5] = {1.0925484305920792f, -1.0925484305920792f, 0.31539156525252005f, -1.0925484305920792f,
                          0.5462742152960396f};
constexpr float kC3[7] = {-0.5900435899266435f, 2.890611442640554f, -0.4570457994644658f, 0.3731763325901154f,
                          -0.4570457994644658f, 1.445305721320277f, -0.5900435899266435f};
constexpr int kMaxBases = 16;

// The basis of bands 0..degree at the unit direction (x, y, z) into b, and with d its gradient (db / dx, dy, dz).
int basis(int degree, float x, float y, float z, float* b, float (*d)[3]) {
  const float xx = x * x, yy = y * y, zz = z * z;
  int count = 0;
  auto put = [&](float value, float dx, float dy, float dz) {
    b[count] = value;
    if (d != nullptr) d[count][0] = dx, d[count][1] = dy, d[count][2] = dz;
    ++count;
  };
  put(kC0, 0, 0, 0);
  if (degree >= 1) {
    put(-kC1 * y, 0, -kC1, 0);
    put(kC1 * z, 0, 0, kC1);
    put(-kC1 * x, -kC1, 0, 0);
  }
  if (degree >= 2) {
    put(kC2[0] * x * y, kC2[0] * y, kC2[0] * x, 0);
    put(kC2[1] * y * z, 0, kC2[1] * z, kC2[1] * y);
    put(kC2[2] * (2 * zz - xx - yy), -2 * kC2[2] * x, -2 * kC2[2] * y, 4 * kC2[2] * z);
    put(kC2[3] * x * z, kC2[3] * z, 0, kC2[3] * x);
    put(kC2[4] * (xx - yy), 2 * kC2[4] * x, -2 * kC2[4] * y, 0);
  }
  if (degree >= 3) {
    put(kC3[0] * y * (3 * xx - yy), 6 * kC3[0] * x * y, kC3[0] * (3 * xx - 3 * yy), 0);
    put(kC3[1] * x * y * z, kC3[1] * y * z, kC3[1] * x * z, kC3[1] * x * y);
    put(kC3[2] * y * (4 * zz - xx - yy), -2 * kC3[2] * x * y, kC3[2] * (4 * zz - xx - 3 * yy), 8 * kC3[2] * y * z);
    put(kC3[3] * z * (2 * zz - 3 * xx - 3 * yy), -6 * kC3[3] * x * z, -6 * kC3[3] * y * z,
        kC3[3] * (6 * zz - 3 * xx - 3 * yy));
    put(kC3[4] * x * (4 * zz - xx - yy), kC3[4] * (4 * zz - 3 * xx - yy), -2 * kC3[4] * x * y, 8 * kC3[4] * x * z);
    put(kC3[5] * z * (xx - yy), 2 * kC3[5] * x * z, -2 * kC3[5] * y * z, kC3[5] * (xx - yy));
    put(kC3[6] * x * (xx - 3 * yy), kC3[6] * (3 * xx - 3 * yy), -6 * kC3[6] * x * y, 0);
  }
  return count;
}

// The unit direction from campos to mean, and the length it was divided by (clamped like F.normalize).
float direction(const float* mean, const float* campos, float* dir) {
  for (int a = 0; a < 3; ++a) dir[a] = mean[a] - campos[a];
  const float norm = std::max(std::sqrt(dir[0] * dir[0] + dir[1] * dir[1] + dir[2] * dir[2]), 1e-12f);
  for (int a = 0; a < 3; ++a) dir[a] /= norm;
  return norm;
}

}  // namespace

void sh_colors_forward(const float* sh, const float* means, const float* campos, int64_t n, int k, int degree,
                       float* colors, int num_threads) {
#pragma omp parallel for schedule(static) num_threads(num_threads)
  for (int64_t g = 0; g < n; ++g) {
    float dir[3], b[kMaxBases];
    direction(means + 3 * g, campos, dir);
    const int count = basis(degree, dir[0], dir[1], dir[2], b, nullptr);
    const float* coeffs = sh + g * k * 3;
    for (int c = 0; c < 3; ++c) {
      float sum = 0.0f;
      for (int i = 0; i < count; ++i) sum += b[i] * coeffs[3 * i + c];
      colors[3 * g + c] = std::max(sum + 0.5f, 0.0f);
    }
  }
}

void sh_colors_backward(const float* sh, const float* means, const float* campos, int64_t n, int k, int degree,
                        const float* grad_colors, float* grad_sh, float* grad_means, int num_threads) {
#pragma omp parallel for schedule(static) num_threads(num_threads)
  for (int64_t g = 0; g < n; ++g) {
    float dir[3], b[kMaxBases], db[kMaxBases][3];
    const float norm = direction(means + 3 * g, campos, dir);
    const int count = basis(degree, dir[0], dir[1], dir[2], b, db);
    const float* coeffs = sh + g * k * 3;
    float gc[3];
    for (int c = 0; c < 3; ++c) {  // the clamp at 0 passes the gradient where the colour is >= 0
      float sum = 0.0f;
      for (int i = 0; i < count; ++i) sum += b[i] * coeffs[3 * i + c];
      gc[c] = sum + 0.5f >= 0.0f ? grad_colors[3 * g + c] : 0.0f;
    }
    float* gsh = grad_sh + g * k * 3;
    float gdir[3] = {0.0f, 0.0f, 0.0f};
    for (int i = 0; i < k; ++i) {
      float along = 0.0f;  // sum over channels of coefficient x colour gradient
      for (int c = 0; c < 3; ++c) {
        gsh[3 * i + c] = i < count ? b[i] * gc[c] : 0.0f;
        along += i < count ? coeffs[3 * i + c] * gc[c] : 0.0f;
      }
      if (i < count) {
        for (int a = 0; a < 3; ++a) gdir[a] += db[i][a] * along;
      }
    }
    // dir = v / |v|: d v = (d dir - dir (dir . d dir)) / |v|
    const float dot = dir[0] * gdir[0] + dir[1] * gdir[1] + dir[2] * gdir[2];
    for (int a = 0; a < 3; ++a) grad_means[3 * g + a] = (gdir[a] - dir[a] * dot) / norm;
  }
}
