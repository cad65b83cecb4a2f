// Tile binning on the CPU: binning.py's rules (which tiles a Gaussian's footprint reaches, front-to-back order
// within a tile), with a stable sort by depth and a counting sort by tile instead of PyTorch's sort of every
// (tile, Gaussian) pair. Gaussians of equal depth keep their index order.
#include "bin.h"

#include <algorithm>
#include <cmath>
#include <numeric>

namespace {

constexpr int kTile = 16;

struct TileSpan {
  int x0, y0, x1, y1;  // first and last tile, inclusive; x1 < x0 when it reaches none
};

TileSpan span_of(float mx, float my, float ex, float ey, int width, int height) {
  ex += 1e-3f, ey += 1e-3f;  // binning.py's margin: the kernels test alpha exactly
  auto clamp_tile = [](float v, int size) {
    return static_cast<int>(std::min(std::max(v, 0.0f), static_cast<float>(size - 1))) / kTile;
  };
  return {clamp_tile(std::ceil(mx - ex - 0.5f), width), clamp_tile(std::ceil(my - ey - 0.5f), height),
          clamp_tile(std::floor(mx + ex - 0.5f), width), clamp_tile(std::floor(my + ey - 0.5f), height)};
}

}  // namespace

void bin_tiles(const float* means2d, const float* extents, const float* depths, const int32_t* radii, int64_t n,
               int width, int height, std::vector<int32_t>& offsets, std::vector<int32_t>& ids) {
  const int tiles_x = (width + kTile - 1) / kTile;
  const int num_tiles = tiles_x * ((height + kTile - 1) / kTile);
  std::vector<int32_t> order;
  for (int64_t g = 0; g < n; ++g) {
    if (radii[g] > 0) order.push_back(static_cast<int32_t>(g));
  }
  std::stable_sort(order.begin(), order.end(), [depths](int32_t a, int32_t b) { return depths[a] < depths[b]; });
  std::vector<TileSpan> spans(order.size());
  std::vector<int64_t> counts(num_tiles + 1, 0);
  for (size_t i = 0; i < order.size(); ++i) {
    const int32_t g = order[i];
    spans[i] = span_of(means2d[2 * g], means2d[2 * g + 1], extents[2 * g], extents[2 * g + 1], width, height);
    for (int ty = spans[i].y0; ty <= spans[i].y1; ++ty) {
      for (int tx = spans[i].x0; tx <= spans[i].x1; ++tx) ++counts[ty * tiles_x + tx + 1];
    }
  }
  std::partial_sum(counts.begin(), counts.end(), counts.begin());
  offsets.assign(counts.begin(), counts.end());
  ids.resize(counts[num_tiles]);
  std::vector<int64_t> next(counts.begin(), counts.end() - 1);
  for (size_t i = 0; i < order.size(); ++i) {
    for (int ty = spans[i].y0; ty <= spans[i].y1; ++ty) {
      for (int tx = spans[i].x0; tx <= spans[i].x1; ++tx) ids[next[ty * tiles_x + tx]++] = order[i];
    }
  }
}
