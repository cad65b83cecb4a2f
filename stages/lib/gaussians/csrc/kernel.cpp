// CPU tile rasterizer kernels for 2D Gaussians (plain C++): forward and backward, OpenMP over tiles.
//
// Same compositing rules as the PyTorch reference (rasterize_torch.py) and 3DGS: front to back,
// alpha = min(0.99, o * exp(power)), power = -(a dx^2 + 2 b dx dy + c dy^2) / 2, contributions with
// alpha < 1/255 skipped, a pixel stops at the first Gaussian that would bring its transmittance
// below 1e-4. Pixel (u, v) samples at (u + 0.5, v + 0.5).
//
// Speed: one OpenMP task per 16x16 tile; a tile is cut into segments of kLanes pixels of one row, each one SIMD
// vector (GCC vector extensions: 16 lanes = one AVX-512 register, or 8 = one AVX2 register; 16-lane vectors split
// in two on AVX2 spilled registers and ran ~2x slower; plain loops with `omp simd` were not vectorised by GCC 12
// here), with a polynomial exp. A Gaussian's alpha >= 1/255 ellipse is computed once per pass (not once per tile it
// is listed in), and in each tile it visits only the rows its ellipse crosses within the tile's columns (a tilted
// ellipse's box holds others; on a real capture a third of the visits). Features are F = 4 channels (RGB + camera
// depth); the caller adds background. None of this moves a bit: it skips only work that would add nothing.
//
// Same bits on every CPU and vector width (kernel_builds.py builds x86-64-v2/v3 with 8 lanes and x86-64-v4 with
// 16, without floating-point contraction: -ffp-contract=off):
// - every pixel's value is computed by the same IEEE operations whatever the lane count (a pixel's column is an
//   exact integer before its offset is taken; multiply-adds that matter for speed are explicit FMAs, fma_vec,
//   which round once on every instruction set: x86-64-v2 calls fmaf, slowly);
// - the gradient sums over a Gaussian's pixels run in 8-lane vectors, row by row, each row's left half then its
//   right half, whatever the lane count (accumulate; a half the 8-lane build skips adds zeros), then over the 8
//   lanes in order (hsum).
//
// Determinism: the backward writes each tile-list entry's gradient to its own slot, then sums the slots
// of each Gaussian in tile-list order (threads own disjoint ranges of Gaussians). The result is the same
// bits for any thread count and schedule; per-thread buffers summed as tiles finish were not.
#include "kernel.h"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <vector>
#if defined(__FMA__) || defined(__AVX512F__)
#include <immintrin.h>
#endif

namespace {

constexpr int kTile = 16;
constexpr int kFeat = kRasterFeatures;
constexpr int kGradStride = kRasterGradStride;
constexpr float kAlphaMin = 1.0f / 255.0f;
constexpr float kAlphaMax = 0.99f;
constexpr float kTransMin = 1e-4f;

#if defined(CUT_AND_SPLAT_LANES)
#define SEGMENT_LANES CUT_AND_SPLAT_LANES
#elif defined(__AVX512F__)
#define SEGMENT_LANES 16
#else
#define SEGMENT_LANES 8
#endif
constexpr int kLanes = SEGMENT_LANES;  // pixels per SIMD vector (8 or 16)
static_assert(kLanes == 8 || kLanes == 16, "a segment is half a tile row or a whole one");
constexpr int kSumLanes = 8;  // the gradient sums' vector, whatever kLanes
constexpr int kSegsPerRow = kTile / kLanes;
constexpr int kSegs = kTile * kSegsPerRow;  // segments per tile; segment v: row v / kSegsPerRow

typedef float vf __attribute__((vector_size(kLanes * sizeof(float))));      // one segment
typedef int32_t vi __attribute__((vector_size(kLanes * sizeof(int32_t))));  // its masks / ints
typedef float vsum __attribute__((vector_size(kSumLanes * sizeof(float))));  // a gradient sum

vf column_index() {
  vf index;
  for (int i = 0; i < kLanes; ++i) index[i] = static_cast<float>(i);
  return index;
}
const vf kColumnIndex = column_index();  // the lanes' pixel columns within a segment

// a * b + c rounded once, lane by lane: one FMA instruction where the target has them (an intrinsic: GCC's
// vectoriser split a lane loop of 16 into 256-bit halves under tunings that prefer them, 6x slower), else fmaf
// per lane (x86-64-v2).
inline vf fma_vec(vf a, vf b, vf c) {
#if SEGMENT_LANES == 16 && defined(__AVX512F__)
  return (vf)_mm512_fmadd_ps((__m512)a, (__m512)b, (__m512)c);
#elif SEGMENT_LANES == 8 && defined(__FMA__)
  return (vf)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c);
#else
  vf out;
  for (int i = 0; i < kLanes; ++i) out[i] = __builtin_fmaf(a[i], b[i], c[i]);
  return out;
#endif
}

// a * b + c rounded once, lane by lane, on the gradient sums' 8-lane vectors.
inline vsum fma_sum(vsum a, vsum b, vsum c) {
#if defined(__FMA__)
  return (vsum)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c);
#else
  vsum out;
  for (int i = 0; i < kSumLanes; ++i) out[i] = __builtin_fmaf(a[i], b[i], c[i]);
  return out;
#endif
}

// sum += a * b (each product rounded with its sum), as the 8-lane build adds a row: its left half, then its right
// half (a template, so that the branch of the other width is discarded).
template <typename Segment>
inline void accumulate_product(vsum& sum, Segment a, Segment b) {
  if constexpr (sizeof(Segment) == sizeof(vsum)) {
    sum = fma_sum(a, b, sum);
  } else {
    sum = fma_sum(__builtin_shufflevector(a, a, 0, 1, 2, 3, 4, 5, 6, 7),
                  __builtin_shufflevector(b, b, 0, 1, 2, 3, 4, 5, 6, 7), sum);
    sum = fma_sum(__builtin_shufflevector(a, a, 8, 9, 10, 11, 12, 13, 14, 15),
                  __builtin_shufflevector(b, b, 8, 9, 10, 11, 12, 13, 14, 15), sum);
  }
}

inline float hsum(vsum v) {
  float total = 0.0f;
  for (int i = 0; i < kSumLanes; ++i) total += v[i];
  return total;
}

// Whether any lane of a mask (lanes -1 or 0) is set.
inline bool any_lane(vi mask) {
#if SEGMENT_LANES == 16 && defined(__AVX512F__)
  return _mm512_test_epi32_mask((__m512i)mask, (__m512i)mask) != 0;
#elif SEGMENT_LANES == 8 && defined(__AVX2__)
  return !_mm256_testz_si256((__m256i)mask, (__m256i)mask);
#else
  bool any = false;
  for (int i = 0; i < kLanes; ++i) any |= mask[i] != 0;
  return any;
#endif
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
  const vf n = fma_vec(x, vf{} + 1.44269504088896341f, vf{} + 12582912.0f) - 12582912.0f;
  const vf r = fma_vec(n, vf{} + 2.12194440e-4f, fma_vec(n, vf{} - 0.693359375f, x));
  vf p = vf{} + 1.9875691500e-4f;
  p = fma_vec(p, r, vf{} + 1.3981999507e-3f);
  p = fma_vec(p, r, vf{} + 8.3334519073e-3f);
  p = fma_vec(p, r, vf{} + 4.1665795894e-2f);
  p = fma_vec(p, r, vf{} + 1.6666665459e-1f);
  p = fma_vec(p, r, vf{} + 5.0000001201e-1f);
  p = fma_vec(p, r * r, r) + 1.0f;
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

// A Gaussian's alpha >= 1/255 ellipse, a x^2 + 2 b x y + c y^2 <= reach around its mean, computed once per Gaussian
// (a tile list names it in every tile it reaches): its half extents along x and y, and its determinant a c - b^2.
// reach <= 0: the Gaussian reaches no pixel.
struct Ellipse {
  float reach, ex, ey, det;
};

inline Ellipse ellipse_of(const Splat& s) {
  if (s.o < kAlphaMin) return {};
  const float reach = 2.0f * std::log(s.o * 255.0f);
  const float det = s.a * s.c - s.b * s.b;
  if (!(reach > 0.0f) || !(det > 0.0f)) return {};
  return {reach, std::sqrt(reach * s.c / det) + 1e-3f,  // (conic^-1)_xx = c / det
          std::sqrt(reach * s.a / det) + 1e-3f, det};   // (conic^-1)_yy = a / det
}

// The ellipses of all Gaussians of `in`.
std::vector<Ellipse> ellipses_of(const RasterInputs& in, int num_threads) {
  std::vector<Ellipse> out(static_cast<size_t>(in.num_gaussians));
#pragma omp parallel for schedule(static) num_threads(num_threads)
  for (int64_t g = 0; g < in.num_gaussians; ++g) out[g] = ellipse_of(load_splat(in, g));
  return out;
}

// The rows [y_lo, y_hi] (offsets from the mean) of the ellipse's part within the columns [dx_lo, dx_hi] (offsets
// from the mean): a tilted ellipse's box holds rows whose slice passes beside the tile. The part is convex: its
// smallest y is the ellipse's own where that point lies between the columns, else on the nearer column (and so for
// its largest y). Computed for a slightly larger ellipse and widened by 1e-3 of a pixel, margins a thousand times
// float's rounding: a pixel whose alpha reaches 1/255 is never left out. False where the columns miss the ellipse.
inline bool strip_rows(const Ellipse& e, const Splat& s, float dx_lo, float dx_hi, float& y_lo, float& y_hi) {
  const float reach = e.reach * 1.001f + 1e-3f;
  const float ey = std::sqrt(reach * s.a / e.det);
  const float top_dx = s.b / s.a * ey;  // the point of smallest y (dy = -ey) lies at dx = b / a * ey, of largest y at -
  const float dx0 = std::min(std::max(top_dx, dx_lo), dx_hi), dx1 = std::min(std::max(-top_dx, dx_lo), dx_hi);
  const float disc0 = s.c * reach - e.det * dx0 * dx0, disc1 = s.c * reach - e.det * dx1 * dx1;
  if (disc0 < 0.0f || disc1 < 0.0f) return false;
  y_lo = (-s.b * dx0 - std::sqrt(disc0)) / s.c;
  y_hi = (-s.b * dx1 + std::sqrt(disc1)) / s.c;
  y_lo -= 1e-3f * (1.0f + std::fabs(y_lo));
  y_hi += 1e-3f * (1.0f + std::fabs(y_hi));
  return true;
}

// The part of a tile a Gaussian's ellipse can reach: segments [v0, v1] (the rows its pixel centres reach) and,
// within each row, segment columns [c0, c1] (its horizontal extent).
struct Reach {
  int v0, v1, c0, c1;
  float x0, x1;  // the reached pixel columns within the tile (the window every lane count applies alike)
};

inline bool reached(const Ellipse& e, const Splat& s, int tile_x0, int tile_y0, int height, Reach& out) {
  if (!(e.reach > 0.0f)) return false;
  int r0 = std::max(0, static_cast<int>(std::ceil(s.my - e.ey - 0.5f)) - tile_y0);
  int r1 = std::min({kTile - 1, height - 1 - tile_y0, static_cast<int>(std::floor(s.my + e.ey - 0.5f)) - tile_y0});
  const int x0 = std::max(0, static_cast<int>(std::ceil(s.mx - e.ex - 0.5f)) - tile_x0);
  const int x1 = std::min(kTile - 1, static_cast<int>(std::floor(s.mx + e.ex - 0.5f)) - tile_x0);
  if (r0 > r1 || x0 > x1) return false;
  if (s.a > 0.0f && s.c > 0.0f) {  // the rows the part of the ellipse above columns [x0, x1] reaches
    float y_lo, y_hi;
    const float dx_lo = static_cast<float>(tile_x0 + x0) + 0.5f - s.mx;
    const float dx_hi = static_cast<float>(tile_x0 + x1) + 0.5f - s.mx;
    if (!strip_rows(e, s, dx_lo, dx_hi, y_lo, y_hi)) return false;
    r0 = std::max(r0, static_cast<int>(std::ceil(s.my + y_lo - 0.5f)) - tile_y0);
    r1 = std::min(r1, static_cast<int>(std::floor(s.my + y_hi - 0.5f)) - tile_y0);
    if (r0 > r1) return false;
  }
  out = {r0 * kSegsPerRow, r1 * kSegsPerRow + kSegsPerRow - 1, x0 / kLanes, x1 / kLanes, static_cast<float>(x0),
         static_cast<float>(x1)};
  return true;
}

// Whether segment v lies in the reached columns (a segment the 8-lane build skips has none of its pixels there).
inline bool in_columns(const Reach& reach, int v) {
  const int c = v % kSegsPerRow;
  return c >= reach.c0 && c <= reach.c1;
}

// The lanes of segment v in the reached columns: pixels beyond them take no part whatever the lane count (float
// rounding can put an alpha of 1/255 a hair beyond the ellipse's extent; a 16-lane row would take such a pixel
// where the 8-lane build skips its half row).
inline vi column_window(const Reach& reach, int v) {
  const vf columns = (vf{} + static_cast<float>(seg_col(v))) + kColumnIndex;
  return (columns >= reach.x0) & (columns <= reach.x1);
}

struct Footprint {
  vf dx, power, gauss, alpha;
  float dy;
};

// Footprint on segment v of the tile at (x0, y0).
inline Footprint footprint(const Splat& s, int x0, int y0, int v) {
  const int y = y0 + seg_row(v);
  Footprint fp;
  fp.dx = ((static_cast<float>(x0 + seg_col(v)) + kColumnIndex) + 0.5f) - s.mx;  // the column is exact
  fp.dy = y + 0.5f - s.my;
  const float c_dy2 = s.c * fp.dy * fp.dy, b_dy = s.b * fp.dy;
  fp.power = fma_vec(vf{} - b_dy, fp.dx, -0.5f * fma_vec(s.a * fp.dx, fp.dx, vf{} + c_dy2));
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
  const std::vector<Ellipse> ellipses = ellipses_of(in, num_threads);

#pragma omp parallel for schedule(dynamic, 1) num_threads(num_threads)
  for (int tile = 0; tile < num_tiles; ++tile) {
    const int begin = in.offsets[tile], end = in.offsets[tile + 1];
    const int x0 = (tile % tiles_x) * kTile, y0 = (tile / tiles_x) * kTile;
    vf trans[kSegs], acc[kFeat][kSegs];
    vi alive[kSegs], last[kSegs];  // alive: -1 running, 0 stopped or outside the image
    for (int r = 0; r < kSegs; ++r) {
      trans[r] = vf{} + 1.0f;
      const vi inside = ((vf{} + static_cast<float>(x0 + seg_col(r))) + kColumnIndex < static_cast<float>(w)) &
                        (vi{} + (y0 + seg_row(r) < h ? -1 : 0));
      alive[r] = inside;
      last[r] = vi{};
      for (int f = 0; f < kFeat; ++f) acc[f][r] = vf{};
    }
    for (int k = begin; k < end; ++k) {
      if ((k - begin) % 32 == 31) {  // stop the tile once every pixel has terminated
        vi any = vi{};
        for (int r = 0; r < kSegs; ++r) any |= alive[r];
        if (!any_lane(any)) break;
      }
      const int64_t g = in.ids[k];
      const Splat s = load_splat(in, g);
      const Ellipse& e = ellipses[g];
      Reach reach;
      if (!reached(e, s, x0, y0, h, reach)) continue;
      const float* fg = in.features + kFeat * g;
      const int32_t walked = k - begin + 1;
      for (int r = reach.v0; r <= reach.v1; ++r) {
        if (!in_columns(reach, r)) continue;
        const Footprint fp = footprint(s, x0, y0, r);
        const vf test_t = trans[r] * (1.0f - fp.alpha);
        const vi use = alive[r] & column_window(reach, r) & (fp.alpha >= kAlphaMin) & (fp.power <= 0.0f);
        const vi stop = use & (test_t < kTransMin);
        const vi add = use & ~stop;
        const vf weight = add ? fp.alpha * trans[r] : vf{};
        for (int f = 0; f < kFeat; ++f) acc[f][r] = fma_vec(weight, vf{} + fg[f], acc[f][r]);
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
  // One gradient slot per tile-list entry, kept from the previous call of this thread (MBs of fresh memory a step
  // cost page faults and a fill): every slot is written below, zeros where the entry takes no part. The OpenMP
  // threads reach it through `entries` (a thread_local named inside the parallel region would be each thread's own).
  thread_local std::vector<float> kept_entries;
  if (kept_entries.size() < static_cast<size_t>(num_entries) * kGradStride) {
    kept_entries.resize(static_cast<size_t>(num_entries) * kGradStride);
  }
  float* const entries = kept_entries.data();
  const std::vector<Ellipse> ellipses = ellipses_of(in, threads);

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
    int seg_last[kSegs];  // the segment's largest walked count: Gaussians from there on touch none of its pixels
    bool no_dtf[kSegs];   // dL/dT_final is zero (+0 or -0) on every lane, as in training on a black background
    int max_last = 0;
    bool last_feature_used = false;
    for (int r = 0; r < kSegs; ++r) {
      trans[r] = tfin[r] = vf{} + 1.0f;
      dtf[r] = next_alpha[r] = vf{};
      last[r] = vi{};
      seg_last[r] = 0;
      for (int f = 0; f < kFeat; ++f) dpix[f][r] = behind[f][r] = next_feat[f][r] = vf{};
      for (int col = 0; col < kLanes && y0 + seg_row(r) < h && x0 + seg_col(r) + col < w; ++col) {
        const int64_t pix = static_cast<int64_t>(y0 + seg_row(r)) * w + x0 + seg_col(r) + col;
        trans[r][col] = tfin[r][col] = t_final[pix];
        last[r][col] = walked_final[pix];
        dtf[r][col] = d_trans[pix];
        for (int f = 0; f < kFeat; ++f) dpix[f][r][col] = d_feat[kFeat * pix + f];
        seg_last[r] = std::max(seg_last[r], walked_final[pix]);
      }
      max_last = std::max(max_last, seg_last[r]);
      no_dtf[r] = !any_lane(((vi)dtf[r] & 0x7fffffff) != 0);
      last_feature_used |= any_lane(((vi)dpix[kFeat - 1][r] & 0x7fffffff) != 0);
    }
    // Where no pixel of the tile has a gradient on the last feature (depth, in training), its terms add signed zeros
    // to sums that never hold -0 (each starts at +0): leaving them out moves no bit.
    const int features = last_feature_used ? kFeat : kFeat - 1;
    std::fill(entries + static_cast<size_t>(begin + max_last) * kGradStride,
              entries + static_cast<size_t>(end) * kGradStride, 0.0f);  // behind every pixel's last Gaussian
    for (int k = begin + max_last - 1; k >= begin; --k) {
      const int64_t g = in.ids[k];
      const Splat s = load_splat(in, g);
      const Ellipse& e = ellipses[g];
      float* out = entries + static_cast<size_t>(k) * kGradStride;
      Reach reach;
      if (!reached(e, s, x0, y0, h, reach)) {
        std::fill(out, out + kGradStride, 0.0f);
        continue;
      }
      const float* fg = in.features + kFeat * g;
      const int32_t index = k - begin;
      vsum g_mx{}, g_my{}, g_a{}, g_b{}, g_c{}, g_o{}, g_f[kFeat] = {};
      for (int r = reach.v0; r <= reach.v1; ++r) {
        if (index >= seg_last[r] || !in_columns(reach, r)) continue;
        const Footprint fp = footprint(s, x0, y0, r);
        const vi use = (vi{} + index < last[r]) & column_window(reach, r) & (fp.alpha >= kAlphaMin) &
                       (fp.power <= 0.0f);
        const vf t_before = use ? trans[r] / (1.0f - fp.alpha) : trans[r];
        const vf weight = use ? fp.alpha * t_before : vf{};
        vf d_alpha{};
        for (int f = 0; f < features; ++f) {
          const vf rec = fma_vec(next_alpha[r], next_feat[f][r], (1.0f - next_alpha[r]) * behind[f][r]);
          behind[f][r] = use ? rec : behind[f][r];
          next_feat[f][r] = use ? vf{} + fg[f] : next_feat[f][r];
          d_alpha = fma_vec(fg[f] - rec, dpix[f][r], d_alpha);
          accumulate_product(g_f[f], weight, dpix[f][r]);
        }
        // -(dtf T_final / (1 - alpha)) is -dtf, bit for bit, where dtf is a signed zero (T_final >= 0, 1 - alpha > 0 on
        // the lanes used): that saves the second division
        const vf from_final = no_dtf[r] ? -dtf[r] : -(dtf[r] * tfin[r] / (1.0f - fp.alpha));
        d_alpha = fma_vec(d_alpha, t_before, from_final);
        const vi unclamped = use & (s.o * fp.gauss < kAlphaMax);
        d_alpha = unclamped ? d_alpha : vf{};
        next_alpha[r] = use ? fp.alpha : next_alpha[r];
        trans[r] = t_before;
        const vf d_power = d_alpha * fp.alpha;
        const vf half_d_power = -0.5f * d_power;
        accumulate_product(g_o, d_alpha, fp.gauss);
        accumulate_product(g_mx, d_power, fma_vec(vf{} + s.a, fp.dx, vf{} + s.b * fp.dy));
        accumulate_product(g_my, d_power, fma_vec(vf{} + s.b, fp.dx, vf{} + s.c * fp.dy));
        accumulate_product(g_a, half_d_power * fp.dx, fp.dx);
        accumulate_product(g_b, -d_power * fp.dx, vf{} + fp.dy);
        accumulate_product(g_c, half_d_power * fp.dy, vf{} + fp.dy);
      }
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
      const float* slot = entries + static_cast<size_t>(k) * kGradStride;
      float* out = grad_out + g * kGradStride;
      for (int j = 0; j < kGradStride; ++j) out[j] += slot[j];
    }
  }
}
