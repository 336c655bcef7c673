// Tile compositing of 2D Gaussians on the CPU: forward and backward.
//
// Plain C++17 (no torch headers, so it builds in about a second); called via
// ctypes from splat/_cpu_kernel.py with pointers to contiguous tensors.
// The maths is the same as splat/composite.py::_composite_tiles_torch (the
// reference the tests compare against) and as gsplat's rasterize_to_pixels:
//   pixel (row, col) is evaluated at (col + 0.5, row + 0.5);
//   sigma = 0.5 (a dx^2 + c dy^2) + b dx dy with d = mean - pixel;
//   alpha = min(0.99, opacity * exp(-sigma)); skipped when sigma < 0 or
//   alpha < 1/255; a pixel stops before the Gaussian that would bring the
//   transmittance to <= 1e-4.
// Outputs: accum (H, W, C) = sum_i c_i alpha_i T_i and T_final (H, W).
// The backward writes one gradient row per tile intersection (each tile is
// owned by one thread, so no atomics); the caller sums rows per Gaussian.

#include <atomic>
#include <cmath>
#include <cstdint>
#include <thread>
#include <vector>

namespace {

constexpr double kAlphaMin = 1.0 / 255.0;
constexpr double kAlphaMax = 0.99;
constexpr double kTransmittanceMin = 1e-4;

template <typename F>
void parallel_tiles(int64_t num_tiles, int num_threads, F fn) {
  if (num_threads <= 1 || num_tiles <= 1) {
    for (int64_t t = 0; t < num_tiles; ++t) fn(t);
    return;
  }
  std::atomic<int64_t> next{0};
  auto worker = [&]() {
    for (int64_t t = next.fetch_add(1); t < num_tiles; t = next.fetch_add(1)) fn(t);
  };
  std::vector<std::thread> pool;
  int extra = num_threads - 1;
  pool.reserve(extra);
  for (int i = 0; i < extra; ++i) pool.emplace_back(worker);
  worker();
  for (auto& th : pool) th.join();
}

// Per-Gaussian record gathered per tile: [mx, my, a, b, c, o, skip_sigma].
// skip_sigma = log(255 o) * (1 + 1e-4) + 1e-6: sigma above it gives alpha < 1/255 for sure, so the
// exp() is skipped; at or below it the exact alpha test decides (identical results, much less work).
constexpr int64_t kStride = 7;

template <typename T>
void gather(int64_t n, int64_t begin, const int64_t* gaussian_ids, const T* means2d, const T* conics,
            const T* opacities, T* g) {
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
    gk[6] = o > 0 ? T(std::log(o / kAlphaMin) * (1.0 + 1e-4) + 1e-6) : T(-1);
  }
}

template <typename T>
void forward_impl(int64_t tiles_x, int64_t tiles_y, int64_t tile_size, int64_t width, int64_t height,
                  const int64_t* tile_offsets, const int64_t* gaussian_ids, const T* means2d,
                  const T* conics, const T* colors, const T* opacities, int64_t C, T* out_accum,
                  T* out_transmittance, int32_t* out_last, int num_threads) {
  const T alpha_min = T(kAlphaMin), alpha_max = T(kAlphaMax), t_min = T(kTransmittanceMin);
  parallel_tiles(tiles_x * tiles_y, num_threads, [&](int64_t tile) {
    const int64_t ty = tile / tiles_x, tx = tile % tiles_x;
    const int64_t begin = tile_offsets[tile], end = tile_offsets[tile + 1];
    const int64_t n = end - begin;
        std::vector<T> g(kStride * n);
    gather(n, begin, gaussian_ids, means2d, conics, opacities, g.data());
    std::vector<T> acc(C);
    for (int64_t row = ty * tile_size; row < std::min(height, (ty + 1) * tile_size); ++row) {
      for (int64_t col = tx * tile_size; col < std::min(width, (tx + 1) * tile_size); ++col) {
        const T px = T(col) + T(0.5), py = T(row) + T(0.5);
        T trans = T(1);
        int32_t last = 0;
        for (int64_t c = 0; c < C; ++c) acc[c] = T(0);
        for (int64_t k = 0; k < n; ++k) {
          const T* gk = &g[kStride * k];
          const T dx = gk[0] - px, dy = gk[1] - py;
          const T sigma = T(0.5) * (gk[2] * dx * dx + gk[4] * dy * dy) + gk[3] * dx * dy;
          if (sigma < T(0) || sigma > gk[6]) continue;
          const T alpha = std::min(alpha_max, gk[5] * std::exp(-sigma));
          if (alpha < alpha_min) continue;
          const T next_t = trans * (T(1) - alpha);
          if (next_t <= t_min) break;
          const T w = alpha * trans;
          const T* col_k = colors + C * gaussian_ids[begin + k];
          for (int64_t c = 0; c < C; ++c) acc[c] += w * col_k[c];
          trans = next_t;
          last = int32_t(k + 1);
        }
        const int64_t pix = row * width + col;
        for (int64_t c = 0; c < C; ++c) out_accum[pix * C + c] = acc[c];
        out_transmittance[pix] = trans;
        out_last[pix] = last;
      }
    }
  });
}

template <typename T>
void backward_impl(int64_t tiles_x, int64_t tiles_y, int64_t tile_size, int64_t width, int64_t height,
                   const int64_t* tile_offsets, const int64_t* gaussian_ids, const T* means2d,
                   const T* conics, const T* colors, const T* opacities, int64_t C,
                   const T* transmittance, const int32_t* last, const T* grad_accum,
                   const T* grad_transmittance, T* g_means2d, T* g_conics, T* g_colors, T* g_opacities,
                   int num_threads) {
  const T alpha_min = T(kAlphaMin), alpha_max = T(kAlphaMax);
  parallel_tiles(tiles_x * tiles_y, num_threads, [&](int64_t tile) {
    const int64_t ty = tile / tiles_x, tx = tile % tiles_x;
    const int64_t begin = tile_offsets[tile], end = tile_offsets[tile + 1];
    const int64_t n = end - begin;
    if (n == 0) return;
    std::vector<T> g(kStride * n);
    gather(n, begin, gaussian_ids, means2d, conics, opacities, g.data());
    // Rows [begin, end) of the per-intersection gradients belong to this tile only.
    std::vector<T> s(C), gc(C);
    for (int64_t row = ty * tile_size; row < std::min(height, (ty + 1) * tile_size); ++row) {
      for (int64_t col = tx * tile_size; col < std::min(width, (tx + 1) * tile_size); ++col) {
        const int64_t pix = row * width + col;
        const int32_t stop = last[pix];
        if (stop == 0) continue;
        const T px = T(col) + T(0.5), py = T(row) + T(0.5);
        const T t_final = transmittance[pix];
        const T g_t = grad_transmittance[pix];
        for (int64_t c = 0; c < C; ++c) {
          s[c] = T(0);
          gc[c] = grad_accum[pix * C + c];
        }
        T trans = t_final;  // transmittance after the Gaussian being visited
        for (int64_t k = stop - 1; k >= 0; --k) {
          const T* gk = &g[kStride * k];
          const T dx = gk[0] - px, dy = gk[1] - py;
          const T sigma = T(0.5) * (gk[2] * dx * dx + gk[4] * dy * dy) + gk[3] * dx * dy;
          if (sigma < T(0) || sigma > gk[6]) continue;
          const T e = std::exp(-sigma);
          const T raw = gk[5] * e;
          const T alpha = std::min(alpha_max, raw);
          if (alpha < alpha_min) continue;
          const T one_minus = T(1) - alpha;
          const T t_before = trans / one_minus;
          const T w = alpha * t_before;
          const int64_t j = begin + k;
          const T* col_k = colors + C * gaussian_ids[j];
          T d_alpha = T(0);
          for (int64_t c = 0; c < C; ++c) {
            g_colors[j * C + c] += w * gc[c];
            d_alpha += (col_k[c] - s[c]) * gc[c];
            s[c] = alpha * col_k[c] + one_minus * s[c];
          }
          d_alpha = d_alpha * t_before - g_t * t_final / one_minus;
          trans = t_before;
          if (raw > alpha_max) continue;  // clamped: no gradient to opacity / sigma
          g_opacities[j] += d_alpha * e;
          const T d_sigma = -alpha * d_alpha;
          g_conics[3 * j + 0] += d_sigma * T(0.5) * dx * dx;
          g_conics[3 * j + 1] += d_sigma * dx * dy;
          g_conics[3 * j + 2] += d_sigma * T(0.5) * dy * dy;
          g_means2d[2 * j + 0] += d_sigma * (gk[2] * dx + gk[3] * dy);
          g_means2d[2 * j + 1] += d_sigma * (gk[3] * dx + gk[4] * dy);
        }
      }
    }
  });
}

}  // namespace

#define SPLAT_EXPORT(T, SUFFIX)                                                                           \
  extern "C" void splat_composite_forward_##SUFFIX(                                                       \
      int64_t tiles_x, int64_t tiles_y, int64_t tile_size, int64_t width, int64_t height,                \
      const int64_t* tile_offsets, const int64_t* gaussian_ids, const T* means2d, const T* conics,       \
      const T* colors, const T* opacities, int64_t C, T* out_accum, T* out_transmittance,                \
      int32_t* out_last, int num_threads) {                                                               \
    forward_impl<T>(tiles_x, tiles_y, tile_size, width, height, tile_offsets, gaussian_ids, means2d,     \
                    conics, colors, opacities, C, out_accum, out_transmittance, out_last, num_threads);  \
  }                                                                                                       \
  extern "C" void splat_composite_backward_##SUFFIX(                                                      \
      int64_t tiles_x, int64_t tiles_y, int64_t tile_size, int64_t width, int64_t height,                \
      const int64_t* tile_offsets, const int64_t* gaussian_ids, const T* means2d, const T* conics,       \
      const T* colors, const T* opacities, int64_t C, const T* transmittance, const int32_t* last,       \
      const T* grad_accum, const T* grad_transmittance, T* g_means2d, T* g_conics, T* g_colors,          \
      T* g_opacities, int num_threads) {                                                                  \
    backward_impl<T>(tiles_x, tiles_y, tile_size, width, height, tile_offsets, gaussian_ids, means2d,    \
                     conics, colors, opacities, C, transmittance, last, grad_accum, grad_transmittance,  \
                     g_means2d, g_conics, g_colors, g_opacities, num_threads);                           \
  }

SPLAT_EXPORT(float, f32)
SPLAT_EXPORT(double, f64)
