// Real spherical harmonics colour (degree 0..3, 3DGS / gsplat basis and ordering): forward and backward.
//
// Same maths as splat/sh.py::eval_sh (the reference the tests compare against):
//   u = d / max(|d|, eps);  colour_c = sum_{k < (degree+1)^2} B_k(u) sh[k][c].
// Backward: d sh[k][c] = B_k(u) g_c (zero for unused bases), and d d = (I - u u^T) / |d| * dL/du
// (dL/du / eps when |d| <= eps, as torch's normalize). Plain C++17, no torch headers; called via
// ctypes (splat/_cpu_kernel.py) with pointers to contiguous arrays (C API: kernel_api.h), except the
// coefficients, which come as two strided parts (the DC band and the rest; `Bands`), so a model that keeps
// them in two tensors is read without first copying them into one.
// The basis constants (C0, C1, C2[5], C3[7], in this order) and eps are arguments, passed from
// splat/sh.py, where they are defined.
// Gaussians are independent, so they are split into fixed blocks on up to num_threads threads
// (splat/csrc/parallel.h); each output is written by one thread, and results do not depend on the count.

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "kernel_api.h"
#include "parallel.h"

namespace {

// Offsets of the degree-1, -2 and -3 constants in the basis_constants array (C0 is at 0).
constexpr int kOffC1 = 1, kOffC2 = 2, kOffC3 = 7, kNumConstants = 14;

// The constants converted to T once per call, in a local array: the loops below then read them
// from memory the compiler knows nothing else writes (as fast as compiled-in constants).
template <typename T>
struct Constants {
  T c[kNumConstants];
  explicit Constants(const double* cst) {
    for (int k = 0; k < kNumConstants; ++k) c[k] = T(cst[k]);
  }
};

// Basis values b[0..nb) and, when grad != nullptr, their gradients w.r.t. the unit direction.
template <typename T>
void basis(int degree, const Constants<T>& cst, T x, T y, T z, T* b, T (*grad)[3]) {
  const T kC0 = cst.c[0], kC1 = cst.c[kOffC1];
  const T* kC2 = cst.c + kOffC2;
  const T* kC3 = cst.c + kOffC3;
  b[0] = T(kC0);
  if (grad) grad[0][0] = grad[0][1] = grad[0][2] = T(0);
  if (degree < 1) return;
  const T c1 = T(kC1);
  b[1] = -c1 * y;
  b[2] = c1 * z;
  b[3] = -c1 * x;
  if (grad) {
    grad[1][0] = 0, grad[1][1] = -c1, grad[1][2] = 0;
    grad[2][0] = 0, grad[2][1] = 0, grad[2][2] = c1;
    grad[3][0] = -c1, grad[3][1] = 0, grad[3][2] = 0;
  }
  if (degree < 2) return;
  const T xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  const T c20 = T(kC2[0]), c21 = T(kC2[1]), c22 = T(kC2[2]), c23 = T(kC2[3]), c24 = T(kC2[4]);
  b[4] = c20 * xy;
  b[5] = c21 * yz;
  b[6] = c22 * (T(2) * zz - xx - yy);
  b[7] = c23 * xz;
  b[8] = c24 * (xx - yy);
  if (grad) {
    grad[4][0] = c20 * y, grad[4][1] = c20 * x, grad[4][2] = 0;
    grad[5][0] = 0, grad[5][1] = c21 * z, grad[5][2] = c21 * y;
    grad[6][0] = T(-2) * c22 * x, grad[6][1] = T(-2) * c22 * y, grad[6][2] = T(4) * c22 * z;
    grad[7][0] = c23 * z, grad[7][1] = 0, grad[7][2] = c23 * x;
    grad[8][0] = T(2) * c24 * x, grad[8][1] = T(-2) * c24 * y, grad[8][2] = 0;
  }
  if (degree < 3) return;
  const T c30 = T(kC3[0]), c31 = T(kC3[1]), c32 = T(kC3[2]), c33 = T(kC3[3]), c34 = T(kC3[4]), c35 = T(kC3[5]),
          c36 = T(kC3[6]);
  b[9] = c30 * y * (T(3) * xx - yy);
  b[10] = c31 * xy * z;
  b[11] = c32 * y * (T(4) * zz - xx - yy);
  b[12] = c33 * z * (T(2) * zz - T(3) * xx - T(3) * yy);
  b[13] = c34 * x * (T(4) * zz - xx - yy);
  b[14] = c35 * z * (xx - yy);
  b[15] = c36 * x * (xx - T(3) * yy);
  if (grad) {
    grad[9][0] = T(6) * c30 * xy, grad[9][1] = T(3) * c30 * (xx - yy), grad[9][2] = 0;
    grad[10][0] = c31 * yz, grad[10][1] = c31 * xz, grad[10][2] = c31 * xy;
    grad[11][0] = T(-2) * c32 * xy, grad[11][1] = c32 * (T(4) * zz - xx - T(3) * yy), grad[11][2] = T(8) * c32 * yz;
    grad[12][0] = T(-6) * c33 * xz, grad[12][1] = T(-6) * c33 * yz,
    grad[12][2] = c33 * (T(6) * zz - T(3) * xx - T(3) * yy);
    grad[13][0] = c34 * (T(4) * zz - T(3) * xx - yy), grad[13][1] = T(-2) * c34 * xy, grad[13][2] = T(8) * c34 * xz;
    grad[14][0] = T(2) * c35 * xz, grad[14][1] = T(-2) * c35 * yz, grad[14][2] = c35 * (xx - yy);
    grad[15][0] = T(3) * c36 * (xx - yy), grad[15][1] = T(-6) * c36 * xy, grad[15][2] = 0;
  }
}

template <typename T>
void unit(const T* d, double norm_eps, T* u, T* norm_out) {
  const T norm = std::sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]);
  const T denom = norm > T(norm_eps) ? norm : T(norm_eps);
  u[0] = d[0] / denom, u[1] = d[1] / denom, u[2] = d[2] / denom;
  *norm_out = norm;
}

// Gaussians per work item: large enough that handing out items costs nothing next to the work.
constexpr int64_t kBlock = 2048;

template <typename F>
void for_blocks(int64_t n, int num_threads, F body) {
  splat_parallel::dynamic_for((n + kBlock - 1) / kBlock, num_threads, [&](int64_t blk) {
    for (int64_t i = blk * kBlock, end = std::min(n, (blk + 1) * kBlock); i < end; ++i) body(i);
  });
}

// Coefficient rows: band 0 of Gaussian i at sh0 + i * s0, bands 1.. at shN + i * sN (three values per band,
// adjacent). A contiguous (N, K, 3) array is sh0 = base, shN = base + 3, s0 = sN = 3 K; a model's separate
// DC and rest tensors (no copy into one array) are s0 = 3, sN = 3 (K - 1).
// The same layout serves the gradients (P = T, writable), where a part may be null (its gradient not wanted):
// `band` is then null too.
template <typename P>
struct Bands {
  P* sh0;
  int64_t s0;
  P* shN;
  int64_t sN;
  P* band(int64_t i, int k) const {
    P* part = k == 0 ? sh0 : shN;
    return part == nullptr ? nullptr : k == 0 ? part + i * s0 : part + i * sN + 3 * (k - 1);
  }
};

template <typename T>
void forward_impl(int64_t n, int degree, const Bands<const T>& sh, const T* dirs, const double* constants,
                  double norm_eps, T* out, int num_threads) {
  const Constants<T> cst(constants);
  const int nb = (degree + 1) * (degree + 1);
  for_blocks(n, num_threads, [&](int64_t i) {
    T u[3], norm, b[16];
    unit(dirs + 3 * i, norm_eps, u, &norm);
    basis<T>(degree, cst, u[0], u[1], u[2], b, nullptr);
    T acc[3] = {T(0), T(0), T(0)};
    for (int k = 0; k < nb; ++k) {
      const T* s = sh.band(i, k);
      for (int c = 0; c < 3; ++c) acc[c] += b[k] * s[c];
    }
    for (int c = 0; c < 3; ++c) out[3 * i + c] = acc[c];
  });
}

// The coefficients' gradients are written in the layout of `gsh` (either part may be null: not wanted). Bands
// above `degree` get zero gradients.
template <typename T>
void backward_impl(int64_t n, int64_t K, int degree, const Bands<const T>& sh, const T* dirs,
                   const double* constants, double norm_eps, const T* grad_out, const Bands<T>& gsh, T* g_dirs,
                   int num_threads) {
  const Constants<T> cst(constants);
  const int nb = (degree + 1) * (degree + 1);
  for_blocks(n, num_threads, [&](int64_t i) {
    T u[3], norm, b[16], gb[16][3];
    unit(dirs + 3 * i, norm_eps, u, &norm);
    basis<T>(degree, cst, u[0], u[1], u[2], b, gb);
    const T* g = grad_out + 3 * i;
    T du[3] = {T(0), T(0), T(0)};
    for (int k = 0; k < nb; ++k) {
      const T* s = sh.band(i, k);
      T* gs = gsh.band(i, k);
      T db = T(0);
      for (int c = 0; c < 3; ++c) {
        if (gs) gs[c] = b[k] * g[c];
        db += s[c] * g[c];
      }
      for (int a = 0; a < 3; ++a) du[a] += db * gb[k][a];
    }
    for (int k = std::max(nb, 1); k < K; ++k) {
      if (T* gs = gsh.band(i, k)) gs[0] = gs[1] = gs[2] = T(0);
    }
    T* gd = g_dirs + 3 * i;
    if (norm > T(norm_eps)) {
      const T dot = u[0] * du[0] + u[1] * du[1] + u[2] * du[2];
      for (int a = 0; a < 3; ++a) gd[a] = (du[a] - u[a] * dot) / norm;
    } else {
      for (int a = 0; a < 3; ++a) gd[a] = du[a] / T(norm_eps);
    }
  });
}

}  // namespace

#define SH_EXPORT(T, SUFFIX)                                                                              \
  extern "C" void splat_sh_forward_##SUFFIX(int64_t n, int64_t K, int32_t degree, const T* sh0, int64_t sh0_stride, \
                                             const T* shN, int64_t shN_stride, const T* dirs,               \
                                             const double* basis_constants, double norm_eps, T* out,       \
                                             int32_t num_threads) {                                        \
    (void)K;                                                                                              \
    forward_impl<T>(n, degree, Bands<const T>{sh0, sh0_stride, shN, shN_stride}, dirs, basis_constants, norm_eps, out, \
                    num_threads);                                                                         \
  }                                                                                                       \
  extern "C" void splat_sh_backward_##SUFFIX(int64_t n, int64_t K, int32_t degree, const T* sh0,              \
                                              int64_t sh0_stride, const T* shN, int64_t shN_stride,         \
                                              const T* dirs, const double* basis_constants, double norm_eps, \
                                              const T* grad_out, T* g_sh0, int64_t g_sh0_stride, T* g_shN,   \
                                              int64_t g_shN_stride, T* g_dirs, int32_t num_threads) {       \
    backward_impl<T>(n, K, degree, Bands<const T>{sh0, sh0_stride, shN, shN_stride}, dirs, basis_constants,       \
                     norm_eps, grad_out, Bands<T>{g_sh0, g_sh0_stride, g_shN, g_shN_stride}, g_dirs, num_threads); \
  }

SH_EXPORT(float, f32)
SH_EXPORT(double, f64)
