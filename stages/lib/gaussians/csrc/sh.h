// Interface of the CPU view-dependent colours of 3D Gaussians (plain C++, raw float32 arrays).
#pragma once

#include <cstdint>

// colors [N, 3] = max(0.5 + sum over the SH bands 0..degree of basis(d) sh, 0), d the unit direction from campos [3]
// to each mean [N, 3]; sh [N, K, 3] with K >= (degree + 1)^2.
void sh_colors_forward(const float* sh, const float* means, const float* campos, int64_t n, int k, int degree,
                       float* colors, int num_threads);

// d loss / d (sh [N, K, 3], means [N, 3]) from d loss / d colors [N, 3] (bands above degree get zeros).
void sh_colors_backward(const float* sh, const float* means, const float* campos, int64_t n, int k, int degree,
                        const float* grad_colors, float* grad_sh, float* grad_means, int num_threads);
