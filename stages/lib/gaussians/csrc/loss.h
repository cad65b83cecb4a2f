// Interface of the CPU photometric loss (plain C++, raw float32 arrays).
#pragma once

// (1 - lambda) mean |prediction - target| + lambda (1 - mean SSIM) of two images [H, W, C] (kornia's SSIM,
// 'same' reflect padding, with the separable window [2 radius + 1]); writes d loss / d prediction into grad
// [H, W, C] and returns the loss.
double photometric_loss(const float* prediction, const float* target, int h, int w, int c, const float* window,
                        int radius, float lambda, float* grad, int num_threads);
