// EWA projection of 3D Gaussians on the CPU, forward and backward: the same arithmetic as
// stages/gaussians/projection.py (its docstring has the rules), one Gaussian per loop iteration. The PyTorch
// version runs some 60 small operations over [N] tensors forward and twice as many backward; here each
// Gaussian is projected, and its gradient computed, in registers.
//
// Gradients flow to the means, quaternions and scales (not to the camera: callers whose viewmat or K need a
// gradient use the PyTorch version). Every Gaussian is computed by one thread: the bits do not depend on the
// thread count.
#include "project.h"

#include <omp.h>

#include <algorithm>
#include <cmath>

namespace {

constexpr float kAlphaMin = 1.0f / 255.0f;

struct Camera {
  float r[3][3], t[3], fx, fy, cx, cy;
  float lim_x_neg, lim_x_pos, lim_y_neg, lim_y_pos;
};

Camera make_camera(const float* viewmat, const float* k, int width, int height) {
  Camera cam;
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) cam.r[a][b] = viewmat[4 * a + b];
    cam.t[a] = viewmat[4 * a + 3];
  }
  cam.fx = k[0], cam.fy = k[4], cam.cx = k[2], cam.cy = k[5];
  cam.lim_x_pos = (width - cam.cx) / cam.fx + 0.3f * width / cam.fx;
  cam.lim_x_neg = cam.cx / cam.fx + 0.3f * width / cam.fx;
  cam.lim_y_pos = (height - cam.cy) / cam.fy + 0.3f * height / cam.fy;
  cam.lim_y_neg = cam.cy / cam.fy + 0.3f * height / cam.fy;
  return cam;
}

// One Gaussian's forward values, kept for its backward.
struct Projected {
  float q[4], norm;                // unit quaternion (w, x, y, z) and the input's clamped norm
  float rot[3][3];                 // its rotation
  float p[3], z_safe, u, v;        // camera-frame position, the depth divided by, the clamped x / z and y / z
  bool clamped_x, clamped_y;
  float m[3][3];                   // camera <- local, columns scaled: viewmat R * R(q) * diag(s)
  float j0[3], j1[3];              // the Jacobian's rows
  float m0[3], m1[3];              // the rows of J M
  float a, b, c, det;              // the low-passed 2D covariance (a, b; b, c) and its determinant
};

Projected project_one(const Camera& cam, const float* mean, const float* quat, const float* scale, float eps2d,
                      float near) {
  Projected o;
  const float n2 = quat[0] * quat[0] + quat[1] * quat[1] + quat[2] * quat[2] + quat[3] * quat[3];
  o.norm = std::max(std::sqrt(n2), 1e-12f);
  for (int i = 0; i < 4; ++i) o.q[i] = quat[i] / o.norm;
  const float w = o.q[0], x = o.q[1], y = o.q[2], z = o.q[3];
  const float r[3][3] = {{1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)},
                         {2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)},
                         {2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)}};
  for (int a = 0; a < 3; ++a) {
    for (int b = 0; b < 3; ++b) o.rot[a][b] = r[a][b];
  }
  for (int a = 0; a < 3; ++a) {
    o.p[a] = cam.r[a][0] * mean[0] + cam.r[a][1] * mean[1] + cam.r[a][2] * mean[2] + cam.t[a];
  }
  o.z_safe = o.p[2] > near ? o.p[2] : 1.0f;
  const float ux = o.p[0] / o.z_safe, uy = o.p[1] / o.z_safe;
  o.u = std::min(std::max(ux, -cam.lim_x_neg), cam.lim_x_pos);
  o.v = std::min(std::max(uy, -cam.lim_y_neg), cam.lim_y_pos);
  o.clamped_x = o.u != ux, o.clamped_y = o.v != uy;
  const float tx = o.z_safe * o.u, ty = o.z_safe * o.v;
  for (int a = 0; a < 3; ++a) {
    for (int k = 0; k < 3; ++k) {
      o.m[a][k] = (cam.r[a][0] * r[0][k] + cam.r[a][1] * r[1][k] + cam.r[a][2] * r[2][k]) * scale[k];
    }
  }
  const float zz = o.z_safe * o.z_safe;
  o.j0[0] = cam.fx / o.z_safe, o.j0[1] = 0.0f, o.j0[2] = -cam.fx * tx / zz;
  o.j1[0] = 0.0f, o.j1[1] = cam.fy / o.z_safe, o.j1[2] = -cam.fy * ty / zz;
  for (int k = 0; k < 3; ++k) {
    o.m0[k] = o.j0[0] * o.m[0][k] + o.j0[2] * o.m[2][k];
    o.m1[k] = o.j1[1] * o.m[1][k] + o.j1[2] * o.m[2][k];
  }
  o.a = o.m0[0] * o.m0[0] + o.m0[1] * o.m0[1] + o.m0[2] * o.m0[2] + eps2d;
  o.b = o.m0[0] * o.m1[0] + o.m0[1] * o.m1[1] + o.m0[2] * o.m1[2];
  o.c = o.m1[0] * o.m1[0] + o.m1[1] * o.m1[1] + o.m1[2] * o.m1[2] + eps2d;
  o.det = o.a * o.c - o.b * o.b;
  return o;
}

}  // namespace

void project_forward(const ProjectInputs& in, float* means2d, float* conics, float* depths, int32_t* radii,
                     float* extents, int num_threads) {
  const Camera cam = make_camera(in.viewmat, in.k, in.width, in.height);
#pragma omp parallel for schedule(static) num_threads(num_threads)
  for (int64_t g = 0; g < in.num_gaussians; ++g) {
    const Projected o = project_one(cam, in.means + 3 * g, in.quats + 4 * g, in.scales + 3 * g, in.eps2d, in.near);
    const float det_safe = o.det > 0.0f ? o.det : 1.0f;
    conics[3 * g] = o.c / det_safe, conics[3 * g + 1] = -o.b / det_safe, conics[3 * g + 2] = o.a / det_safe;
    const float mx = cam.fx * o.p[0] / o.z_safe + cam.cx, my = cam.fy * o.p[1] / o.z_safe + cam.cy;
    means2d[2 * g] = mx, means2d[2 * g + 1] = my;
    depths[g] = o.p[2];
    // Visibility, the 3-sigma radius and the alpha >= 1/255 half-sizes.
    const float mid = 0.5f * (o.a + o.c);
    const float lambda_max = mid + std::sqrt(std::max(mid * mid - o.det, 0.1f));
    const float reach = 2.0f * std::log(std::max(in.opacities[g] / kAlphaMin, 1e-30f));
    const float ex = std::sqrt(std::max(reach * o.a, 0.0f)), ey = std::sqrt(std::max(reach * o.c, 0.0f));
    const bool on_screen = mx + ex > 0.0f && mx - ex < in.width && my + ey > 0.0f && my - ey < in.height;
    const bool visible = o.p[2] > in.near && o.det > 0.0f && reach > 0.0f && on_screen && std::isfinite(mx) &&
                         std::isfinite(my);
    radii[g] = visible ? static_cast<int32_t>(std::ceil(3.0f * std::sqrt(lambda_max))) : 0;
    extents[2 * g] = visible ? ex : 0.0f;
    extents[2 * g + 1] = visible ? ey : 0.0f;
  }
}

void project_backward(const ProjectInputs& in, const float* grad_means2d, const float* grad_conics,
                      const float* grad_depths, float* grad_means, float* grad_quats, float* grad_scales,
                      int num_threads) {
  const Camera cam = make_camera(in.viewmat, in.k, in.width, in.height);
#pragma omp parallel for schedule(static) num_threads(num_threads)
  for (int64_t g = 0; g < in.num_gaussians; ++g) {
    const float* scale = in.scales + 3 * g;
    const Projected o = project_one(cam, in.means + 3 * g, in.quats + 4 * g, scale, in.eps2d, in.near);
    const float* gc = grad_conics + 3 * g;
    // conics = (c, -b, a) / det where det > 0, else (c, -b, a)
    float ga, gb, gcc;
    if (o.det > 0.0f) {
      const float inv = 1.0f / o.det;
      const float c0 = o.c * inv, c1 = -o.b * inv, c2 = o.a * inv;
      // d det = c da - 2 b db + a dc; d (x / det) = dx / det - x d det / det^2
      const float g_det = -(gc[0] * c0 + gc[1] * c1 + gc[2] * c2) * inv;
      ga = gc[2] * inv + g_det * o.c;
      gb = -gc[1] * inv - 2.0f * g_det * o.b;
      gcc = gc[0] * inv + g_det * o.a;
    } else {
      ga = gc[2], gb = -gc[1], gcc = gc[0];
    }
    float gm0[3], gm1[3];
    for (int k = 0; k < 3; ++k) {
      gm0[k] = 2.0f * ga * o.m0[k] + gb * o.m1[k];
      gm1[k] = 2.0f * gcc * o.m1[k] + gb * o.m0[k];
    }
    // m0 = j0 M, m1 = j1 M (j0[1] = j1[0] = 0)
    float gm[3][3];
    for (int k = 0; k < 3; ++k) {
      gm[0][k] = o.j0[0] * gm0[k];
      gm[1][k] = o.j1[1] * gm1[k];
      gm[2][k] = o.j0[2] * gm0[k] + o.j1[2] * gm1[k];
    }
    float gj0[3], gj1[3];
    for (int a = 0; a < 3; ++a) {
      gj0[a] = o.m[a][0] * gm0[0] + o.m[a][1] * gm0[1] + o.m[a][2] * gm0[2];
      gj1[a] = o.m[a][0] * gm1[0] + o.m[a][1] * gm1[1] + o.m[a][2] * gm1[2];
    }
    const float zs = o.z_safe, zs2 = zs * zs, zs3 = zs2 * zs;
    const float tx = zs * o.u, ty = zs * o.v;
    float g_zs = -gj0[0] * cam.fx / zs2 + 2.0f * gj0[2] * cam.fx * tx / zs3 - gj1[1] * cam.fy / zs2 +
                 2.0f * gj1[2] * cam.fy * ty / zs3;
    const float g_tx = -gj0[2] * cam.fx / zs2, g_ty = -gj1[2] * cam.fy / zs2;
    const float* gm2 = grad_means2d + 2 * g;
    float gp[3] = {gm2[0] * cam.fx / zs, gm2[1] * cam.fy / zs, grad_depths[g]};
    g_zs -= gm2[0] * cam.fx * o.p[0] / zs2 + gm2[1] * cam.fy * o.p[1] / zs2;
    // tx = z_safe * clamp(x / z_safe): d tx = dx unclamped, the bound times d z_safe clamped
    if (o.clamped_x) g_zs += g_tx * o.u; else gp[0] += g_tx;
    if (o.clamped_y) g_zs += g_ty * o.v; else gp[1] += g_ty;
    if (o.p[2] > in.near) gp[2] += g_zs;
    for (int b = 0; b < 3; ++b) {
      grad_means[3 * g + b] = cam.r[0][b] * gp[0] + cam.r[1][b] * gp[1] + cam.r[2][b] * gp[2];
    }
    // M = R_view R(q) diag(s): d (R(q) diag(s)) = R_view^T dM
    float grot[3][3];
    for (int a = 0; a < 3; ++a) {
      for (int k = 0; k < 3; ++k) grot[a][k] = cam.r[0][a] * gm[0][k] + cam.r[1][a] * gm[1][k] + cam.r[2][a] * gm[2][k];
    }
    for (int k = 0; k < 3; ++k) {
      grad_scales[3 * g + k] = grot[0][k] * o.rot[0][k] + grot[1][k] * o.rot[1][k] + grot[2][k] * o.rot[2][k];
      for (int a = 0; a < 3; ++a) grot[a][k] *= scale[k];
    }
    const float w = o.q[0], x = o.q[1], y = o.q[2], z = o.q[3];
    const float (*G)[3] = grot;
    const float gq[4] = {
        2.0f * (-z * G[0][1] + y * G[0][2] + z * G[1][0] - x * G[1][2] - y * G[2][0] + x * G[2][1]),
        2.0f * (y * G[0][1] + z * G[0][2] + y * G[1][0] - 2.0f * x * G[1][1] - w * G[1][2] + z * G[2][0] +
                w * G[2][1] - 2.0f * x * G[2][2]),
        2.0f * (-2.0f * y * G[0][0] + x * G[0][1] + w * G[0][2] + x * G[1][0] + z * G[1][2] - w * G[2][0] +
                z * G[2][1] - 2.0f * y * G[2][2]),
        2.0f * (-2.0f * z * G[0][0] - w * G[0][1] + x * G[0][2] + w * G[1][0] - 2.0f * z * G[1][1] + y * G[1][2] +
                x * G[2][0] + y * G[2][1])};
    // q = v / max(|v|, 1e-12): d v = (d q - q (q . d q)) / |v| while |v| > 1e-12
    const float dot = w * gq[0] + x * gq[1] + y * gq[2] + z * gq[3];
    const bool normalised = o.norm > 1e-12f;
    for (int i = 0; i < 4; ++i) grad_quats[4 * g + i] = (gq[i] - (normalised ? o.q[i] * dot : 0.0f)) / o.norm;
  }
}
