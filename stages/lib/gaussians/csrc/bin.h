// Interface of the CPU tile binning of projected Gaussians (plain C++).
#pragma once

#include <cstdint>
#include <vector>

// Per 16x16 tile (row-major), the visible Gaussians (radii > 0) whose alpha >= 1/255 footprint (means2d [N, 2] +-
// extents [N, 2]) reaches it, front to back (depths [N]): offsets [num_tiles + 1], ids [P].
void bin_tiles(const float* means2d, const float* extents, const float* depths, const int32_t* radii, int64_t n,
               int width, int height, std::vector<int32_t>& offsets, std::vector<int32_t>& ids);
