// The training loss (1 - w) * L1 + w * (1 - SSIM) of an image against its target, and its gradient
// with respect to the image, in one call (CPU, 2 threads in the trainer).
//
// Plain C++17, called via ctypes from splat/_cpu_kernel.py (C API: kernel_api.h). The maths is that
// of splat/losses.py::photometric_loss's torch path (mvgeo.image_metrics.ssim with
// border="reflect"), which the tests compare against:
//   moments mu_x, mu_y, E[x^2], E[y^2], E[xy] per channel, filtered by the separable window
//   taps (x) taps with half-sample symmetric borders (scipy's "reflect": d c b a | a b c d);
//   S = (2 mx my + c1)(2 cxy + c2) / ((mx^2 + my^2 + c1)(vx + vy + c2)),
//   vx = E[x^2] - mx^2, cxy = E[xy] - mx my; the loss uses the mean of S over channels and pixels.
// Gradient: with A = dS/dmx, B = dS/dE[x^2], D = dS/dE[xy] per pixel and F the filter operator,
//   d mean(S) / dx = (F^T A + 2 x F^T B + y F^T D) / N,
// and d L1 / dx = sign(x - y) / N (0 where they are equal, as torch's abs).
// Each 1-D pass is a small sparse operator along one axis (its rows list (source, weight) pairs,
// the reflected border included); its transpose is built from the same pairs, so the adjoint
// passes are gathers as well and every output row is written by one thread (no atomics). Away
// from the borders both are plain 2r+1-tap correlations (the transpose with the taps reversed),
// which the compiler vectorises. Sums of per-row partials are taken in row order, so the result
// does not depend on the thread count.

#include <algorithm>
#include <atomic>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

#include "kernel_api.h"
#include "parallel.h"

namespace {


// Half-sample symmetric index of v in [0, n) (any v: the image is mirrored repeatedly).
int64_t reflect(int64_t v, int64_t n) {
  const int64_t period = 2 * n;
  int64_t m = v % period;
  if (m < 0) m += period;
  return m >= n ? period - 1 - m : m;
}

// A 1-D filter along an axis of length n, as a sparse matrix in row form: out[i] = sum w * in[src]
// over the pairs of row i. `lo`..`hi` (exclusive) is the interior, where row i is exactly
// sum_k taps[k] * in[i + k - r] with `taps` (so the caller may use the dense loop there).
template <typename T>
struct AxisOp {
  std::vector<int64_t> ptr, src;
  std::vector<T> w;
  std::vector<T> taps;
  int64_t lo = 0, hi = 0, r = 0;
};

// The forward operator (rows: outputs, pairs: taps applied to reflected sources) and its transpose.
template <typename T>
void build_ops(int64_t n, const double* taps, int64_t K, AxisOp<T>& fwd, AxisOp<T>& adj) {
  const int64_t r = K / 2;
  // Dense n x n would be wasteful for long axes: collect (out, src, weight) with duplicates merged.
  std::vector<std::vector<std::pair<int64_t, double>>> rows(n), cols(n);
  for (int64_t i = 0; i < n; ++i) {
    for (int64_t k = 0; k < K; ++k) {
      const int64_t j = reflect(i + k - r, n);
      auto& row = rows[i];
      bool merged = false;
      for (auto& e : row) {
        if (e.first == j) {
          e.second += taps[k];
          merged = true;
          break;
        }
      }
      if (!merged) row.emplace_back(j, taps[k]);
    }
  }
  for (int64_t i = 0; i < n; ++i)
    for (const auto& e : rows[i]) cols[e.first].emplace_back(i, e.second);
  auto fill = [&](const std::vector<std::vector<std::pair<int64_t, double>>>& table, AxisOp<T>& op, bool reverse) {
    op.ptr.assign(1, 0);
    op.src.clear();
    op.w.clear();
    for (int64_t i = 0; i < n; ++i) {
      for (const auto& e : table[i]) {
        op.src.push_back(e.first);
        op.w.push_back(T(e.second));
      }
      op.ptr.push_back(int64_t(op.src.size()));
    }
    op.r = r;
    op.taps.resize(K);
    for (int64_t k = 0; k < K; ++k) op.taps[k] = T(taps[reverse ? K - 1 - k : k]);
    // Interior: rows whose pairs are exactly the K unreflected taps (n >= K needed).
    op.lo = r;
    op.hi = n >= K ? n - r : r;
  };
  fill(rows, fwd, false);
  fill(cols, adj, true);
}

// out[0..n) = op(in[0..n)) along a contiguous row.
template <typename T>
void apply_row(const AxisOp<T>& op, const T* in, T* out, int64_t n) {
  const bool dense = op.hi > op.lo;
  auto sparse_rows = [&](int64_t from, int64_t to) {
    for (int64_t i = from; i < to; ++i) {
      T acc = T(0);
      for (int64_t t = op.ptr[i]; t < op.ptr[i + 1]; ++t) acc += op.w[t] * in[op.src[t]];
      out[i] = acc;
    }
  };
  if (!dense) {
    sparse_rows(0, n);
    return;
  }
  sparse_rows(0, op.lo);
  sparse_rows(op.hi, n);
  const int64_t K = int64_t(op.taps.size());
  for (int64_t i = op.lo; i < op.hi; ++i) out[i] = T(0);
  for (int64_t k = 0; k < K; ++k) {
    const T tk = op.taps[k];
    const T* base = in + (k - op.r);
    for (int64_t i = op.lo; i < op.hi; ++i) out[i] += tk * base[i];
  }
}

// Row `out_row` of `out` (length W) = sum over the pairs of the operator's row i of w * (row src of
// the W-wide plane `in`).
template <typename T>
void apply_col(const AxisOp<T>& op, const T* in, T* out, int64_t i, int64_t W, int64_t out_row) {
  T* o = out + out_row * W;
  for (int64_t x = 0; x < W; ++x) o[x] = T(0);
  for (int64_t t = op.ptr[i]; t < op.ptr[i + 1]; ++t) {
    const T wt = op.w[t];
    const T* s = in + op.src[t] * W;
    for (int64_t x = 0; x < W; ++x) o[x] += wt * s[x];
  }
}

template <typename T>
void loss_impl(int64_t C, int64_t H, int64_t W, const T* rendered, const T* target, const double* taps,
               int64_t K, double c1_d, double c2_d, double ssim_weight, T* ws, double* out_terms, T* grad,
               int num_threads) {
  const int64_t P = H * W;
  AxisOp<T> fx, ax, fy, ay;
  build_ops(W, taps, K, fx, ax);
  build_ops(H, taps, K, fy, ay);
  const T c1 = T(c1_d), c2 = T(c2_d);
  // Workspace: 11 planes of H x W per channel: 0..4 the row-filtered moments, 5..7 dS/d(mx, E[x^2],
  // E[xy]) per pixel, 8..10 their column adjoints (the column passes read rows around the one they
  // write, so no plane is reused in place).
  auto plane = [&](int64_t c, int64_t k) { return ws + (c * 11 + k) * P; };
  std::vector<double> l1_rows(C * H, 0.0), ssim_rows(C * H, 0.0);

  // Pass 1: row-filter the five moment images; per-row L1 sums.
  splat_parallel::dynamic_for(C * H, num_threads, [&](int64_t item) {
    const int64_t c = item / H, y = item % H;
    const T* xr = rendered + c * P + y * W;
    const T* yr = target + c * P + y * W;
    std::vector<T> m(5 * W);
    double l1 = 0.0;
    for (int64_t x = 0; x < W; ++x) {
      const T a = xr[x], b = yr[x];
      m[x] = a;
      m[W + x] = b;
      m[2 * W + x] = a * a;
      m[3 * W + x] = b * b;
      m[4 * W + x] = a * b;
      l1 += std::fabs(double(a) - double(b));
    }
    l1_rows[item] = l1;
    for (int64_t k = 0; k < 5; ++k) apply_row(fx, &m[k * W], plane(c, k) + y * W, W);
  });

  // Pass 2: column-filter, SSIM per pixel, and the per-pixel derivatives of S by the moments.
  splat_parallel::dynamic_for(C * H, num_threads, [&](int64_t item) {
    const int64_t c = item / H, y = item % H;
    std::vector<T> mom(5 * W);
    for (int64_t k = 0; k < 5; ++k) apply_col(fy, plane(c, k), &mom[k * W], y, W, /*out_row=*/0);
    const T *mx = &mom[0], *my = &mom[W], *mxx = &mom[2 * W], *myy = &mom[3 * W], *mxy = &mom[4 * W];
    T* dA = plane(c, 5) + y * W;
    T* dB = plane(c, 6) + y * W;
    T* dD = plane(c, 7) + y * W;
    double s_sum = 0.0;
    for (int64_t x = 0; x < W; ++x) {
      const T ux = mx[x], uy = my[x];
      const T vx = mxx[x] - ux * ux, vy = myy[x] - uy * uy, cxy = mxy[x] - ux * uy;
      const T a1 = T(2) * ux * uy + c1, a2 = T(2) * cxy + c2;
      const T b1 = ux * ux + uy * uy + c1, b2 = vx + vy + c2;
      const T inv_den = T(1) / (b1 * b2);
      const T s = a1 * a2 * inv_den;
      s_sum += double(s);
      if (grad != nullptr) {
        // dS/dA1 = A2/(B1 B2), dS/dA2 = A1/(B1 B2), dS/dB1 = -S/B1, dS/dB2 = -S/B2;
        // A1 = 2 mx my + c1, A2 = 2 (mxy - mx my) + c2, B1 = mx^2 + my^2 + c1, B2 = mxx - mx^2 + vy + c2.
        const T s_b1 = s / b1, s_b2 = s / b2;
        dA[x] = T(2) * uy * (a2 - a1) * inv_den - T(2) * ux * s_b1 + T(2) * ux * s_b2;
        dB[x] = -s_b2;
        dD[x] = T(2) * a1 * inv_den;
      }
    }
    ssim_rows[item] = s_sum;
  });

  const double n_total = double(C) * double(P);
  double l1_sum = 0.0, ssim_sum = 0.0;
  for (int64_t i = 0; i < C * H; ++i) {
    l1_sum += l1_rows[i];
    ssim_sum += ssim_rows[i];
  }
  out_terms[0] = l1_sum / n_total;
  out_terms[1] = ssim_sum / n_total;
  if (grad == nullptr) return;

  // Pass 3: column adjoint of the three derivative planes (into planes 8..10).
  splat_parallel::dynamic_for(C * H, num_threads, [&](int64_t item) {
    const int64_t c = item / H, y = item % H;
    for (int64_t k = 0; k < 3; ++k) apply_col(ay, plane(c, 5 + k), plane(c, 8 + k), y, W, y);
  });

  // Pass 4: row adjoint, then the gradient of the loss.
  const T g_l1 = T((1.0 - ssim_weight) / n_total), g_s = T(-ssim_weight / n_total);
  splat_parallel::dynamic_for(C * H, num_threads, [&](int64_t item) {
    const int64_t c = item / H, y = item % H;
    std::vector<T> fa(W), fb(W), fd(W);
    apply_row(ax, plane(c, 8) + y * W, fa.data(), W);
    apply_row(ax, plane(c, 9) + y * W, fb.data(), W);
    apply_row(ax, plane(c, 10) + y * W, fd.data(), W);
    const T* xr = rendered + c * P + y * W;
    const T* yr = target + c * P + y * W;
    T* g = grad + c * P + y * W;
    for (int64_t x = 0; x < W; ++x) {
      const T diff = xr[x] - yr[x];
      const T sgn = diff > T(0) ? T(1) : (diff < T(0) ? T(-1) : T(0));
      g[x] = g_l1 * sgn + g_s * (fa[x] + T(2) * xr[x] * fb[x] + yr[x] * fd[x]);
    }
  });
}

}  // namespace

#define SPLAT_LOSS_EXPORT(T, SUFFIX)                                                                      \
  extern "C" void splat_photometric_loss_##SUFFIX(int64_t C, int64_t H, int64_t W, const T* rendered,    \
                                                  const T* target, const double* taps, int64_t K,         \
                                                  double c1, double c2, double ssim_weight, T* workspace, \
                                                  double* out_terms, T* grad, int32_t num_threads) {      \
    loss_impl<T>(C, H, W, rendered, target, taps, K, c1, c2, ssim_weight, workspace, out_terms, grad,     \
                 num_threads);                                                                            \
  }

SPLAT_LOSS_EXPORT(float, f32)
SPLAT_LOSS_EXPORT(double, f64)
