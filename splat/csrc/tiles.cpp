// Tile binning of projected Gaussians, the same lists as the torch reference `splat.tiles.bin_gaussians`:
// a visible Gaussian is listed in every tile holding a pixel centre (col + 0.5, row + 0.5) inside its
// box [u - ex, u + ex] x [v - ey, v + ey]; each tile's list is ordered by (depth, Gaussian index).
//
// Two calls: `splat_tiles_count` gives the number of Gaussians per tile (the caller takes the prefix
// sum, allocates the intersection array), `splat_tiles_fill` writes the lists. The fill visits the
// Gaussians once in (depth, index) order and appends each to its tiles, so every tile's list comes out
// sorted without a per-intersection sort: O(N log N + I).

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <numeric>
#include <vector>

#include "kernel_api.h"

namespace {

struct TileRect {
  int64_t x0, x1, y0, y1;  // tiles [x0, x1) x [y0, y1)
};

inline int64_t floor_div(double v, int64_t d) { return int64_t(std::floor(v / double(d))); }

// The tile rectangle of one Gaussian's box, with the reference's double-precision rounding.
// Pixel columns [col0, col1] and rows [row0, row1] whose centres lie in the box, clamped to the image;
// an empty range gives an empty rectangle.
template <typename T>
TileRect tile_rect(const T* m, const T* e, int64_t width, int64_t height, int64_t tile_size) {
  const double u = m[0], v = m[1], ex = e[0], ey = e[1];
  const double col0 = std::max(std::ceil(u - ex - 0.5), 0.0);
  const double col1 = std::min(std::floor(u + ex - 0.5), double(width - 1));
  const double row0 = std::max(std::ceil(v - ey - 0.5), 0.0);
  const double row1 = std::min(std::floor(v + ey - 0.5), double(height - 1));
  TileRect r{0, 0, 0, 0};
  if (!(col1 >= col0) || !(row1 >= row0)) return r;
  r.x0 = floor_div(col0, tile_size);
  r.x1 = floor_div(col1, tile_size) + 1;
  r.y0 = floor_div(row0, tile_size);
  r.y1 = floor_div(row1, tile_size) + 1;
  return r;
}

template <typename T>
void count_impl(int64_t n, const T* means2d, const T* extents, const int32_t* visible, int64_t width, int64_t height,
                int64_t tile_size, int64_t tiles_x, int64_t tiles_y, int64_t* tile_counts) {
  std::fill(tile_counts, tile_counts + tiles_x * tiles_y, int64_t(0));
  for (int64_t g = 0; g < n; ++g) {
    if (!visible[g]) continue;
    const TileRect r = tile_rect(means2d + 2 * g, extents + 2 * g, width, height, tile_size);
    for (int64_t ty = r.y0; ty < r.y1; ++ty)
      for (int64_t tx = r.x0; tx < r.x1; ++tx) ++tile_counts[ty * tiles_x + tx];
  }
}

template <typename T>
void fill_impl(int64_t n, const T* means2d, const T* extents, const T* depths, const int32_t* visible, int64_t width,
               int64_t height, int64_t tile_size, int64_t tiles_x, int64_t tiles_y, const int64_t* tile_offsets,
               int64_t* gaussian_ids) {
  std::vector<int64_t> order;
  order.reserve(size_t(n));
  for (int64_t g = 0; g < n; ++g)
    if (visible[g]) order.push_back(g);
  // Strict weak order on (depth, index); visible Gaussians have finite depths.
  std::sort(order.begin(), order.end(), [depths](int64_t i, int64_t j) {
    return depths[i] < depths[j] || (depths[i] == depths[j] && i < j);
  });
  std::vector<int64_t> cursor(tile_offsets, tile_offsets + tiles_x * tiles_y);
  for (const int64_t g : order) {
    const TileRect r = tile_rect(means2d + 2 * g, extents + 2 * g, width, height, tile_size);
    for (int64_t ty = r.y0; ty < r.y1; ++ty)
      for (int64_t tx = r.x0; tx < r.x1; ++tx) gaussian_ids[cursor[ty * tiles_x + tx]++] = g;
  }
}

}  // namespace

#define SPLAT_DEFINE_TILES(T, SUFFIX)                                                                            \
  extern "C" void splat_tiles_count_##SUFFIX(int64_t n, const T* means2d, const T* extents,                      \
                                             const int32_t* visible, int64_t width, int64_t height,              \
                                             int64_t tile_size, int64_t tiles_x, int64_t tiles_y,                \
                                             int64_t* tile_counts) {                                              \
    count_impl<T>(n, means2d, extents, visible, width, height, tile_size, tiles_x, tiles_y, tile_counts);        \
  }                                                                                                              \
  extern "C" void splat_tiles_fill_##SUFFIX(int64_t n, const T* means2d, const T* extents, const T* depths,      \
                                            const int32_t* visible, int64_t width, int64_t height,               \
                                            int64_t tile_size, int64_t tiles_x, int64_t tiles_y,                 \
                                            const int64_t* tile_offsets, int64_t* gaussian_ids) {                 \
    fill_impl<T>(n, means2d, extents, depths, visible, width, height, tile_size, tiles_x, tiles_y, tile_offsets, \
                 gaussian_ids);                                                                                  \
  }

SPLAT_DEFINE_TILES(float, f32)
SPLAT_DEFINE_TILES(double, f64)
