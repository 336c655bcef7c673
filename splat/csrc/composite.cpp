// Tile compositing of 2D Gaussians on the CPU: forward and backward.
//
// Plain C++17 (no torch headers, so it builds in about a second); called via
// ctypes from splat/_cpu_kernel.py with pointers to contiguous tensors (C API: kernel_api.h).
// The maths is the same as splat/composite.py::_composite_tiles_torch (the
// reference the tests compare against) and as gsplat's rasterize_to_pixels:
//   pixel (row, col) is evaluated at (col + 0.5, row + 0.5);
//   sigma = 0.5 (a dx^2 + c dy^2) + b dx dy with d = mean - pixel (evaluated per row as
//   dx (a dx / 2 + b dy) + c dy^2 / 2, the same in both passes);
//   alpha = min(alpha_max, opacity * exp(-sigma)); skipped when sigma < 0 or
//   alpha < alpha_min; a pixel stops before the Gaussian that would bring the
//   transmittance to <= transmittance_min.
// The three rule constants are arguments, passed from splat/composite.py (ALPHA_MAX,
// TRANSMITTANCE_MIN) and splat/projection.py (ALPHA_MIN): they are defined there only.
// Outputs: accum (H, W, C) = sum_i c_i alpha_i T_i and T_final (H, W).
// The backward writes one gradient row per tile intersection, [d mean_x, d mean_y, d a, d b, d c,
// d opacity, d colour_0 .. d colour_{C-1}] (each tile is owned by one thread, so no atomics); the
// caller sums rows per Gaussian.

#include <atomic>
#include <cmath>
#include <cstdint>
#include <limits>
#include <algorithm>
#include <thread>
#include <vector>

#include "kernel_api.h"
#include "parallel.h"

namespace {


// Per-Gaussian record gathered per tile: [mx, my, a, b, c, o, skip_sigma].
// skip_sigma = log(o / alpha_min) * (1 + 1e-4) + 1e-6: sigma above it gives alpha < alpha_min for sure, so the
// exp() is skipped; at or below it the exact alpha test decides (identical results, much less work).
constexpr int64_t kStride = 7;

// Pixel box (tile-local, inclusive) outside which a Gaussian's computed sigma exceeds skip_sigma.
struct Box {
  int32_t c0, c1, r0, r1;  // empty when c0 > c1 or r0 > r1
};

// The ellipse 0.5 d^T Q d <= s (Q = [[a, b], [b, c]]) has half-widths sqrt(2 s Q^-1_xx) and
// sqrt(2 s Q^-1_yy). The pixel test uses sigma computed in T, whose rounding error is bounded by
// err = 8 eps_T (|a| dx^2 + |c| dy^2 + 2 |b dx dy|) / 2 over the tile; the box is taken for s + err,
// so every pixel the per-pixel test could accept lies inside it (the box never changes a result, it
// only skips pixels that the test would reject). When Q is not positive definite in double, or the
// bound is not finite, the whole tile is used.
template <typename T>
Box pixel_box(const T* gk, int64_t col_lo, int64_t col_hi, int64_t row_lo, int64_t row_hi) {
  Box full{int32_t(0), int32_t(col_hi - col_lo), int32_t(0), int32_t(row_hi - row_lo)};
  const double mx = gk[0], my = gk[1], a = gk[2], b = gk[3], c = gk[4], s = gk[6];
  if (!(s >= 0)) return Box{1, 0, 1, 0};  // opacity <= 0: never visible
  const double det = a * c - b * b;  // exact-ish: products of floats are exact in double
  if (!(det > 0) || !(a > 0) || !(c > 0)) return full;
  const double dx_max = std::max(std::fabs(mx - (col_lo + 0.5)), std::fabs(mx - (col_hi + 0.5)));
  const double dy_max = std::max(std::fabs(my - (row_lo + 0.5)), std::fabs(my - (row_hi + 0.5)));
  const double eps = double(std::numeric_limits<T>::epsilon());
  const double err = 4.0 * eps * (a * dx_max * dx_max + c * dy_max * dy_max + 2.0 * std::fabs(b) * dx_max * dy_max);
  const double s2 = 2.0 * (s + err) * (1.0 + 1e-6);
  const double ex = std::sqrt(s2 * c / det) + 1e-3, ey = std::sqrt(s2 * a / det) + 1e-3;
  if (!std::isfinite(ex) || !std::isfinite(ey)) return full;
  // Pixel centres col + 0.5 within [mx - ex, mx + ex].
  const double c0 = std::max(double(col_lo), std::ceil(mx - ex - 0.5));
  const double c1 = std::min(double(col_hi), std::floor(mx + ex - 0.5));
  const double r0 = std::max(double(row_lo), std::ceil(my - ey - 0.5));
  const double r1 = std::min(double(row_hi), std::floor(my + ey - 0.5));
  if (c0 > c1 || r0 > r1) return Box{1, 0, 1, 0};
  return Box{int32_t(c0 - col_lo), int32_t(c1 - col_lo), int32_t(r0 - row_lo), int32_t(r1 - row_lo)};
}

template <typename T>
void gather(int64_t n, int64_t begin, const int64_t* gaussian_ids, const T* means2d, const T* conics,
            const T* opacities, double alpha_min, int64_t col_lo, int64_t col_hi, int64_t row_lo,
            int64_t row_hi, T* g, Box* boxes) {
  for (int64_t k = 0; k < n; ++k) {
    const int64_t id = gaussian_ids[begin + k];
    T* gk = g + kStride * k;
    gk[0] = means2d[2 * id];
    gk[1] = means2d[2 * id + 1];
    gk[2] = conics[3 * id];
    gk[3] = conics[3 * id + 1];
    gk[4] = conics[3 * id + 2];
    gk[5] = opacities[id];
    const double o = double(opacities[id]);
    gk[6] = o > 0 ? T(std::log(o / alpha_min) * (1.0 + 1e-4) + 1e-6) : T(-1);
    boxes[k] = pixel_box(gk, col_lo, col_hi, row_lo, row_hi);
  }
}

// Each tile is processed Gaussian by Gaussian (front to back), visiting only the pixels of the
// Gaussian's box; per-pixel state lives in small arrays. For every pixel the sequence of operations
// is exactly that of a per-pixel loop over the tile's list, so results do not depend on the order.
template <typename T>
void forward_impl(int64_t tiles_x, int64_t tiles_y, int64_t tile_size, int64_t width, int64_t height,
                  const int64_t* tile_offsets, const int64_t* gaussian_ids, const T* means2d,
                  const T* conics, const T* colors, const T* opacities, int64_t C, T* out_accum,
                  T* out_transmittance, int32_t* out_last, double alpha_min_d, double alpha_max_d,
                  double transmittance_min_d, int num_threads) {
  const T alpha_min = T(alpha_min_d), alpha_max = T(alpha_max_d), t_min = T(transmittance_min_d);
  splat_parallel::dynamic_for(tiles_x * tiles_y, num_threads, [&](int64_t tile) {
    const int64_t ty = tile / tiles_x, tx = tile % tiles_x;
    const int64_t begin = tile_offsets[tile], end = tile_offsets[tile + 1];
    const int64_t n = end - begin;
    const int64_t col_lo = tx * tile_size, col_hi = std::min(width, (tx + 1) * tile_size) - 1;
    const int64_t row_lo = ty * tile_size, row_hi = std::min(height, (ty + 1) * tile_size) - 1;
    const int64_t tw = col_hi - col_lo + 1, th = row_hi - row_lo + 1, P = tw * th;
    std::vector<T> g(kStride * n);
    std::vector<Box> boxes(n);
    gather(n, begin, gaussian_ids, means2d, conics, opacities, alpha_min_d, col_lo, col_hi, row_lo, row_hi,
           g.data(), boxes.data());
    std::vector<T> trans(P, T(1)), acc(P * C, T(0));
    std::vector<int32_t> last(P, 0);
    std::vector<uint8_t> done(P, 0);
    int64_t active = P;
    for (int64_t k = 0; k < n && active > 0; ++k) {
      const Box bx = boxes[k];
      const T* gk = &g[kStride * k];
      const T* col_k = colors + C * gaussian_ids[begin + k];
      for (int32_t r = bx.r0; r <= bx.r1; ++r) {
        const T py = T(row_lo + r) + T(0.5);
        const T dy = gk[1] - py;
        // Row constants of sigma = dx (a dx / 2 + b dy) + c dy^2 / 2 (the same expression in the backward
        // pass, so both make the same alpha decisions).
        const T half_a = T(0.5) * gk[2], b_dy = gk[3] * dy, c_term = T(0.5) * gk[4] * dy * dy;
        for (int32_t cc = bx.c0; cc <= bx.c1; ++cc) {
          const int64_t p = int64_t(r) * tw + cc;
          if (done[p]) continue;
          const T px = T(col_lo + cc) + T(0.5);
          const T dx = gk[0] - px;
          const T sigma = dx * (half_a * dx + b_dy) + c_term;
          if (sigma < T(0) || sigma > gk[6]) continue;
          const T alpha = std::min(alpha_max, gk[5] * std::exp(-sigma));
          if (alpha < alpha_min) continue;
          const T next_t = trans[p] * (T(1) - alpha);
          if (next_t <= t_min) {
            done[p] = 1;
            --active;
            continue;
          }
          const T w = alpha * trans[p];
          T* a = &acc[p * C];
          for (int64_t c = 0; c < C; ++c) a[c] += w * col_k[c];
          trans[p] = next_t;
          last[p] = int32_t(k + 1);
        }
      }
    }
    for (int64_t r = 0; r < th; ++r) {
      for (int64_t cc = 0; cc < tw; ++cc) {
        const int64_t p = r * tw + cc, pix = (row_lo + r) * width + col_lo + cc;
        for (int64_t c = 0; c < C; ++c) out_accum[pix * C + c] = acc[p * C + c];
        out_transmittance[pix] = trans[p];
        out_last[pix] = last[p];
      }
    }
  });
}

// Back to front over the tile's list, each Gaussian over its box; per pixel the visits are those of
// the per-pixel reverse loop from last[pix] - 1 down to 0, and gradients of one Gaussian are summed
// over pixels in row-major order (deterministic, independent of the thread count).
template <typename T>
void backward_impl(int64_t tiles_x, int64_t tiles_y, int64_t tile_size, int64_t width, int64_t height,
                   const int64_t* tile_offsets, const int64_t* gaussian_ids, const T* means2d,
                   const T* conics, const T* colors, const T* opacities, int64_t C,
                   const T* transmittance, const int32_t* last, const T* grad_accum,
                   const T* grad_transmittance, T* g_rows, double alpha_min_d, double alpha_max_d,
                   int num_threads) {
  const T alpha_min = T(alpha_min_d), alpha_max = T(alpha_max_d);
  splat_parallel::dynamic_for(tiles_x * tiles_y, num_threads, [&](int64_t tile) {
    const int64_t ty = tile / tiles_x, tx = tile % tiles_x;
    const int64_t begin = tile_offsets[tile], end = tile_offsets[tile + 1];
    const int64_t n = end - begin;
    if (n == 0) return;
    const int64_t col_lo = tx * tile_size, col_hi = std::min(width, (tx + 1) * tile_size) - 1;
    const int64_t row_lo = ty * tile_size, row_hi = std::min(height, (ty + 1) * tile_size) - 1;
    const int64_t tw = col_hi - col_lo + 1, th = row_hi - row_lo + 1, P = tw * th;
    // Per-pixel state: transmittance after the Gaussian being visited, colour behind it, dL/dcolour,
    // and dL/dT_final * T_final.
    std::vector<T> trans(P), gtf(P), s(P * C, T(0)), gc(P * C);
    std::vector<int32_t> stop(P);
    int32_t k_end = 0;
    for (int64_t r = 0; r < th; ++r) {
      for (int64_t cc = 0; cc < tw; ++cc) {
        const int64_t p = r * tw + cc, pix = (row_lo + r) * width + col_lo + cc;
        stop[p] = last[pix];
        k_end = std::max(k_end, stop[p]);
        trans[p] = transmittance[pix];
        gtf[p] = grad_transmittance[pix] * transmittance[pix];
        for (int64_t c = 0; c < C; ++c) gc[p * C + c] = grad_accum[pix * C + c];
      }
    }
    if (k_end == 0) return;
    std::vector<T> g(kStride * n);
    std::vector<Box> boxes(n);
    gather(n, begin, gaussian_ids, means2d, conics, opacities, alpha_min_d, col_lo, col_hi, row_lo, row_hi,
           g.data(), boxes.data());
    // Rows [begin, end) of the per-intersection gradients belong to this tile only.
    for (int64_t k = k_end - 1; k >= 0; --k) {
      const Box bx = boxes[k];
      const T* gk = &g[kStride * k];
      const int64_t j = begin + k;
      const T* col_k = colors + C * gaussian_ids[j];
      // Sums over the box in registers, row by row in row-major order (independent of the thread count).
      T gm0 = T(0), gm1 = T(0), gc0 = T(0), gc1 = T(0), gc2 = T(0), go = T(0);
      T* row = g_rows + j * (6 + C);  // this row belongs to this tile only; starts at zero
      T* gcol = row + 6;
      for (int32_t r = bx.r0; r <= bx.r1; ++r) {
        const T py = T(row_lo + r) + T(0.5);
        const T dy = gk[1] - py;
        const T half_a = T(0.5) * gk[2], b_dy = gk[3] * dy, c_term = T(0.5) * gk[4] * dy * dy;
        // Per-row sums of d_sigma, d_sigma dx and d_sigma dx^2; the row's dy enters once at its end.
        T s0 = T(0), s1 = T(0), s2 = T(0);
        for (int32_t cc = bx.c0; cc <= bx.c1; ++cc) {
          const int64_t p = int64_t(r) * tw + cc;
          if (k >= stop[p]) continue;
          const T px = T(col_lo + cc) + T(0.5);
          const T dx = gk[0] - px;
          const T sigma = dx * (half_a * dx + b_dy) + c_term;
          if (sigma < T(0) || sigma > gk[6]) continue;
          const T e = std::exp(-sigma);
          const T raw = gk[5] * e;
          const T alpha = std::min(alpha_max, raw);
          if (alpha < alpha_min) continue;
          const T one_minus = T(1) - alpha;
          const T t_before = trans[p] / one_minus;
          const T w = alpha * t_before;
          T* sp = &s[p * C];
          const T* gcp = &gc[p * C];
          T d_alpha = T(0);
          for (int64_t c = 0; c < C; ++c) {
            gcol[c] += w * gcp[c];
            d_alpha += (col_k[c] - sp[c]) * gcp[c];
            sp[c] = alpha * col_k[c] + one_minus * sp[c];
          }
          d_alpha = d_alpha * t_before - gtf[p] / one_minus;
          trans[p] = t_before;
          if (raw > alpha_max) continue;  // clamped: no gradient to opacity / sigma
          go += d_alpha * e;
          const T d_sigma = -alpha * d_alpha;
          s0 += d_sigma;
          s1 += d_sigma * dx;
          s2 += d_sigma * dx * dx;
        }
        // d sigma / d(a, b, c) = (dx^2 / 2, dx dy, dy^2 / 2); d sigma / d mean = (a dx + b dy, b dx + c dy).
        gc0 += T(0.5) * s2;
        gc1 += dy * s1;
        gc2 += T(0.5) * dy * dy * s0;
        gm0 += gk[2] * s1 + gk[3] * dy * s0;
        gm1 += gk[3] * s1 + gk[4] * dy * s0;
      }
      row[0] = gm0;
      row[1] = gm1;
      row[2] = gc0;
      row[3] = gc1;
      row[4] = gc2;
      row[5] = go;
    }
  });
}

}  // namespace

#define SPLAT_EXPORT(T, SUFFIX)                                                                           \
  extern "C" void splat_composite_forward_##SUFFIX(                                                       \
      int64_t tiles_x, int64_t tiles_y, int64_t tile_size, int64_t width, int64_t height,                \
      const int64_t* tile_offsets, const int64_t* gaussian_ids, const T* means2d, const T* conics,       \
      const T* colors, const T* opacities, int64_t C, T* out_accum, T* out_transmittance,                \
      int32_t* out_last, double alpha_min, double alpha_max, double transmittance_min,                   \
      int32_t num_threads) {                                                                              \
    forward_impl<T>(tiles_x, tiles_y, tile_size, width, height, tile_offsets, gaussian_ids, means2d,     \
                    conics, colors, opacities, C, out_accum, out_transmittance, out_last, alpha_min,     \
                    alpha_max, transmittance_min, num_threads);                                          \
  }                                                                                                       \
  extern "C" void splat_composite_backward_##SUFFIX(                                                      \
      int64_t tiles_x, int64_t tiles_y, int64_t tile_size, int64_t width, int64_t height,                \
      const int64_t* tile_offsets, const int64_t* gaussian_ids, const T* means2d, const T* conics,       \
      const T* colors, const T* opacities, int64_t C, const T* transmittance, const int32_t* last,       \
      const T* grad_accum, const T* grad_transmittance, T* g_rows, double alpha_min, double alpha_max,   \
      int32_t num_threads) {                                                                              \
    backward_impl<T>(tiles_x, tiles_y, tile_size, width, height, tile_offsets, gaussian_ids, means2d,    \
                     conics, colors, opacities, C, transmittance, last, grad_accum, grad_transmittance,  \
                     g_rows, alpha_min, alpha_max, num_threads);                                         \
  }

SPLAT_EXPORT(float, f32)
SPLAT_EXPORT(double, f64)
