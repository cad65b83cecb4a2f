// CPU tile rasterizer kernels for 2D Gaussians (plain C++): forward and backward, OpenMP over tiles.
//
// Same compositing rules as the PyTorch reference (rasterize_torch.py) and 3DGS: front to back,
// alpha = min(0.99, o * exp(power)), power = -(a dx^2 + 2 b dx dy + c dy^2) / 2, contributions with
// alpha < 1/255 skipped, a pixel stops at the first Gaussian that would bring its transmittance
// below 1e-4. Pixel (u, v) samples at (u + 0.5, v + 0.5).
//
// Speed: one OpenMP task per tile; a tile row of 16 pixels is the vectorised inner loop
// (`omp simd`, a polynomial exp that vectorises without -ffast-math); each Gaussian visits only
// the tile rows where its alpha can reach 1/255; gradients go to per-thread buffers summed at the
// end. Features are F = 4 channels (RGB + camera depth); background is added by the caller.
#include "kernel.h"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstring>
#include <vector>

namespace {

constexpr int kTile = 16;
constexpr int kTilePixels = kTile * kTile;
constexpr int kFeat = kRasterFeatures;
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;
constexpr float kTransMin = 1e-4f;
constexpr int kGradStride = kRasterGradStride;

// exp(x) to ~2 ulp for -30 <= x <= 88 (Cephes expf polynomial), branch-free so `omp simd`
// vectorises it. Inputs below -30 give exp(-30): every caller discards alpha < 1/255 (x < -5.6),
// and the floor keeps o * exp(x) far from float denormals, whose microcode assists made the
// kernel ~10x slower.
#pragma omp declare simd notinbranch
inline float exp_vec(float x) {
  x = std::min(std::max(x, -30.0f), 88.0f);
  const float n = std::floor(x * 1.44269504088896341f + 0.5f);
  const float r = x - n * 0.693359375f + n * 2.12194440e-4f;
  float p = 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  const int32_t bits = (static_cast<int32_t>(n) + 127) << 23;
  float scale;
  std::memcpy(&scale, &bits, sizeof(float));
  return p * scale;
}

struct Splat {
  float mx, my, a, b, c, o;
};

// Tile rows [r0, r1] (local, inclusive) whose pixel centres lie inside the alpha >= 1/255 ellipse.
inline bool rows_reached(const Splat& s, int tile_y0, int height, int& r0, int& r1) {
  if (s.o < kAlphaMin) return false;
  const float reach = 2.0f * std::log(s.o * 255.0f);
  const float det = s.a * s.c - s.b * s.b;
  if (!(reach > 0.0f) || !(det > 0.0f)) return false;
  const float ey = std::sqrt(reach * s.a / det) + 1e-3f;  // (conic^-1)_yy = a / det
  r0 = std::max(0, static_cast<int>(std::ceil(s.my - ey - 0.5f)) - tile_y0);
  r1 = std::min({kTile - 1, height - 1 - tile_y0, static_cast<int>(std::floor(s.my + ey - 0.5f)) - tile_y0});
  return r0 <= r1;
}

inline Splat load_splat(const float* means2d, const float* conics, const float* opac, int64_t g) {
  return {means2d[2 * g], means2d[2 * g + 1], conics[3 * g], conics[3 * g + 1], conics[3 * g + 2], opac[g]};
}

}  // namespace

void raster_forward(const RasterInputs& in, float* o_feat, float* o_trans, int32_t* o_last, int num_threads) {
  const float* m2 = in.means2d;
  const float* con = in.conics;
  const float* op = in.opacities;
  const float* feat = in.features;
  const int32_t* off = in.offsets;
  const int32_t* gid = in.ids;
  const int w = in.width, h = in.height;
  const int tiles_x = (w + kTile - 1) / kTile;
  const int num_tiles = tiles_x * ((h + kTile - 1) / kTile);

#pragma omp parallel for schedule(dynamic, 1) num_threads(num_threads)
  for (int tile = 0; tile < num_tiles; ++tile) {
    const int begin = off[tile], end = off[tile + 1];
    if (begin == end) continue;
    const int x0 = (tile % tiles_x) * kTile, y0 = (tile / tiles_x) * kTile;
    alignas(64) float trans[kTilePixels], alive[kTilePixels], acc[kFeat][kTilePixels];
    alignas(64) int32_t last[kTilePixels];
    int num_alive = 0;
    for (int p = 0; p < kTilePixels; ++p) {
      const bool inside = x0 + p % kTile < w && y0 + p / kTile < h;
      trans[p] = 1.0f;
      alive[p] = inside ? 1.0f : 0.0f;
      num_alive += inside;
      last[p] = 0;
      for (int f = 0; f < kFeat; ++f) acc[f][p] = 0.0f;
    }
    for (int k = begin; k < end && num_alive > 0; ++k) {
      const int64_t g = gid[k];
      const Splat s = load_splat(m2, con, op, g);
      int r0, r1;
      if (!rows_reached(s, y0, h, r0, r1)) continue;
      const float f0 = feat[kFeat * g], f1 = feat[kFeat * g + 1], f2 = feat[kFeat * g + 2], f3 = feat[kFeat * g + 3];
      const int32_t walked = k - begin + 1;
      for (int r = r0; r <= r1; ++r) {
        const float dy = y0 + r + 0.5f - s.my;
        int stopped = 0;
#pragma omp simd reduction(+ : stopped)
        for (int col = 0; col < kTile; ++col) {
          const int p = r * kTile + col;
          const float dx = x0 + col + 0.5f - s.mx;
          const float power = -0.5f * (s.a * dx * dx + s.c * dy * dy) - s.b * dx * dy;
          const float alpha = std::min(kAlphaMax, s.o * exp_vec(power));
          const float test_t = trans[p] * (1.0f - alpha);
          const bool use = alive[p] > 0.0f && alpha >= kAlphaMin && power <= 0.0f;
          const bool stop = use && test_t < kTransMin;
          const bool add = use && !stop;
          const float weight = add ? alpha * trans[p] : 0.0f;
          acc[0][p] += weight * f0;
          acc[1][p] += weight * f1;
          acc[2][p] += weight * f2;
          acc[3][p] += weight * f3;
          trans[p] = add ? test_t : trans[p];
          last[p] = add ? walked : last[p];
          alive[p] = stop ? 0.0f : alive[p];
          stopped += stop ? 1 : 0;
        }
        num_alive -= stopped;
      }
    }
    for (int p = 0; p < kTilePixels; ++p) {
      const int x = x0 + p % kTile, y = y0 + p / kTile;
      if (x >= w || y >= h) continue;
      const int64_t pix = static_cast<int64_t>(y) * w + x;
      for (int f = 0; f < kFeat; ++f) o_feat[kFeat * pix + f] = acc[f][p];
      o_trans[pix] = trans[p];
      o_last[pix] = last[p];
    }
  }
}

void raster_backward(const RasterInputs& in, const float* t_final, const int32_t* walked_final, const float* d_feat,
                     const float* d_trans, float* tot, int num_threads) {
  const float* m2 = in.means2d;
  const float* con = in.conics;
  const float* op = in.opacities;
  const float* feat = in.features;
  const int32_t* off = in.offsets;
  const int32_t* gid = in.ids;
  const int64_t n = in.num_gaussians;
  const int w = in.width, h = in.height;
  const int tiles_x = (w + kTile - 1) / kTile;
  const int num_tiles = tiles_x * ((h + kTile - 1) / kTile);
  const int threads = std::max(1, num_threads);
  std::vector<float> buffers(static_cast<size_t>(threads) * n * kGradStride, 0.0f);

#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int tile = 0; tile < num_tiles; ++tile) {
    const int begin = off[tile], end = off[tile + 1];
    if (begin == end) continue;
    float* grad = buffers.data() + static_cast<size_t>(omp_get_thread_num()) * n * kGradStride;
    const int x0 = (tile % tiles_x) * kTile, y0 = (tile / tiles_x) * kTile;
    alignas(64) float trans[kTilePixels], tfin[kTilePixels], dtf[kTilePixels], dpix[kFeat][kTilePixels],
        behind[kFeat][kTilePixels], next_alpha[kTilePixels], next_feat[kFeat][kTilePixels];
    alignas(64) int32_t last[kTilePixels];
    int max_last = 0;
    for (int p = 0; p < kTilePixels; ++p) {
      const int x = x0 + p % kTile, y = y0 + p / kTile;
      const bool inside = x < w && y < h;
      const int64_t pix = static_cast<int64_t>(y) * w + x;
      trans[p] = tfin[p] = inside ? t_final[pix] : 1.0f;
      last[p] = inside ? walked_final[pix] : 0;
      dtf[p] = inside ? d_trans[pix] : 0.0f;
      for (int f = 0; f < kFeat; ++f) {
        dpix[f][p] = inside ? d_feat[kFeat * pix + f] : 0.0f;
        behind[f][p] = next_feat[f][p] = 0.0f;
      }
      next_alpha[p] = 0.0f;
      max_last = std::max(max_last, last[p]);
    }
    for (int k = begin + max_last - 1; k >= begin; --k) {
      const int64_t g = gid[k];
      const Splat s = load_splat(m2, con, op, g);
      int r0, r1;
      if (!rows_reached(s, y0, h, r0, r1)) continue;
      const float f0 = feat[kFeat * g], f1 = feat[kFeat * g + 1], f2 = feat[kFeat * g + 2], f3 = feat[kFeat * g + 3];
      const int32_t index = k - begin;
      float g_mx = 0, g_my = 0, g_a = 0, g_b = 0, g_c = 0, g_o = 0, g_f0 = 0, g_f1 = 0, g_f2 = 0, g_f3 = 0;
      for (int r = r0; r <= r1; ++r) {
        const float dy = y0 + r + 0.5f - s.my;
#pragma omp simd reduction(+ : g_mx, g_my, g_a, g_b, g_c, g_o, g_f0, g_f1, g_f2, g_f3)
        for (int col = 0; col < kTile; ++col) {
          const int p = r * kTile + col;
          const float dx = x0 + col + 0.5f - s.mx;
          const float power = -0.5f * (s.a * dx * dx + s.c * dy * dy) - s.b * dx * dy;
          const float gauss = exp_vec(power);
          const float raw_alpha = s.o * gauss;
          const float alpha = std::min(kAlphaMax, raw_alpha);
          const bool use = index < last[p] && alpha >= kAlphaMin && power <= 0.0f;
          const float t_before = use ? trans[p] / (1.0f - alpha) : trans[p];
          const float weight = use ? alpha * t_before : 0.0f;
          // Colour of everything behind this Gaussian, normalised to the transmittance after it.
          float d_alpha = 0.0f;
          float feat_k[kFeat] = {f0, f1, f2, f3};
          for (int f = 0; f < kFeat; ++f) {
            const float rec = next_alpha[p] * next_feat[f][p] + (1.0f - next_alpha[p]) * behind[f][p];
            behind[f][p] = use ? rec : behind[f][p];
            next_feat[f][p] = use ? feat_k[f] : next_feat[f][p];
            d_alpha += (feat_k[f] - rec) * dpix[f][p];
          }
          d_alpha *= t_before;
          d_alpha -= dtf[p] * tfin[p] / (1.0f - alpha);
          d_alpha = use ? d_alpha : 0.0f;
          next_alpha[p] = use ? alpha : next_alpha[p];
          trans[p] = t_before;
          const float d_power = raw_alpha < kAlphaMax ? d_alpha * alpha : 0.0f;
          g_o += raw_alpha < kAlphaMax ? d_alpha * gauss : 0.0f;
          g_mx += d_power * (s.a * dx + s.b * dy);
          g_my += d_power * (s.b * dx + s.c * dy);
          g_a += -0.5f * d_power * dx * dx;
          g_b += -d_power * dx * dy;
          g_c += -0.5f * d_power * dy * dy;
          g_f0 += weight * dpix[0][p];
          g_f1 += weight * dpix[1][p];
          g_f2 += weight * dpix[2][p];
          g_f3 += weight * dpix[3][p];
        }
      }
      float* out = grad + g * kGradStride;
      out[0] += g_mx; out[1] += g_my;
      out[2] += g_a; out[3] += g_b; out[4] += g_c;
      out[5] += g_o;
      out[6] += g_f0; out[7] += g_f1; out[8] += g_f2; out[9] += g_f3;
    }
  }

  const int64_t count = n * kGradStride;
#pragma omp parallel for schedule(static) num_threads(threads)
  for (int64_t i = 0; i < count; ++i) {
    float sum = 0.0f;
    for (int t = 0; t < threads; ++t) sum += buffers[static_cast<size_t>(t) * count + i];
    tot[i] = sum;
  }
}
