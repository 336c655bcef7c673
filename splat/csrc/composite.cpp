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
// d opacity, d colour_0 .. d colour_{C-1}] (each tile is owned by one thread, so no atomics);
// gather.cpp sums them per Gaussian.

#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <algorithm>
#include <type_traits>
#include <vector>

#include "kernel_api.h"
#include "parallel.h"

namespace {


// Per-Gaussian record gathered per tile: [mx, my, a, b, c, o, skip_sigma].
// skip_sigma = log(o / alpha_min) * (1 + 1e-4) + 1e-6: sigma above it gives alpha < alpha_min for sure, so the
// exp() is skipped; at or below it the exact alpha test decides (identical results, much less work).
constexpr int64_t kStride = 7;

// Pixel box (tile-local, inclusive) outside which a Gaussian's computed sigma exceeds skip_sigma, and what
// row_span needs to narrow each of its rows to the ellipse.
struct Box {
  int32_t c0, c1, r0, r1;  // empty when c0 > c1 or r0 > r1
  bool by_row;             // false: every pixel of a row of the box is visited
  double s2, det, margin;  // 2 (s + err) (1 + 1e-6); a c - b^2; the span's widening, px
  double inv_a, b_over_a;  // 1 / a, b / a
};

// The ellipse 0.5 d^T Q d <= s (Q = [[a, b], [b, c]]) has half-widths sqrt(2 s Q^-1_xx) and
// sqrt(2 s Q^-1_yy). The pixel test uses sigma computed in T, whose rounding error is bounded by
// err = 8 eps_T (|a| dx^2 + |c| dy^2 + 2 |b dx dy|) / 2 over the tile; the box is taken for s + err,
// so every pixel the per-pixel test could accept lies inside it (the box never changes a result, it
// only skips pixels that the test would reject). When Q is not positive definite in double, or the
// bound is not finite, the whole tile is used.
template <typename T>
Box pixel_box(const T* gk, int64_t col_lo, int64_t col_hi, int64_t row_lo, int64_t row_hi) {
  const Box full{int32_t(0), int32_t(col_hi - col_lo), int32_t(0), int32_t(row_hi - row_lo), false, 0.0, 0.0, 0.0, 0.0, 0.0};
  const Box empty{1, 0, 1, 0, false, 0.0, 0.0, 0.0, 0.0, 0.0};
  const double mx = gk[0], my = gk[1], a = gk[2], b = gk[3], c = gk[4], s = gk[6];
  if (!(s >= 0)) return empty;  // opacity <= 0: never visible
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
  if (c0 > c1 || r0 > r1) return empty;
  // Margin of the row spans (row_span), whose half-width sqrt(a s2 - det dy^2) / a is computed in double. det
  // carries a relative error up to rel = 4 eps (a c + b^2) / det (large for a thin Gaussian), a s2 and det dy^2
  // one of a few eps; near the rim the difference under the root then moves by up to (rel + 4 eps) a s2, which
  // moves the half-width by at most sqrt(rel + 4 eps) sqrt(s2 / a) <= sqrt(rel + 4 eps) ex. The margin is that
  // bound, plus 1e-6 ex and 1e-3 px for the remaining roundings.
  const double eps_d = std::numeric_limits<double>::epsilon();
  const double rel = 4.0 * eps_d * (a * c + b * b) / det;
  const double margin = 1e-3 + ex * (1e-6 + std::sqrt(rel + 4.0 * eps_d));
  return Box{int32_t(c0 - col_lo), int32_t(c1 - col_lo), int32_t(r0 - row_lo), int32_t(r1 - row_lo), true, s2, det,
             margin, 1.0 / a, b / a};
}

// The columns [lo, hi] of box row r (tile-local) whose pixel centres lie in the ellipse of the box: with the
// row's dy fixed, sigma = a dx^2 / 2 + b dx dy + c dy^2 / 2 <= s2 / 2 for dx in (-b dy -+ sqrt(a s2 - det dy^2)) / a.
// Like the box it only leaves out pixels whose computed sigma exceeds skip_sigma.
template <typename T>
inline void row_span(const Box& bx, const T* gk, int64_t col_lo, int64_t row_lo, int32_t r, int32_t* lo,
                     int32_t* hi) {
  if (!bx.by_row) {
    *lo = bx.c0;
    *hi = bx.c1;
    return;
  }
  const double dy = double(gk[1]) - (double(row_lo + r) + 0.5);
  const double half = std::sqrt(std::max(0.0, double(gk[2]) * bx.s2 - bx.det * dy * dy)) * bx.inv_a + bx.margin;
  // Pixel centre col_lo + cc + 0.5 = mx - dx.
  const double centre = double(gk[0]) + bx.b_over_a * dy - double(col_lo) - 0.5;
  // Clamped to the box in double before the conversion, which is undefined beyond int32's range; a NaN (std::max
  // and std::min return their first argument then) keeps the whole row of the box.
  *lo = int32_t(std::min(double(bx.c1) + 1.0, std::max(double(bx.c0), std::ceil(centre - half))));
  *hi = int32_t(std::max(double(bx.c0) - 1.0, std::min(double(bx.c1), std::floor(centre + half))));
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

// Four adjacent pixels of a row are processed together (GCC's vector extensions, which Clang >= 11 also
// compiles: SSE2 on x86-64, NEON on aarch64). Per-lane arithmetic is IEEE and the same sequence of operations as a per-pixel loop, so a
// lane's result does not depend on its neighbours; decisions are masks, not branches (a Gaussian's rim
// makes per-pixel branches unpredictable). The build's -fno-trapping-math (splat/_cpu_kernel.py) lets the
// compiler turn std::min/std::max and the selects into vector instructions; it changes no value.
// The vector types never cross the library's interface (these functions are internal and inlined), so GCC's
// warning about the ABI of returning 32-byte vectors without AVX does not concern them.
#pragma GCC diagnostic ignored "-Wpsabi"
template <typename T>
struct Lanes;
template <>
struct Lanes<float> {
  typedef float V __attribute__((vector_size(16)));
  typedef int32_t M __attribute__((vector_size(16)));  // comparison masks: all bits set or zero
  typedef int32_t I;
};
template <>
struct Lanes<double> {
  typedef double V __attribute__((vector_size(32)));
  typedef int64_t M __attribute__((vector_size(32)));
  typedef int64_t I;
};
constexpr int kLanes = 4;

template <typename V>
inline V load4(const typename std::remove_reference<decltype(V{}[0])>::type* p) {
  V v;
  std::memcpy(&v, p, sizeof v);
  return v;
}
template <typename V>
inline void store4(typename std::remove_reference<decltype(V{}[0])>::type* p, const V& v) {
  std::memcpy(p, &v, sizeof v);
}

// exp(-sigma) for sigma in [0, 80] (callers clamp; the result is then a normal number).
// float: Cody-Waite reduction -sigma = n ln2 + r, |r| <= ln2 / 2 (ln2 split so that n * ln2_hi is exact), and
// Cephes' expf polynomial for e^r, evaluated by Estrin's scheme (a shorter dependency chain than Horner's);
// vectorised. Checked on every float in [0, 80] against exp in double: at most 0.999 float ulp, 8.2e-8 relative
// (std::exp of float differs from the correctly rounded value by up to 0.5 ulp). double: std::exp per lane
// (the float64 path is the reference precision).
inline void exp_neg(const Lanes<float>::V& sigma, Lanes<float>::V* out) {
  typedef Lanes<float>::V V;
  typedef Lanes<float>::M M;
  const V y = -sigma;
  const V shift = V{} + 12582912.0f;  // 1.5 * 2^23: adding and removing it rounds to the nearest integer
  const V n = (y * 1.44269504088896341f + shift) - shift;
  const V r = (y - n * 0.693359375f) + n * 2.12194440e-4f;
  // e^r = 1 + r + r^2 (p0 + p1 r + ... + p5 r^5), the bracket by Estrin's scheme.
  const V r2 = r * r;
  const V q01 = r * 1.6666665459e-1f + 5.0000001201e-1f;
  const V q23 = r * 8.3334519073e-3f + 4.1665795894e-2f;
  const V q45 = r * 1.9875691500e-4f + 1.3981999507e-3f;
  const V p = ((q45 * r2 + q23) * r2 + q01) * r2 + r + 1.0f;
  const M bits = (__builtin_convertvector(n, M) + 127) << 23;  // 2^n, n in [-116, 0] (-115 at sigma = 80)
  V scale;
  std::memcpy(&scale, &bits, sizeof scale);
  *out = p * scale;
}
inline void exp_neg(const Lanes<double>::V& sigma, Lanes<double>::V* out) {
  for (int l = 0; l < kLanes; ++l) (*out)[l] = std::exp(-sigma[l]);
}

template <typename T>
inline typename Lanes<T>::V select(const typename Lanes<T>::M& m, const typename Lanes<T>::V& a,
                                   const typename Lanes<T>::V& b) {
  return m ? a : b;
}

template <typename T>
inline T hsum(const typename Lanes<T>::V& v) {
  return (v[0] + v[1]) + (v[2] + v[3]);
}

// Gaussian gk at the four pixels with centres x0 + lane of a row (its constants half_a, b_dy, c_term): fills dx,
// e = exp(-sigma), raw = opacity e and alpha = min(alpha_max, raw), and returns the mask of the lanes the
// Gaussian reaches (0 <= sigma <= skip_sigma and alpha >= alpha_min). sigma is clamped to [0, 80] for the
// exponential only: the lanes outside [0, skip_sigma] are masked off.
template <typename T>
inline typename Lanes<T>::M lane_alpha(const T* gk, T x0, T half_a, T b_dy, T c_term, T alpha_min, T alpha_max,
                                       typename Lanes<T>::V* dx_out, typename Lanes<T>::V* e_out,
                                       typename Lanes<T>::V* raw_out, typename Lanes<T>::V* alpha_out) {
  typedef typename Lanes<T>::V V;
  const V lane = {T(0), T(1), T(2), T(3)};
  const V dx = gk[0] - (x0 + lane);
  const V sigma = dx * (half_a * dx + b_dy) + c_term;
  const V zero = V{} + T(0), cap = V{} + T(80);
  V clamped = select<T>(sigma > zero, sigma, zero);
  clamped = select<T>(clamped < cap, clamped, cap);
  V e;
  exp_neg(clamped, &e);
  const V raw = gk[5] * e;
  const V amax = V{} + alpha_max;
  const V alpha = select<T>(raw < amax, raw, amax);
  *dx_out = dx;
  *e_out = e;
  *raw_out = raw;
  *alpha_out = alpha;
  return (sigma >= zero) & (sigma <= gk[6]) & (alpha >= alpha_min);
}

// Tile-local pixel state is stored by channel, rows padded by a group of lanes (stride S); padding pixels start
// done (forward) or with no Gaussians to visit (backward), so a box's row is visited in groups of 4 pixels from
// its first column on.
inline int64_t padded(int64_t tw) { return tw + kLanes; }

// Visits Gaussian gk (its box bx) row by row: for each row, group(p, mask, dx, e, raw, alpha) for each group of
// four pixels of the row's span from its first column on (p: the group's first pixel in the tile's state; mask:
// the lanes the Gaussian reaches, lane_alpha), then row_end(dy). One definition for both passes, so that they
// make the same alpha decisions.
template <typename T, typename Group, typename RowEnd>
inline void visit_box(const Box& bx, const T* gk, int64_t col_lo, int64_t row_lo, int64_t S, T alpha_min,
                      T alpha_max, Group group, RowEnd row_end) {
  typedef typename Lanes<T>::V V;
  typedef typename Lanes<T>::M M;
  for (int32_t r = bx.r0; r <= bx.r1; ++r) {
    const T py = T(row_lo + r) + T(0.5);
    const T dy = gk[1] - py;
    // Row constants of sigma = dx (a dx / 2 + b dy) + c dy^2 / 2.
    const T half_a = T(0.5) * gk[2], b_dy = gk[3] * dy, c_term = T(0.5) * gk[4] * dy * dy;
    int32_t lo, hi;
    row_span(bx, gk, col_lo, row_lo, r, &lo, &hi);
    for (int32_t q = lo; q <= hi; q += kLanes) {
      V dx, e, raw, alpha;
      const M mask = lane_alpha<T>(gk, T(col_lo + q) + T(0.5), half_a, b_dy, c_term, alpha_min, alpha_max, &dx, &e,
                                   &raw, &alpha);
      group(int64_t(r) * S + q, mask, dx, e, raw, alpha);
    }
    row_end(dy);
  }
}

// Each tile is processed Gaussian by Gaussian (front to back), visiting each row of the Gaussian's box from the
// first column of its span (row_span) in groups of 4 pixels; for every pixel the sequence of operations is
// exactly that of a per-pixel loop over the tile's list, so results do not depend on the order. A pixel the
// Gaussian does not reach, or that is done, gets weight 0, which adds exactly 0 to its (finite) colour sums.
template <typename T>
void forward_impl(int64_t tiles_x, int64_t tiles_y, int64_t tile_size, int64_t width, int64_t height,
                  const int64_t* tile_offsets, const int64_t* gaussian_ids, const T* means2d,
                  const T* conics, const T* colors, const T* opacities, int64_t C, T* out_accum,
                  T* out_transmittance, int32_t* out_last, double alpha_min_d, double alpha_max_d,
                  double transmittance_min_d, int num_threads) {
  typedef typename Lanes<T>::V V;
  typedef typename Lanes<T>::M M;
  typedef typename Lanes<T>::I I;
  const T alpha_min = T(alpha_min_d), alpha_max = T(alpha_max_d), t_min = T(transmittance_min_d);
  splat_parallel::dynamic_for(tiles_x * tiles_y, num_threads, [&](int64_t tile) {
    const int64_t ty = tile / tiles_x, tx = tile % tiles_x;
    const int64_t begin = tile_offsets[tile], end = tile_offsets[tile + 1];
    const int64_t n = end - begin;
    const int64_t col_lo = tx * tile_size, col_hi = std::min(width, (tx + 1) * tile_size) - 1;
    const int64_t row_lo = ty * tile_size, row_hi = std::min(height, (ty + 1) * tile_size) - 1;
    const int64_t tw = col_hi - col_lo + 1, th = row_hi - row_lo + 1, S = padded(tw), NP = S * th;
    std::vector<T> g(kStride * n);
    std::vector<Box> boxes(n);
    gather(n, begin, gaussian_ids, means2d, conics, opacities, alpha_min_d, col_lo, col_hi, row_lo, row_hi,
           g.data(), boxes.data());
    std::vector<T> trans(NP, T(1)), acc(NP * C, T(0));
    std::vector<I> last(NP, 0), alive(NP, 0);  // alive: all bits set while the pixel takes Gaussians
    for (int64_t r = 0; r < th; ++r)
      for (int64_t cc = 0; cc < tw; ++cc) alive[r * S + cc] = I(-1);
    int64_t active = tw * th;
    const V t_min_v = V{} + t_min, one = V{} + T(1), zero = V{} + T(0);
    for (int64_t k = 0; k < n && active > 0; ++k) {
      const Box bx = boxes[k];
      if (bx.c0 > bx.c1 || bx.r0 > bx.r1) continue;
      const T* gk = &g[kStride * k];
      const T* col_k = colors + C * gaussian_ids[begin + k];
      const M next_last = M{} + I(k + 1);
      visit_box(bx, gk, col_lo, row_lo, S, alpha_min, alpha_max,
                [&](int64_t p, const M& reached, const V&, const V&, const V&, const V& alpha) {
                  const M keep = reached & load4<M>(&alive[p]);
                  const V t = load4<V>(&trans[p]);
                  const V next_t = t * (one - alpha);
                  const M stop = keep & (next_t <= t_min_v);
                  const M take = keep & ~stop;
                  const V w = select<T>(take, alpha * t, zero);
                  for (int64_t c = 0; c < C; ++c) {  // selected, so that a non-finite colour stays in its pixels
                    T* a = &acc[c * NP + p];
                    store4<V>(a, load4<V>(a) + select<T>(take, w * col_k[c], zero));
                  }
                  store4<V>(&trans[p], select<T>(take, next_t, t));
                  store4<M>(&last[p], take ? next_last : load4<M>(&last[p]));
                  store4<M>(&alive[p], load4<M>(&alive[p]) & ~stop);
                  for (int l = 0; l < kLanes; ++l) active += stop[l];  // stop lanes are -1
                },
                [](T) {});
    }
    for (int64_t r = 0; r < th; ++r) {
      for (int64_t cc = 0; cc < tw; ++cc) {
        const int64_t p = r * S + cc, pix = (row_lo + r) * width + col_lo + cc;
        for (int64_t c = 0; c < C; ++c) out_accum[pix * C + c] = acc[c * NP + p];
        out_transmittance[pix] = trans[p];
        out_last[pix] = int32_t(last[p]);
      }
    }
  });
}

// Back to front over the tile's list, each Gaussian over the 4-pixel groups of its box; per pixel the visits are
// those of the per-pixel reverse loop from last[pix] - 1 down to 0. A Gaussian's gradients are summed per lane
// over its box's rows, then over the lanes in a fixed order (deterministic, independent of the thread count).
template <typename T>
void backward_impl(int64_t tiles_x, int64_t tiles_y, int64_t tile_size, int64_t width, int64_t height,
                   const int64_t* tile_offsets, const int64_t* gaussian_ids, const T* means2d,
                   const T* conics, const T* colors, const T* opacities, int64_t C,
                   const T* transmittance, const int32_t* last, const T* grad_accum,
                   const T* grad_transmittance, T* g_rows, double alpha_min_d, double alpha_max_d,
                   int num_threads) {
  typedef typename Lanes<T>::V V;
  typedef typename Lanes<T>::M M;
  typedef typename Lanes<T>::I I;
  const T alpha_min = T(alpha_min_d), alpha_max = T(alpha_max_d);
  splat_parallel::dynamic_for(tiles_x * tiles_y, num_threads, [&](int64_t tile) {
    const int64_t ty = tile / tiles_x, tx = tile % tiles_x;
    const int64_t begin = tile_offsets[tile], end = tile_offsets[tile + 1];
    const int64_t n = end - begin;
    if (n == 0) return;
    const int64_t col_lo = tx * tile_size, col_hi = std::min(width, (tx + 1) * tile_size) - 1;
    const int64_t row_lo = ty * tile_size, row_hi = std::min(height, (ty + 1) * tile_size) - 1;
    const int64_t tw = col_hi - col_lo + 1, th = row_hi - row_lo + 1, S = padded(tw), NP = S * th;
    // Per-pixel state: transmittance after the Gaussian being visited, colour behind it, dL/dcolour,
    // and dL/dT_final * T_final; padding pixels visit nothing (stop = 0).
    std::vector<T> trans(NP, T(1)), gtf(NP, T(0)), s(NP * C, T(0)), gc(NP * C, T(0));
    std::vector<I> stop(NP, 0);
    I k_end = 0;
    for (int64_t r = 0; r < th; ++r) {
      for (int64_t cc = 0; cc < tw; ++cc) {
        const int64_t p = r * S + cc, pix = (row_lo + r) * width + col_lo + cc;
        stop[p] = last[pix];
        k_end = std::max(k_end, stop[p]);
        trans[p] = transmittance[pix];
        gtf[p] = grad_transmittance[pix] * transmittance[pix];
        for (int64_t c = 0; c < C; ++c) gc[c * NP + p] = grad_accum[pix * C + c];
      }
    }
    if (k_end == 0) return;
    std::vector<T> g(kStride * n);
    std::vector<Box> boxes(n);
    gather(n, begin, gaussian_ids, means2d, conics, opacities, alpha_min_d, col_lo, col_hi, row_lo, row_hi,
           g.data(), boxes.data());
    const V one = V{} + T(1), zero = V{} + T(0), amax = V{} + alpha_max;
    std::vector<V> gcol(C);
    // Rows [begin, end) of the per-intersection gradients belong to this tile only.
    for (int64_t k = int64_t(k_end) - 1; k >= 0; --k) {
      const Box bx = boxes[k];
      if (bx.c0 > bx.c1 || bx.r0 > bx.r1) continue;
      const T* gk = &g[kStride * k];
      const int64_t j = begin + k;
      const T* col_k = colors + C * gaussian_ids[j];
      const M kk = M{} + I(k);
      // Per-lane sums over the box: dL/d(a, b, c) and dL/dmean as combinations of the rows' sums of
      // d_sigma, d_sigma dx and d_sigma dx^2 (the row's dy enters once per row), and dL/dopacity.
      V gm0 = zero, gm1 = zero, ga = zero, gb = zero, gcc = zero, go = zero;
      for (int64_t c = 0; c < C; ++c) gcol[c] = zero;
      // Per-row sums of d_sigma, d_sigma dx and d_sigma dx^2.
      V s0 = zero, s1 = zero, s2 = zero;
      visit_box(bx, gk, col_lo, row_lo, S, alpha_min, alpha_max,
                [&](int64_t p, const M& reached, const V& dx, const V& e, const V& raw, const V& alpha) {
                  const M valid = reached & (kk < load4<M>(&stop[p]));
                  const V one_minus = one - alpha;
                  const V t_after = load4<V>(&trans[p]);
                  const V t_before = t_after / one_minus;
                  const V w = alpha * t_before;
                  V d_alpha = zero;
                  for (int64_t c = 0; c < C; ++c) {
                    T* sp = &s[c * NP + p];
                    const V sc = load4<V>(sp), gcv = load4<V>(&gc[c * NP + p]);
                    gcol[c] += select<T>(valid, w * gcv, zero);
                    d_alpha += (col_k[c] - sc) * gcv;
                    store4<V>(sp, select<T>(valid, alpha * col_k[c] + one_minus * sc, sc));
                  }
                  d_alpha = d_alpha * t_before - load4<V>(&gtf[p]) / one_minus;
                  store4<V>(&trans[p], select<T>(valid, t_before, t_after));
                  const M graded = valid & (raw <= amax);  // clamped alpha: no gradient to opacity / sigma
                  go += select<T>(graded, d_alpha * e, zero);
                  const V d_sigma = select<T>(graded, -alpha * d_alpha, zero);
                  s0 += d_sigma;  // and dx selected too: 0 * dx is NaN where a masked-off lane's dx is not finite
                  s1 += select<T>(graded, d_sigma * dx, zero);
                  s2 += select<T>(graded, d_sigma * dx * dx, zero);
                },
                [&](T dy) {
                  // d sigma / d(a, b, c) = (dx^2 / 2, dx dy, dy^2 / 2); d sigma / d mean = (a dx + b dy, b dx + c dy).
                  ga += T(0.5) * s2;
                  gb += dy * s1;
                  gcc += T(0.5) * dy * dy * s0;
                  gm0 += gk[2] * s1 + gk[3] * dy * s0;
                  gm1 += gk[3] * s1 + gk[4] * dy * s0;
                  s0 = s1 = s2 = zero;
                });
      T* row = g_rows + j * (6 + C);  // this row belongs to this tile only
      row[0] = hsum<T>(gm0);
      row[1] = hsum<T>(gm1);
      row[2] = hsum<T>(ga);
      row[3] = hsum<T>(gb);
      row[4] = hsum<T>(gcc);
      row[5] = hsum<T>(go);
      for (int64_t c = 0; c < C; ++c) row[6 + c] = hsum<T>(gcol[c]);
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
