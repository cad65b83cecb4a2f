// Interface of the CPU EWA projection of 3D Gaussians (plain C++, raw float32 arrays).
#pragma once

#include <cstdint>

struct ProjectInputs {
  const float* means;      // [N, 3] world
  const float* quats;      // [N, 4] (w, x, y, z), normalised here
  const float* scales;     // [N, 3]
  const float* opacities;  // [N] (visibility and extents only)
  const float* viewmat;    // [4, 4] world-to-camera, row-major
  const float* k;          // [3, 3] intrinsics, row-major
  int64_t num_gaussians;
  int width, height;
  float eps2d, near;
};

// means2d [N, 2], conics [N, 3], depths [N], radii [N] (0 = not visible), extents [N, 2]: projection.py's fields.
void project_forward(const ProjectInputs& in, float* means2d, float* conics, float* depths, int32_t* radii,
                     float* extents, int num_threads);

// d loss / d (means [N, 3], quats [N, 4], scales [N, 3]) from d loss / d (means2d, conics, depths).
void project_backward(const ProjectInputs& in, const float* grad_means2d, const float* grad_conics,
                      const float* grad_depths, float* grad_means, float* grad_quats, float* grad_scales,
                      int num_threads);
