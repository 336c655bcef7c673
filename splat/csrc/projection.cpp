// EWA projection of 3D Gaussians into one pinhole view, forward and hand-written backward.
//
// The same arithmetic as the torch reference `splat.projection.project_gaussians` (3DGS / gsplat):
//   p = R_cw m + t,  z_safe = z if near < z < far else 1,
//   (u, v) = (fx x / z_safe + cx, fy y / z_safe + cy),
//   A = R_cw R(q / |q|) diag(s)   (R S in camera axes),
//   J = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]] with (tx, ty) the mean clamped to
//       0.3 tan(fov) beyond the image border (gsplat),
//   Sigma2d = (J A)(J A)^T + eps2d I,  conic = Sigma2d^-1 as (a, b, c),
//   opacity * sqrt(det(Sigma2d - eps2d I) / det(Sigma2d)) when antialiased (Mip-Splatting).
// The backward is the chain rule of exactly these expressions, including the torch reference's
// choices at the culling branches (a culled Gaussian's z_safe = 1 and det = 1 are constants), so
// both paths give the same gradients. The alpha threshold (1/255) is passed in by the caller.

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

#include "kernel_api.h"

namespace {

struct Camera {
  double R[3][3];
  double t[3];
  double fx, fy, cx, cy;
  double lim_x_pos, lim_x_neg, lim_y_pos, lim_y_neg;
};

template <typename T>
Camera make_camera(const T* cam_from_world, const T* K, int64_t width, int64_t height) {
  Camera c;
  for (int i = 0; i < 3; ++i) {
    for (int k = 0; k < 3; ++k) c.R[i][k] = cam_from_world[i * 4 + k];
    c.t[i] = cam_from_world[i * 4 + 3];
  }
  c.fx = K[0];
  c.fy = K[4];
  c.cx = K[2];
  c.cy = K[5];
  const double tan_fovx = 0.5 * double(width) / c.fx, tan_fovy = 0.5 * double(height) / c.fy;
  c.lim_x_pos = (double(width) - c.cx) / c.fx + 0.3 * tan_fovx;
  c.lim_x_neg = c.cx / c.fx + 0.3 * tan_fovx;
  c.lim_y_pos = (double(height) - c.cy) / c.fy + 0.3 * tan_fovy;
  c.lim_y_neg = c.cy / c.fy + 0.3 * tan_fovy;
  return c;
}

// Rotation of the normalised quaternion (w, x, y, z) and the norm used.
inline void quat_to_rot(const double q[4], double qn[4], double& norm, double R[3][3]) {
  norm = std::max(std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]), 1e-12);
  for (int i = 0; i < 4; ++i) qn[i] = q[i] / norm;
  const double w = qn[0], x = qn[1], y = qn[2], z = qn[3];
  R[0][0] = 1 - 2 * (y * y + z * z);
  R[0][1] = 2 * (x * y - w * z);
  R[0][2] = 2 * (x * z + w * y);
  R[1][0] = 2 * (x * y + w * z);
  R[1][1] = 1 - 2 * (x * x + z * z);
  R[1][2] = 2 * (y * z - w * x);
  R[2][0] = 2 * (x * z - w * y);
  R[2][1] = 2 * (y * z + w * x);
  R[2][2] = 1 - 2 * (x * x + y * y);
}

// Everything the forward computes for one Gaussian, kept for the backward.
struct Local {
  double p[3];        // camera-frame mean
  bool in_depth;
  double zs, inv_z;   // z_safe and 1 / z_safe
  double qn[4], qnorm, Rg[3][3];
  double M[3][3];     // R(q) diag(s)
  double A[3][3];     // R_cw M
  int clamp_x, clamp_y;  // 0: Jacobian at the mean, +1: at the positive limit, -1: at the negative limit
  double tx, ty;
  double T0[3], T1[3];
  double a0, b, c0, det_orig, a, c, det;
  bool ok_det;
  double det_s;       // det if ok_det else 1
  double comp;        // antialiasing compensation (1 when not antialiased)
};

template <typename T>
void evaluate(const Camera& cam, const T* mean, const T* quat, const T* scale, double near_plane, double far_plane,
              double eps2d, bool antialiased, Local& L) {
  const double m[3] = {double(mean[0]), double(mean[1]), double(mean[2])};
  for (int i = 0; i < 3; ++i) L.p[i] = cam.R[i][0] * m[0] + cam.R[i][1] * m[1] + cam.R[i][2] * m[2] + cam.t[i];
  const double z = L.p[2];
  L.in_depth = z > near_plane && z < far_plane;
  L.zs = L.in_depth ? z : 1.0;
  L.inv_z = 1.0 / L.zs;
  const double q[4] = {double(quat[0]), double(quat[1]), double(quat[2]), double(quat[3])};
  quat_to_rot(q, L.qn, L.qnorm, L.Rg);
  for (int k = 0; k < 3; ++k)
    for (int j = 0; j < 3; ++j) L.M[k][j] = L.Rg[k][j] * double(scale[j]);
  for (int i = 0; i < 3; ++i)
    for (int j = 0; j < 3; ++j) L.A[i][j] = cam.R[i][0] * L.M[0][j] + cam.R[i][1] * L.M[1][j] + cam.R[i][2] * L.M[2][j];
  const double rx = L.p[0] / L.zs, ry = L.p[1] / L.zs;
  // torch.minimum(lim_pos, torch.maximum(-lim_neg, r)).
  double cxr = rx;
  L.clamp_x = 0;
  if (rx < -cam.lim_x_neg) { cxr = -cam.lim_x_neg; L.clamp_x = -1; }
  if (cxr > cam.lim_x_pos) { cxr = cam.lim_x_pos; L.clamp_x = 1; }
  double cyr = ry;
  L.clamp_y = 0;
  if (ry < -cam.lim_y_neg) { cyr = -cam.lim_y_neg; L.clamp_y = -1; }
  if (cyr > cam.lim_y_pos) { cyr = cam.lim_y_pos; L.clamp_y = 1; }
  L.tx = L.zs * cxr;
  L.ty = L.zs * cyr;
  const double iz = L.inv_z;
  const double al0 = cam.fx * iz, be0 = cam.fx * L.tx * iz * iz;
  const double al1 = cam.fy * iz, be1 = cam.fy * L.ty * iz * iz;
  for (int j = 0; j < 3; ++j) {
    L.T0[j] = al0 * L.A[0][j] - be0 * L.A[2][j];
    L.T1[j] = al1 * L.A[1][j] - be1 * L.A[2][j];
  }
  L.a0 = L.T0[0] * L.T0[0] + L.T0[1] * L.T0[1] + L.T0[2] * L.T0[2];
  L.b = L.T0[0] * L.T1[0] + L.T0[1] * L.T1[1] + L.T0[2] * L.T1[2];
  L.c0 = L.T1[0] * L.T1[0] + L.T1[1] * L.T1[1] + L.T1[2] * L.T1[2];
  L.det_orig = L.a0 * L.c0 - L.b * L.b;
  L.a = L.a0 + eps2d;
  L.c = L.c0 + eps2d;
  L.det = L.a * L.c - L.b * L.b;
  L.ok_det = L.det > 0;
  L.det_s = L.ok_det ? L.det : 1.0;
  L.comp = antialiased ? std::sqrt(std::max(L.det_orig / L.det_s, 0.0)) : 1.0;
}

template <typename F>
void parallel_for(int64_t n, int32_t num_threads, F&& body) {
  const int64_t min_per_thread = 4096;
  int64_t workers = std::max<int64_t>(1, std::min<int64_t>(num_threads, (n + min_per_thread - 1) / min_per_thread));
  if (workers == 1) {
    body(int64_t(0), n, 0);
    return;
  }
  std::vector<std::thread> pool;
  const int64_t chunk = (n + workers - 1) / workers;
  for (int64_t w = 0; w < workers; ++w) {
    const int64_t lo = w * chunk, hi = std::min(n, lo + chunk);
    if (lo >= hi) break;
    pool.emplace_back([&body, lo, hi, w] { body(lo, hi, w); });
  }
  for (auto& th : pool) th.join();
}

template <typename T>
void forward_impl(int64_t n, const T* means, const T* quats, const T* scales, const T* opacities,
                  const T* cam_from_world, const T* K, int64_t width, int64_t height, double near_plane,
                  double far_plane, double eps2d, int32_t antialiased, double alpha_min, T* out_means2d,
                  T* out_conics, T* out_depths, T* out_opacities, T* out_extents, int32_t* out_visible,
                  int32_t num_threads) {
  const Camera cam = make_camera(cam_from_world, K, width, height);
  parallel_for(n, num_threads, [&](int64_t lo, int64_t hi, int64_t) {
    Local L;
    for (int64_t g = lo; g < hi; ++g) {
      evaluate(cam, means + 3 * g, quats + 4 * g, scales + 3 * g, near_plane, far_plane, eps2d, antialiased != 0, L);
      const double u = cam.fx * L.p[0] * L.inv_z + cam.cx;
      const double v = cam.fy * L.p[1] * L.inv_z + cam.cy;
      out_means2d[2 * g] = T(u);
      out_means2d[2 * g + 1] = T(v);
      out_conics[3 * g] = T(L.c / L.det_s);
      out_conics[3 * g + 1] = T(-L.b / L.det_s);
      out_conics[3 * g + 2] = T(L.a / L.det_s);
      out_depths[g] = T(L.p[2]);
      const double opac = double(opacities[g]) * L.comp;
      out_opacities[g] = T(opac);
      // Box outside which opac * exp(-0.5 d^T Sigma^-1 d) < alpha_min, in the output precision as the
      // torch reference computes it.
      const T opac_t = T(opac);
      const T r2 = T(2.0) * std::log(std::max(opac_t, T(1e-30)) / T(alpha_min));
      const bool has_alpha = r2 > 0;
      const T r = std::sqrt(std::max(r2, T(0)));
      const T ext_x = r * std::sqrt(std::max(T(L.a), T(0)));
      const T ext_y = r * std::sqrt(std::max(T(L.c), T(0)));
      const T ut = T(u), vt = T(v);
      const bool on_image = (ut + ext_x > 0) && (ut - ext_x < T(width)) && (vt + ext_y > 0) && (vt - ext_y < T(height));
      const bool finite = std::isfinite(ut) && std::isfinite(vt) && std::isfinite(ext_x) && std::isfinite(ext_y);
      const bool vis = L.in_depth && L.ok_det && has_alpha && on_image && finite;
      out_visible[g] = vis ? 1 : 0;
      out_extents[2 * g] = vis ? ext_x : T(0);
      out_extents[2 * g + 1] = vis ? ext_y : T(0);
    }
  });
}

template <typename T>
void backward_impl(int64_t n, const T* means, const T* quats, const T* scales, const T* opacities,
                   const T* cam_from_world, const T* K, int64_t width, int64_t height, double near_plane,
                   double far_plane, double eps2d, int32_t antialiased, const T* g_means2d, const T* g_conics,
                   const T* g_depths, const T* g_opacities_out, T* g_means, T* g_quats, T* g_scales, T* g_opacities,
                   T* g_cam_rows, T* g_K_rows, int32_t num_threads) {
  const Camera cam = make_camera(cam_from_world, K, width, height);
  const bool aa = antialiased != 0;
  parallel_for(n, num_threads, [&](int64_t lo, int64_t hi, int64_t) {
    Local L;
    for (int64_t g = lo; g < hi; ++g) {
      evaluate(cam, means + 3 * g, quats + 4 * g, scales + 3 * g, near_plane, far_plane, eps2d, aa, L);
      const double gu = g_means2d[2 * g], gv = g_means2d[2 * g + 1];
      const double gA = g_conics[3 * g], gB = g_conics[3 * g + 1], gC = g_conics[3 * g + 2];
      const double gop = g_opacities_out[g];
      const double o = opacities[g];
      double g_fx = 0, g_fy = 0, g_cx = 0, g_cy = 0;
      double g_p[3] = {0, 0, double(g_depths[g])};
      double g_zs = 0;

      // conic = (c, -b, a) / det_s.
      double g_a = 0, g_b = 0, g_c = 0, g_a0 = 0, g_c0 = 0;
      if (L.ok_det) {
        const double inv = 1.0 / L.det;
        const double g_det = -(gA * L.c - gB * L.b + gC * L.a) * inv * inv;
        g_a = gC * inv + g_det * L.c;
        g_c = gA * inv + g_det * L.a;
        g_b = -gB * inv - 2.0 * L.b * g_det;
      } else {
        g_a = gC;
        g_c = gA;
        g_b = -gB;
      }
      // opacity_out = o * comp, comp = sqrt(max(det_orig / det_s, 0)).
      if (g_opacities) g_opacities[g] = T(gop * L.comp);
      if (aa) {
        const double ratio = L.det_orig / L.det_s;
        if (ratio > 0) {
          const double g_ratio = gop * o * 0.5 / L.comp;
          const double g_det_orig = g_ratio / L.det_s;
          g_a0 += g_det_orig * L.c0;
          g_c0 += g_det_orig * L.a0;
          g_b += -2.0 * L.b * g_det_orig;
          if (L.ok_det) {
            const double g_det = -g_ratio * ratio / L.det_s;
            g_a += g_det * L.c;
            g_c += g_det * L.a;
            g_b += -2.0 * L.b * g_det;
          }
        }
      }
      g_a0 += g_a;
      g_c0 += g_c;
      // a0 = T0.T0, b = T0.T1, c0 = T1.T1.
      double gT0[3], gT1[3];
      for (int j = 0; j < 3; ++j) {
        gT0[j] = 2.0 * g_a0 * L.T0[j] + g_b * L.T1[j];
        gT1[j] = 2.0 * g_c0 * L.T1[j] + g_b * L.T0[j];
      }
      // T0 = al0 A0 - be0 A2, T1 = al1 A1 - be1 A2.
      const double iz = L.inv_z;
      const double al0 = cam.fx * iz, be0 = cam.fx * L.tx * iz * iz;
      const double al1 = cam.fy * iz, be1 = cam.fy * L.ty * iz * iz;
      double gAm[3][3];
      double g_al0 = 0, g_be0 = 0, g_al1 = 0, g_be1 = 0;
      for (int j = 0; j < 3; ++j) {
        gAm[0][j] = al0 * gT0[j];
        gAm[1][j] = al1 * gT1[j];
        gAm[2][j] = -be0 * gT0[j] - be1 * gT1[j];
        g_al0 += gT0[j] * L.A[0][j];
        g_be0 -= gT0[j] * L.A[2][j];
        g_al1 += gT1[j] * L.A[1][j];
        g_be1 -= gT1[j] * L.A[2][j];
      }
      g_fx += g_al0 * iz + g_be0 * L.tx * iz * iz;
      g_fy += g_al1 * iz + g_be1 * L.ty * iz * iz;
      g_zs += -g_al0 * cam.fx * iz * iz - 2.0 * g_be0 * cam.fx * L.tx * iz * iz * iz;
      g_zs += -g_al1 * cam.fy * iz * iz - 2.0 * g_be1 * cam.fy * L.ty * iz * iz * iz;
      const double g_tx = g_be0 * cam.fx * iz * iz;
      const double g_ty = g_be1 * cam.fy * iz * iz;
      // tx = z_safe * clamp(x / z_safe): x itself inside the limits, else z_safe * limit (limits depend on K).
      if (L.clamp_x == 0) {
        g_p[0] += g_tx;
      } else if (L.clamp_x > 0) {  // lim_x_pos = (1.15 W - cx) / fx
        g_zs += g_tx * cam.lim_x_pos;
        const double g_lim = g_tx * L.zs;
        g_fx += -g_lim * cam.lim_x_pos / cam.fx;
        g_cx += -g_lim / cam.fx;
      } else {  // -lim_x_neg, lim_x_neg = (cx + 0.15 W) / fx
        g_zs += -g_tx * cam.lim_x_neg;
        const double g_lim = -g_tx * L.zs;
        g_fx += -g_lim * cam.lim_x_neg / cam.fx;
        g_cx += g_lim / cam.fx;
      }
      if (L.clamp_y == 0) {
        g_p[1] += g_ty;
      } else if (L.clamp_y > 0) {
        g_zs += g_ty * cam.lim_y_pos;
        const double g_lim = g_ty * L.zs;
        g_fy += -g_lim * cam.lim_y_pos / cam.fy;
        g_cy += -g_lim / cam.fy;
      } else {
        g_zs += -g_ty * cam.lim_y_neg;
        const double g_lim = -g_ty * L.zs;
        g_fy += -g_lim * cam.lim_y_neg / cam.fy;
        g_cy += g_lim / cam.fy;
      }
      // (u, v) = (fx x / z_safe + cx, fy y / z_safe + cy).
      g_p[0] += gu * cam.fx * iz;
      g_p[1] += gv * cam.fy * iz;
      g_zs += -(gu * cam.fx * L.p[0] + gv * cam.fy * L.p[1]) * iz * iz;
      g_fx += gu * L.p[0] * iz;
      g_fy += gv * L.p[1] * iz;
      g_cx += gu;
      g_cy += gv;
      if (L.in_depth) g_p[2] += g_zs;

      // A = R_cw M, M = R(q) diag(s).
      double gM[3][3], g_Rcw[3][3];
      for (int k = 0; k < 3; ++k)
        for (int j = 0; j < 3; ++j)
          gM[k][j] = cam.R[0][k] * gAm[0][j] + cam.R[1][k] * gAm[1][j] + cam.R[2][k] * gAm[2][j];
      for (int i = 0; i < 3; ++i)
        for (int k = 0; k < 3; ++k)
          g_Rcw[i][k] = gAm[i][0] * L.M[k][0] + gAm[i][1] * L.M[k][1] + gAm[i][2] * L.M[k][2];
      double gR[3][3];
      for (int j = 0; j < 3; ++j) {
        double gs = 0;
        for (int k = 0; k < 3; ++k) {
          gR[k][j] = gM[k][j] * double(scales[3 * g + j]);
          gs += gM[k][j] * L.Rg[k][j];
        }
        if (g_scales) g_scales[3 * g + j] = T(gs);
      }
      if (g_quats) {
        const double w = L.qn[0], x = L.qn[1], y = L.qn[2], z = L.qn[3];
        double gqn[4];
        gqn[0] = 2 * (-z * gR[0][1] + y * gR[0][2] + z * gR[1][0] - x * gR[1][2] - y * gR[2][0] + x * gR[2][1]);
        gqn[1] = 2 * (y * gR[0][1] + z * gR[0][2] + y * gR[1][0] - 2 * x * gR[1][1] - w * gR[1][2] + z * gR[2][0] +
                      w * gR[2][1] - 2 * x * gR[2][2]);
        gqn[2] = 2 * (-2 * y * gR[0][0] + x * gR[0][1] + w * gR[0][2] + x * gR[1][0] + z * gR[1][2] - w * gR[2][0] +
                      z * gR[2][1] - 2 * y * gR[2][2]);
        gqn[3] = 2 * (-2 * z * gR[0][0] - w * gR[0][1] + x * gR[0][2] + w * gR[1][0] - 2 * z * gR[1][1] + y * gR[1][2] +
                      x * gR[2][0] + y * gR[2][1]);
        // qn = q / max(|q|, 1e-12): project out the radial part (none when the clamp is active).
        const double dot = gqn[0] * w + gqn[1] * x + gqn[2] * y + gqn[3] * z;
        const bool clamped = L.qnorm <= 1e-12;
        for (int i = 0; i < 4; ++i) g_quats[4 * g + i] = T((gqn[i] - (clamped ? 0.0 : dot * L.qn[i])) / L.qnorm);
      }
      // p = R_cw m + t.
      if (g_means) {
        for (int k = 0; k < 3; ++k)
          g_means[3 * g + k] = T(cam.R[0][k] * g_p[0] + cam.R[1][k] * g_p[1] + cam.R[2][k] * g_p[2]);
      }
      if (g_cam_rows) {
        T* row = g_cam_rows + 12 * g;
        for (int i = 0; i < 3; ++i) {
          for (int k = 0; k < 3; ++k) row[4 * i + k] = T(g_Rcw[i][k] + g_p[i] * double(means[3 * g + k]));
          row[4 * i + 3] = T(g_p[i]);
        }
      }
      if (g_K_rows) {
        T* row = g_K_rows + 4 * g;
        row[0] = T(g_fx);
        row[1] = T(g_fy);
        row[2] = T(g_cx);
        row[3] = T(g_cy);
      }
    }
  });
}

}  // namespace

#define SPLAT_DEFINE_PROJECTION(T, SUFFIX)                                                                      \
  extern "C" void splat_project_forward_##SUFFIX(                                                              \
      int64_t n, const T* means, const T* quats, const T* scales, const T* opacities, const T* cam_from_world,  \
      const T* K, int64_t width, int64_t height, double near_plane, double far_plane, double eps2d,            \
      int32_t antialiased, double alpha_min, T* out_means2d, T* out_conics, T* out_depths, T* out_opacities,   \
      T* out_extents, int32_t* out_visible, int32_t num_threads) {                                             \
    forward_impl<T>(n, means, quats, scales, opacities, cam_from_world, K, width, height, near_plane, far_plane, \
                    eps2d, antialiased, alpha_min, out_means2d, out_conics, out_depths, out_opacities,         \
                    out_extents, out_visible, num_threads);                                                    \
  }                                                                                                            \
  extern "C" void splat_project_backward_##SUFFIX(                                                             \
      int64_t n, const T* means, const T* quats, const T* scales, const T* opacities, const T* cam_from_world,  \
      const T* K, int64_t width, int64_t height, double near_plane, double far_plane, double eps2d,            \
      int32_t antialiased, const T* g_means2d, const T* g_conics, const T* g_depths, const T* g_opacities_out, \
      T* g_means, T* g_quats, T* g_scales, T* g_opacities, T* g_cam_rows, T* g_K_rows, int32_t num_threads) {  \
    backward_impl<T>(n, means, quats, scales, opacities, cam_from_world, K, width, height, near_plane,          \
                     far_plane, eps2d, antialiased, g_means2d, g_conics, g_depths, g_opacities_out, g_means,   \
                     g_quats, g_scales, g_opacities, g_cam_rows, g_K_rows, num_threads);                       \
  }

SPLAT_DEFINE_PROJECTION(float, f32)
SPLAT_DEFINE_PROJECTION(double, f64)
