// The compositor backward's per-Gaussian sums (composite.cpp writes one gradient row per tile
// intersection). Its own file, so that a diagnostic can swap composite.cpp for another version's
// (benchmarks/diag_composite_speed.py) and keep this one. Plain C++17, called via ctypes from
// splat/_cpu_kernel.py (C API: kernel_api.h).

#include <algorithm>
#include <cstdint>

#include "kernel_api.h"
#include "parallel.h"

namespace {

// Per-Gaussian sums of the backward's per-intersection rows, split into the four gradients. Each Gaussian's
// rows are added in intersection order starting from zero, as one `index_add_` of the rows into zeros adds
// them, so the sums are the same numbers, whatever the thread count. The Gaussians are split into one range
// per thread; each thread reads all the ids (8 bytes each) and only its own rows (40 bytes and more), which
// suits the few cores this runs on (at many threads the id scans would dominate). This replaces that
// `index_add_` (one small add per row, on one torch thread) and the copies of its column slices.
// Ids outside [0, N) are the caller's error; they are skipped (the Python wrapper checks the ids).
template <typename T>
void gather_impl(int64_t I, int64_t N, int64_t C, const int64_t* ids, const T* rows, T* g_means2d, T* g_conics,
                 T* g_opacities, T* g_colors, int num_threads) {
  // One range of Gaussians per thread, which zeroes its outputs and reads all the ids once.
  const int64_t parts = std::max<int64_t>(1, std::min<int64_t>(num_threads, I / 4096));
  const int64_t range = (N + parts - 1) / parts;
  const int64_t D = 6 + C;
  splat_parallel::dynamic_for(parts, num_threads, [&](int64_t item) {
    const int64_t lo = std::min(N, item * range), hi = std::min(N, lo + range);
    std::fill(g_means2d + 2 * lo, g_means2d + 2 * hi, T(0));
    std::fill(g_conics + 3 * lo, g_conics + 3 * hi, T(0));
    std::fill(g_opacities + lo, g_opacities + hi, T(0));
    std::fill(g_colors + C * lo, g_colors + C * hi, T(0));
    for (int64_t j = 0; j < I; ++j) {
      const int64_t g = ids[j];
      if (g < lo || g >= hi) continue;
      const T* r = rows + j * D;
      g_means2d[2 * g] += r[0];
      g_means2d[2 * g + 1] += r[1];
      g_conics[3 * g] += r[2];
      g_conics[3 * g + 1] += r[3];
      g_conics[3 * g + 2] += r[4];
      g_opacities[g] += r[5];
      for (int64_t c = 0; c < C; ++c) g_colors[C * g + c] += r[6 + c];
    }
  });
}

}  // namespace

#define GATHER_EXPORT(T, SUFFIX)                                                                            \
  extern "C" void splat_composite_gather_##SUFFIX(int64_t I, int64_t N, int64_t C, const int64_t* gaussian_ids, \
                                                   const T* g_rows, T* g_means2d, T* g_conics, T* g_opacities, \
                                                   T* g_colors, int32_t num_threads) {                      \
    gather_impl<T>(I, N, C, gaussian_ids, g_rows, g_means2d, g_conics, g_opacities, g_colors, num_threads); \
  }

GATHER_EXPORT(float, f32)
GATHER_EXPORT(double, f64)
