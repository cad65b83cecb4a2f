// CPU tile rasterizer kernels for 2D Gaussians (plain C++): forward and backward, OpenMP over tiles.
//
// Same compositing rules as the PyTorch reference (rasterize_torch.py) and 3DGS: front to back,
// alpha = min(0.99, o * exp(power)), power = -(a dx^2 + 2 b dx dy + c dy^2) / 2, contributions with
// alpha < 1/255 skipped, a pixel stops at the first Gaussian that would bring its transmittance
// below 1e-4. Pixel (u, v) samples at (u + 0.5, v + 0.5).
//
// Speed: one OpenMP task per 16x16 tile; a tile is cut into segments of kLanes pixels of one row, each
// one SIMD vector (GCC vector extensions: 16 lanes with AVX-512, else 8 = one AVX2 register; 16-lane
// vectors split in two on AVX2 spilled registers and ran ~2x slower; plain loops with `omp simd` were not
// vectorised by GCC 12 here), with a polynomial exp; each Gaussian visits only the segments (rows, and
// with 8 lanes each half row) where its alpha can reach 1/255. Features are F = 4 channels (RGB +
// camera depth); the caller adds background. Gradient sums over a segment's lanes depend on kLanes, so
// AVX-512 and AVX2 machines give results that differ in the last bits.
//
// Determinism: the backward writes each tile-list entry's gradient to its own slot, then sums the slots
// of each Gaussian in tile-list order (threads own disjoint ranges of Gaussians). The result is the same
// bits for any thread count and schedule; per-thread buffers summed as tiles finish were not.
#include "kernel.h"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <vector>

namespace {

constexpr int kTile = 16;
constexpr int kFeat = kRasterFeatures;
constexpr int kGradStride = kRasterGradStride;
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;
constexpr float kTransMin = 1e-4f;

#if defined(__AVX512F__)
constexpr int kLanes = 16;  // pixels per SIMD vector
#else
constexpr int kLanes = 8;
#endif
constexpr int kSegsPerRow = kTile / kLanes;
constexpr int kSegs = kTile * kSegsPerRow;  // segments per tile; segment v: row v / kSegsPerRow

typedef float vf __attribute__((vector_size(kLanes * sizeof(float))));      // one segment
typedef int32_t vi __attribute__((vector_size(kLanes * sizeof(int32_t))));  // its masks / ints

#if defined(__AVX512F__)
const vf kColumnCentres = {0.5f, 1.5f, 2.5f, 3.5f, 4.5f, 5.5f, 6.5f, 7.5f,
                           8.5f, 9.5f, 10.5f, 11.5f, 12.5f, 13.5f, 14.5f, 15.5f};
#else
const vf kColumnCentres = {0.5f, 1.5f, 2.5f, 3.5f, 4.5f, 5.5f, 6.5f, 7.5f};
#endif

inline float hsum(vf v) {
  float total = 0.0f;
  for (int i = 0; i < kLanes; ++i) total += v[i];
  return total;
}

// Local pixel offsets (row, column) of segment v's first pixel.
inline int seg_row(int v) { return v / kSegsPerRow; }
inline int seg_col(int v) { return (v % kSegsPerRow) * kLanes; }

// exp(x) to ~2 ulp for -30 <= x <= 88 (Cephes expf polynomial, round-to-nearest by the 1.5 * 2^23
// trick). Inputs below -30 give exp(-30): every caller discards alpha < 1/255 (x < -5.6), and the
// floor keeps o * exp(x) far from float denormals, whose microcode assists are very slow.
inline vf exp_vec(vf x) {
  const vf lo = vf{} - 30.0f, hi = vf{} + 88.0f;
  x = x < lo ? lo : x;
  x = x > hi ? hi : x;
  const vf n = (x * 1.44269504088896341f + 12582912.0f) - 12582912.0f;
  const vf r = x - n * 0.693359375f + n * 2.12194440e-4f;
  vf p = vf{} + 1.9875691500e-4f;
  p = p * r + 1.3981999507e-3f;
  p = p * r + 8.3334519073e-3f;
  p = p * r + 4.1665795894e-2f;
  p = p * r + 1.6666665459e-1f;
  p = p * r + 5.0000001201e-1f;
  p = p * r * r + r + 1.0f;
  const vi bits = (__builtin_convertvector(n, vi) + 127) << 23;
  return p * (vf)bits;  // vector cast = bit reinterpretation
}

struct Splat {
  float mx, my, a, b, c, o;
};

inline Splat load_splat(const RasterInputs& in, int64_t g) {
  return {in.means2d[2 * g], in.means2d[2 * g + 1], in.conics[3 * g], in.conics[3 * g + 1], in.conics[3 * g + 2],
          in.opacities[g]};
}

// The part of a tile a Gaussian's alpha >= 1/255 ellipse can reach: segments [v0, v1] (the rows its
// pixel centres reach) and, within each row, segment columns [c0, c1] (its horizontal extent).
struct Reach {
  int v0, v1, c0, c1;
};

inline bool reached(const Splat& s, int tile_x0, int tile_y0, int height, Reach& out) {
  if (s.o < kAlphaMin) return false;
  const float reach = 2.0f * std::log(s.o * 255.0f);
  const float det = s.a * s.c - s.b * s.b;
  if (!(reach > 0.0f) || !(det > 0.0f)) return false;
  const float ey = std::sqrt(reach * s.a / det) + 1e-3f;  // (conic^-1)_yy = a / det
  const float ex = std::sqrt(reach * s.c / det) + 1e-3f;  // (conic^-1)_xx = c / det
  const int r0 = std::max(0, static_cast<int>(std::ceil(s.my - ey - 0.5f)) - tile_y0);
  const int r1 = std::min({kTile - 1, height - 1 - tile_y0, static_cast<int>(std::floor(s.my + ey - 0.5f)) - tile_y0});
  const int x0 = std::max(0, static_cast<int>(std::ceil(s.mx - ex - 0.5f)) - tile_x0);
  const int x1 = std::min(kTile - 1, static_cast<int>(std::floor(s.mx + ex - 0.5f)) - tile_x0);
  if (r0 > r1 || x0 > x1) return false;
  out = {r0 * kSegsPerRow, r1 * kSegsPerRow + kSegsPerRow - 1, x0 / kLanes, x1 / kLanes};
  return true;
}

// Whether segment v lies in the reached columns.
inline bool in_columns(const Reach& reach, int v) {
  const int c = v % kSegsPerRow;
  return c >= reach.c0 && c <= reach.c1;
}

struct Footprint {
  vf dx, power, gauss, alpha;
  float dy;
};

// Footprint on segment v of the tile at (x0, y0).
inline Footprint footprint(const Splat& s, int x0, int y0, int v) {
  const int y = y0 + seg_row(v);
  Footprint fp;
  fp.dx = (x0 + seg_col(v) - s.mx) + kColumnCentres;
  fp.dy = y + 0.5f - s.my;
  fp.power = -0.5f * (s.a * fp.dx * fp.dx + s.c * fp.dy * fp.dy) - s.b * fp.dy * fp.dx;
  fp.gauss = exp_vec(fp.power);
  const vf raw = s.o * fp.gauss;
  fp.alpha = raw < kAlphaMax ? raw : vf{} + kAlphaMax;
  return fp;
}

}  // namespace

void raster_forward(const RasterInputs& in, float* o_feat, float* o_trans, int32_t* o_last, int num_threads) {
  const int w = in.width, h = in.height;
  const int tiles_x = (w + kTile - 1) / kTile;
  const int num_tiles = tiles_x * ((h + kTile - 1) / kTile);

#pragma omp parallel for schedule(dynamic, 1) num_threads(num_threads)
  for (int tile = 0; tile < num_tiles; ++tile) {
    const int begin = in.offsets[tile], end = in.offsets[tile + 1];
    const int x0 = (tile % tiles_x) * kTile, y0 = (tile / tiles_x) * kTile;
    vf trans[kSegs], acc[kFeat][kSegs];
    vi alive[kSegs], last[kSegs];  // alive: -1 running, 0 stopped or outside the image
    for (int r = 0; r < kSegs; ++r) {
      trans[r] = vf{} + 1.0f;
      const vi inside = ((vf{} + static_cast<float>(x0 + seg_col(r))) + kColumnCentres < static_cast<float>(w)) &
                        (vi{} + (y0 + seg_row(r) < h ? -1 : 0));
      alive[r] = inside;
      last[r] = vi{};
      for (int f = 0; f < kFeat; ++f) acc[f][r] = vf{};
    }
    for (int k = begin; k < end; ++k) {
      if ((k - begin) % 32 == 31) {  // stop the tile once every pixel has terminated
        vi any = vi{};
        for (int r = 0; r < kSegs; ++r) any |= alive[r];
        bool running = false;
        for (int i = 0; i < kLanes; ++i) running |= any[i] != 0;
        if (!running) break;
      }
      const int64_t g = in.ids[k];
      const Splat s = load_splat(in, g);
      Reach reach;
      if (!reached(s, x0, y0, h, reach)) continue;
      const float* fg = in.features + kFeat * g;
      const int32_t walked = k - begin + 1;
      for (int r = reach.v0; r <= reach.v1; ++r) {
        if (!in_columns(reach, r)) continue;
        const Footprint fp = footprint(s, x0, y0, r);
        const vf test_t = trans[r] * (1.0f - fp.alpha);
        const vi use = alive[r] & (fp.alpha >= kAlphaMin) & (fp.power <= 0.0f);
        const vi stop = use & (test_t < kTransMin);
        const vi add = use & ~stop;
        const vf weight = add ? fp.alpha * trans[r] : vf{};
        for (int f = 0; f < kFeat; ++f) acc[f][r] += weight * fg[f];
        trans[r] = add ? test_t : trans[r];
        last[r] = add ? vi{} + walked : last[r];
        alive[r] &= ~stop;
      }
    }
    for (int r = 0; r < kSegs && y0 + seg_row(r) < h; ++r) {
      for (int col = 0; col < kLanes && x0 + seg_col(r) + col < w; ++col) {
        const int64_t pix = static_cast<int64_t>(y0 + seg_row(r)) * w + x0 + seg_col(r) + col;
        for (int f = 0; f < kFeat; ++f) o_feat[kFeat * pix + f] = acc[f][r][col];
        o_trans[pix] = trans[r][col];
        o_last[pix] = last[r][col];
      }
    }
  }
}

void raster_backward(const RasterInputs& in, const float* t_final, const int32_t* walked_final, const float* d_feat,
                     const float* d_trans, float* grad_out, int num_threads) {
  const int64_t n = in.num_gaussians;
  const int w = in.width, h = in.height;
  const int tiles_x = (w + kTile - 1) / kTile;
  const int num_tiles = tiles_x * ((h + kTile - 1) / kTile);
  const int threads = std::max(1, num_threads);
  const int64_t num_entries = in.offsets[num_tiles];
  std::vector<float> entries(static_cast<size_t>(num_entries) * kGradStride, 0.0f);  // one slot per list entry

#pragma omp parallel for schedule(dynamic, 1) num_threads(threads)
  for (int tile = 0; tile < num_tiles; ++tile) {
    const int begin = in.offsets[tile], end = in.offsets[tile + 1];
    if (begin == end) continue;
    const int x0 = (tile % tiles_x) * kTile, y0 = (tile / tiles_x) * kTile;
    // Per pixel: transmittance (walked back), final T, dL/dT_final, dL/dfeatures, the features
    // behind the current Gaussian (normalised to the transmittance after it), and the previous
    // (next-behind) Gaussian's alpha and features.
    vf trans[kSegs], tfin[kSegs], dtf[kSegs], dpix[kFeat][kSegs], behind[kFeat][kSegs], next_alpha[kSegs],
        next_feat[kFeat][kSegs];
    vi last[kSegs];
    int max_last = 0;
    for (int r = 0; r < kSegs; ++r) {
      trans[r] = tfin[r] = vf{} + 1.0f;
      dtf[r] = next_alpha[r] = vf{};
      last[r] = vi{};
      for (int f = 0; f < kFeat; ++f) dpix[f][r] = behind[f][r] = next_feat[f][r] = vf{};
      for (int col = 0; col < kLanes && y0 + seg_row(r) < h && x0 + seg_col(r) + col < w; ++col) {
        const int64_t pix = static_cast<int64_t>(y0 + seg_row(r)) * w + x0 + seg_col(r) + col;
        trans[r][col] = tfin[r][col] = t_final[pix];
        last[r][col] = walked_final[pix];
        dtf[r][col] = d_trans[pix];
        for (int f = 0; f < kFeat; ++f) dpix[f][r][col] = d_feat[kFeat * pix + f];
        max_last = std::max(max_last, walked_final[pix]);
      }
    }
    for (int k = begin + max_last - 1; k >= begin; --k) {
      const int64_t g = in.ids[k];
      const Splat s = load_splat(in, g);
      Reach reach;
      if (!reached(s, x0, y0, h, reach)) continue;
      const float* fg = in.features + kFeat * g;
      const int32_t index = k - begin;
      vf g_mx{}, g_my{}, g_a{}, g_b{}, g_c{}, g_o{}, g_f[kFeat] = {};
      for (int r = reach.v0; r <= reach.v1; ++r) {
        if (!in_columns(reach, r)) continue;
        const Footprint fp = footprint(s, x0, y0, r);
        const vi use = (vi{} + index < last[r]) & (fp.alpha >= kAlphaMin) & (fp.power <= 0.0f);
        const vf t_before = use ? trans[r] / (1.0f - fp.alpha) : trans[r];
        const vf weight = use ? fp.alpha * t_before : vf{};
        vf d_alpha{};
        for (int f = 0; f < kFeat; ++f) {
          const vf rec = next_alpha[r] * next_feat[f][r] + (1.0f - next_alpha[r]) * behind[f][r];
          behind[f][r] = use ? rec : behind[f][r];
          next_feat[f][r] = use ? vf{} + fg[f] : next_feat[f][r];
          d_alpha += (fg[f] - rec) * dpix[f][r];
          g_f[f] += weight * dpix[f][r];
        }
        d_alpha = d_alpha * t_before - dtf[r] * tfin[r] / (1.0f - fp.alpha);
        const vi unclamped = use & (s.o * fp.gauss < kAlphaMax);
        d_alpha = unclamped ? d_alpha : vf{};
        next_alpha[r] = use ? fp.alpha : next_alpha[r];
        trans[r] = t_before;
        const vf d_power = d_alpha * fp.alpha;
        g_o += d_alpha * fp.gauss;
        g_mx += d_power * (s.a * fp.dx + s.b * fp.dy);
        g_my += d_power * (s.b * fp.dx + s.c * fp.dy);
        g_a += -0.5f * d_power * fp.dx * fp.dx;
        g_b += -d_power * fp.dx * fp.dy;
        g_c += -0.5f * d_power * fp.dy * fp.dy;
      }
      float* out = entries.data() + static_cast<size_t>(k) * kGradStride;
      out[0] = hsum(g_mx);
      out[1] = hsum(g_my);
      out[2] = hsum(g_a);
      out[3] = hsum(g_b);
      out[4] = hsum(g_c);
      out[5] = hsum(g_o);
      for (int f = 0; f < kFeat; ++f) out[6 + f] = hsum(g_f[f]);
    }
  }

  std::fill(grad_out, grad_out + n * kGradStride, 0.0f);
#pragma omp parallel num_threads(threads)
  {
    const int64_t first = n * omp_get_thread_num() / omp_get_num_threads();
    const int64_t last = n * (omp_get_thread_num() + 1) / omp_get_num_threads();
    for (int64_t k = 0; k < num_entries; ++k) {
      const int64_t g = in.ids[k];
      if (g < first || g >= last) continue;
      const float* slot = entries.data() + static_cast<size_t>(k) * kGradStride;
      float* out = grad_out + g * kGradStride;
      for (int j = 0; j < kGradStride; ++j) out[j] += slot[j];
    }
  }
}
