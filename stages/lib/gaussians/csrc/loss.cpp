// The 3DGS photometric loss on the CPU in one pass: (1 - lambda) L1 + lambda (1 - SSIM) of a prediction and a
// target image [H, W, C], and its gradient with respect to the prediction.
//
// SSIM is kornia.metrics.ssim's with padding 'same': a separable window (passed in; the trainer's is 11 taps of a
// Gaussian of sigma 1.5), along rows then along columns, reflect padding on each pass, C1 = 0.01^2, C2 = 0.03^2 and
// eps = 1e-12 added to the denominator; averaged over pixels and channels. The gradient goes back through the
// adjoint of the same filters. The autograd graph of the PyTorch formulation runs about 60 full-image operations
// per step; here the five moment planes of each channel are filtered once forward and three gradient planes once
// backward.
//
// Determinism: the loss sums each row in double and adds the rows in order; every plane and row is computed by
// one thread. The bits do not depend on the thread count. The filters add a block of columns at a time in vector
// registers (16 or 8 columns: the same operations in the same order for each pixel, so the same bits on every
// build) and the adjoints gather what a scatter would add, in its order.
#include "loss.h"

#include <omp.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <vector>

namespace {

constexpr float kC1 = 0.01f * 0.01f;
constexpr float kC2 = 0.03f * 0.03f;
constexpr float kEps = 1e-12f;
constexpr int kMoments = 5;  // x, y, x^2, y^2, x y
constexpr int kPartials = 3;  // d/d mean_x, d/d E[x^2], d/d E[x y]

inline int reflect(int i, int n) { return i < 0 ? -i : (i >= n ? 2 * (n - 1) - i : i); }

// A block of columns in registers (16 on AVX-512 builds, else 8): every tap is added to each pixel in the order a
// plain loop adds them (the same bits on every build), without storing the row between taps.
#if defined(CUT_AND_SPLAT_LANES) && CUT_AND_SPLAT_LANES == 16
constexpr int kBlock = 16;
#else
constexpr int kBlock = 8;
#endif
typedef float vblock __attribute__((vector_size(kBlock * sizeof(float))));

inline vblock load_block(const float* p) {
  vblock v;
  __builtin_memcpy(&v, p, sizeof(v));
  return v;
}

inline void store_block(float* p, vblock v) { __builtin_memcpy(p, &v, sizeof(v)); }

// dst[x] = 0 + weights[0] rows[0][x] + weights[1] rows[1][x] + ..., for x in [0, w), the taps added in order.
void weighted_sum(const float* const* rows, const float* weights, int count, float* dst, int w) {
  int x = 0;
  for (; x + kBlock <= w; x += kBlock) {
    vblock acc{};
    for (int j = 0; j < count; ++j) acc += weights[j] * load_block(rows[j] + x);
    store_block(dst + x, acc);
  }
  for (; x < w; ++x) {
    float acc = 0.0f;
    for (int j = 0; j < count; ++j) acc += weights[j] * rows[j][x];
    dst[x] = acc;
  }
}

// Scratch of one thread for the filters: a padded row, the padded row of the rows' adjoint, and the taps of one
// output row.
struct FilterScratch {
  std::vector<float> pad, padded_grad;
  std::vector<const float*> rows;

  FilterScratch(int w, int r, int max_taps) : pad(w + 4 * r), padded_grad(w + 2 * r), rows(max_taps) {}
};

// The taps of the columns' adjoint, the same for every plane of a call: row Y of the output sums k[j] grad[y] over
// the (y, j) with reflect(y + j - r) = Y, in the order of y, then j, as scattering each grad row onto the rows it
// came from would add them. Row Y's taps are [begin[Y], begin[Y + 1]) of `source` and `weight` (up to 3 of each
// weight: its own, and those the top and bottom reflections bring).
struct AdjointTaps {
  std::vector<int> begin, source;
  std::vector<float> weight;

  AdjointTaps(int h, const float* k, int r) : begin(h + 1, 0) {
    for (int out_y = 0; out_y < h; ++out_y) {
      for (int y = std::max(0, out_y - 2 * r); y <= std::min(h - 1, out_y + 2 * r); ++y) {
        for (int j = 0; j <= 2 * r; ++j) {
          if (reflect(y + j - r, h) != out_y) continue;
          source.push_back(y);
          weight.push_back(k[j]);
        }
      }
      begin[out_y + 1] = static_cast<int>(source.size());
    }
  }

  int max_taps() const {
    int most = 0;
    for (size_t y = 0; y + 1 < begin.size(); ++y) most = std::max(most, begin[y + 1] - begin[y]);
    return most;
  }
};

// out [H, W] = the window k [2 r + 1] along each row of in [H, W] (reflect padded).
void filter_rows(const float* in, float* out, int h, int w, const float* k, int r, FilterScratch& scratch) {
  float* pad = scratch.pad.data();
  for (int j = 0; j <= 2 * r; ++j) scratch.rows[j] = pad + j;
  for (int y = 0; y < h; ++y) {
    const float* src = in + static_cast<int64_t>(y) * w;
    for (int i = -r; i < w + r; ++i) pad[i + r] = src[reflect(i, w)];
    weighted_sum(scratch.rows.data(), k, 2 * r + 1, out + static_cast<int64_t>(y) * w, w);
  }
}

// out [H, W] = the window along each column of in [H, W] (reflect padded).
void filter_columns(const float* in, float* out, int h, int w, const float* k, int r, FilterScratch& scratch) {
  for (int y = 0; y < h; ++y) {
    for (int j = 0; j <= 2 * r; ++j) scratch.rows[j] = in + static_cast<int64_t>(reflect(y + j - r, h)) * w;
    weighted_sum(scratch.rows.data(), k, 2 * r + 1, out + static_cast<int64_t>(y) * w, w);
  }
}

// The adjoint of filter_columns: out [H, W] = d loss / d in, given grad = d loss / d its output (taps: AdjointTaps).
void filter_columns_adjoint(const float* grad, float* out, int h, int w, const AdjointTaps& taps,
                            FilterScratch& scratch) {
  for (int out_y = 0; out_y < h; ++out_y) {
    const int first = taps.begin[out_y], count = taps.begin[out_y + 1] - first;
    for (int i = 0; i < count; ++i) scratch.rows[i] = grad + static_cast<int64_t>(taps.source[first + i]) * w;
    weighted_sum(scratch.rows.data(), taps.weight.data() + first, count, out + static_cast<int64_t>(out_y) * w, w);
  }
}

// The adjoint of filter_rows: the padded row's gradient (pad[i] sums k[j] grad[i - j] in the order of j), folded
// back onto the pixels the padding copied.
void filter_rows_adjoint(const float* grad, float* out, int h, int w, const float* k, int r, FilterScratch& scratch) {
  std::vector<float>& zeros_around = scratch.pad;  // [w + 4 r]: the grad row with 2 r zeros each side
  const int wide = w + 2 * r;
  float* pad = scratch.padded_grad.data();
  for (int j = 0; j <= 2 * r; ++j) scratch.rows[j] = zeros_around.data() + 2 * r - j;
  std::fill(zeros_around.begin(), zeros_around.end(), 0.0f);
  for (int y = 0; y < h; ++y) {
    const float* src = grad + static_cast<int64_t>(y) * w;
    std::copy(src, src + w, zeros_around.begin() + 2 * r);
    weighted_sum(scratch.rows.data(), k, 2 * r + 1, pad, wide);  // adding k[j] x 0 leaves a sum as it is
    float* dst = out + static_cast<int64_t>(y) * w;
    for (int x = 0; x < w; ++x) dst[x] = pad[x + r];
    for (int i = -r; i < 0; ++i) dst[-i] += pad[i + r];
    for (int i = w; i < w + r; ++i) dst[2 * (w - 1) - i] += pad[i + r];
  }
}

}  // namespace

double photometric_loss(const float* prediction, const float* target, int h, int w, int c, const float* window,
                        int radius, float lambda, float* grad, int num_threads) {
  const int64_t hw = static_cast<int64_t>(h) * w;
  const double count = static_cast<double>(hw) * c;
  const int threads = num_threads > 0 ? num_threads : 1;
  // The moment and gradient planes: every value is written before it is read, so the buffers of the previous call
  // (of this thread) serve again, without the page faults and zero fill of 8 MB of fresh memory a step.
  // (The OpenMP threads below reach them through these references: a thread_local named inside the parallel region
  // would be each thread's own.)
  thread_local std::vector<float> kept_moments, kept_scratch;
  if (kept_moments.size() < static_cast<size_t>(kMoments * c * hw)) {
    kept_moments.resize(static_cast<size_t>(kMoments * c * hw));
    kept_scratch.resize(kept_moments.size());
  }
  std::vector<float>& moments = kept_moments;
  std::vector<float>& scratch = kept_scratch;
  std::vector<double> ssim_rows(h), l1_rows(h);
  auto plane = [hw](std::vector<float>& v, int index) { return v.data() + index * hw; };

  const AdjointTaps adjoint_taps(h, window, radius);

#pragma omp parallel num_threads(threads)
  {
    FilterScratch filter_scratch(w, radius, std::max(2 * radius + 1, adjoint_taps.max_taps()));
    // The moment planes of each channel, filtered.
#pragma omp for schedule(static)
    for (int y = 0; y < h; ++y) {
      for (int ch = 0; ch < c; ++ch) {
        float* mx = plane(moments, ch * kMoments) + static_cast<int64_t>(y) * w;
        float* my = mx + hw;
        float* mxx = my + hw;
        float* myy = mxx + hw;
        float* mxy = myy + hw;
        for (int x = 0; x < w; ++x) {
          const int64_t at = (static_cast<int64_t>(y) * w + x) * c + ch;
          const float a = prediction[at], b = target[at];
          mx[x] = a, my[x] = b, mxx[x] = a * a, myy[x] = b * b, mxy[x] = a * b;
        }
      }
    }
#pragma omp for schedule(static)
    for (int p = 0; p < kMoments * c; ++p) {
      filter_rows(plane(moments, p), plane(scratch, p), h, w, window, radius, filter_scratch);
      filter_columns(plane(scratch, p), plane(moments, p), h, w, window, radius, filter_scratch);
    }
    // SSIM per pixel, the L1 term, and d loss / d (mean_x, E[x^2], E[x y]) into the scratch planes. The pixels'
    // values first (a loop the compiler vectorises), then their sums in double, in order.
    const float scale = static_cast<float>(-lambda / count);
    std::vector<float> ssim_row(w);
#pragma omp for schedule(static)
    for (int y = 0; y < h; ++y) {
      double ssim_sum = 0.0, l1_sum = 0.0;
      for (int ch = 0; ch < c; ++ch) {
        const int64_t row = static_cast<int64_t>(y) * w;
        const float* mx = plane(moments, ch * kMoments) + row;
        const float* my = mx + hw;
        const float* exx = my + hw;
        const float* eyy = exx + hw;
        const float* exy = eyy + hw;
        float* d_mean = plane(scratch, ch * kPartials) + row;
        float* d_exx = d_mean + hw;
        float* d_exy = d_exx + hw;
        float* ssim_px = ssim_row.data();
        for (int x = 0; x < w; ++x) {
          const float mean_x = mx[x], mean_y = my[x];
          const float a1 = 2.0f * mean_x * mean_y + kC1;
          const float a2 = 2.0f * (exy[x] - mean_x * mean_y) + kC2;
          const float b1 = mean_x * mean_x + mean_y * mean_y + kC1;
          const float b2 = (exx[x] - mean_x * mean_x) + (eyy[x] - mean_y * mean_y) + kC2;
          const float den = b1 * b2 + kEps;
          const float s = a1 * a2 / den;
          ssim_px[x] = s;
          d_mean[x] = scale * (2.0f * mean_y * (a2 - a1) - 2.0f * mean_x * s * (b2 - b1)) / den;
          d_exx[x] = scale * (-s * b1 / den);
          d_exy[x] = scale * (2.0f * a1 / den);
        }
        for (int x = 0; x < w; ++x) {
          const int64_t at = (row + x) * c + ch;
          ssim_sum += ssim_px[x];
          l1_sum += std::abs(static_cast<double>(prediction[at]) - target[at]);
        }
      }
      ssim_rows[y] = ssim_sum;
      l1_rows[y] = l1_sum;
    }
    // Back through the filters: columns' adjoint, then rows'.
#pragma omp for schedule(static)
    for (int p = 0; p < kPartials * c; ++p) {
      filter_columns_adjoint(plane(scratch, p), plane(moments, p), h, w, adjoint_taps, filter_scratch);
      filter_rows_adjoint(plane(moments, p), plane(scratch, p), h, w, window, radius, filter_scratch);
    }
    const float l1_scale = static_cast<float>((1.0 - lambda) / count);
#pragma omp for schedule(static)
    for (int y = 0; y < h; ++y) {
      for (int ch = 0; ch < c; ++ch) {
        const int64_t row = static_cast<int64_t>(y) * w;
        const float* g_mean = plane(scratch, ch * kPartials) + row;
        const float* g_exx = g_mean + hw;
        const float* g_exy = g_exx + hw;
        for (int x = 0; x < w; ++x) {
          const int64_t at = (row + x) * c + ch;
          const float a = prediction[at], b = target[at];
          const float sign = a > b ? 1.0f : (a < b ? -1.0f : 0.0f);
          grad[at] = l1_scale * sign + g_mean[x] + 2.0f * a * g_exx[x] + b * g_exy[x];
        }
      }
    }
  }
  double ssim_total = 0.0, l1_total = 0.0;
  for (int y = 0; y < h; ++y) ssim_total += ssim_rows[y], l1_total += l1_rows[y];
  return (1.0 - lambda) * (l1_total / count) + lambda * (1.0 - ssim_total / count);
}
