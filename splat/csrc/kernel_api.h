// The C API of the splat CPU kernels: every function the Python side calls through ctypes
// (splat/_cpu_kernel.py). composite.cpp, gather.cpp, sh.cpp, projection.cpp, tiles.cpp and ssim.cpp include
// this header, so a definition that drifts from its declaration does not compile (two C-linkage functions
// of one name); abi.cpp exports the ABI version and a signature table generated from these declarations,
// which the Python side compares with its own table before the first call.
//
// The compositing rules (alpha bounds, transmittance floor) and the SH basis constants are not
// defined here: the Python caller passes them as arguments, so they exist once, in Python.
//
// Bump SPLAT_KERNEL_ABI_VERSION (and _ABI_VERSION in splat/_cpu_kernel.py) when the meaning of an
// argument changes without its type changing.

#ifndef SPLAT_KERNEL_API_H_
#define SPLAT_KERNEL_API_H_

#include <cstdint>

#define SPLAT_KERNEL_ABI_VERSION 4

#define SPLAT_DECLARE_KERNELS(T, SUFFIX)                                                                 \
  extern "C" void splat_composite_forward_##SUFFIX(                                                      \
      int64_t tiles_x, int64_t tiles_y, int64_t tile_size, int64_t width, int64_t height,               \
      const int64_t* tile_offsets, const int64_t* gaussian_ids, const T* means2d, const T* conics,      \
      const T* colors, const T* opacities, int64_t C, T* out_accum, T* out_transmittance,               \
      int32_t* out_last, double alpha_min, double alpha_max, double transmittance_min, int32_t num_threads); \
  extern "C" void splat_composite_backward_##SUFFIX(                                                     \
      int64_t tiles_x, int64_t tiles_y, int64_t tile_size, int64_t width, int64_t height,               \
      const int64_t* tile_offsets, const int64_t* gaussian_ids, const T* means2d, const T* conics,      \
      const T* colors, const T* opacities, int64_t C, const T* transmittance, const int32_t* last,      \
      const T* grad_accum, const T* grad_transmittance, T* g_rows, double alpha_min, double alpha_max,  \
      int32_t num_threads);                                                                              \
  extern "C" void splat_composite_gather_##SUFFIX(int64_t I, int64_t N, int64_t C, const int64_t* gaussian_ids, \
                                                   const T* g_rows, T* g_means2d, T* g_conics, T* g_opacities, \
                                                   T* g_colors, int32_t num_threads);                       \
  extern "C" void splat_sh_forward_##SUFFIX(int64_t n, int64_t K, int32_t degree, const T* sh0,            \
                                             int64_t sh0_stride, const T* shN, int64_t shN_stride,         \
                                             const T* dirs, const double* basis_constants, double norm_eps, \
                                             T* out, int32_t num_threads);                                 \
  extern "C" void splat_sh_backward_##SUFFIX(int64_t n, int64_t K, int32_t degree, const T* sh0,           \
                                              int64_t sh0_stride, const T* shN, int64_t shN_stride,        \
                                              const T* dirs, const double* basis_constants, double norm_eps, \
                                              const T* grad_out, T* g_sh0, int64_t g_sh0_stride, T* g_shN,  \
                                              int64_t g_shN_stride, T* g_dirs, int32_t num_threads);       \
  extern "C" void splat_project_forward_##SUFFIX(                                                        \
      int64_t n, const T* means, const T* quats, const T* scales, const T* opacities,                   \
      const T* cam_from_world, const T* K, int64_t width, int64_t height, double near_plane,            \
      double far_plane, double eps2d, int32_t antialiased, double alpha_min, T* out_means2d,            \
      T* out_conics, T* out_depths, T* out_opacities, T* out_extents, int32_t* out_visible,             \
      int32_t num_threads);                                                                              \
  extern "C" void splat_project_backward_##SUFFIX(                                                       \
      int64_t n, const T* means, const T* quats, const T* scales, const T* opacities,                   \
      const T* cam_from_world, const T* K, int64_t width, int64_t height, double near_plane,            \
      double far_plane, double eps2d, int32_t antialiased, const T* g_means2d, const T* g_conics,       \
      const T* g_depths, const T* g_opacities_out, T* g_means, T* g_quats, T* g_scales, T* g_opacities, \
      T* g_cam_rows, T* g_K_rows, int32_t num_threads);                                                  \
  extern "C" void splat_tiles_count_##SUFFIX(int64_t n, const T* means2d, const T* extents,              \
                                             const int32_t* visible, int64_t width, int64_t height,      \
                                             int64_t tile_size, int64_t tiles_x, int64_t tiles_y,        \
                                             int64_t* tile_counts);                                      \
  extern "C" void splat_tiles_fill_##SUFFIX(int64_t n, const T* means2d, const T* extents, const T* depths, \
                                            const int32_t* visible, int64_t width, int64_t height,       \
                                            int64_t tile_size, int64_t tiles_x, int64_t tiles_y,         \
                                            const int64_t* tile_offsets, int64_t* gaussian_ids);     \
  extern "C" void splat_photometric_loss_##SUFFIX(int64_t C, int64_t H, int64_t W, const T* rendered,   \
                                                  const T* target, const double* taps, int64_t K,        \
                                                  double c1, double c2, double ssim_weight, T* workspace, \
                                                  double* out_terms, T* grad, int32_t num_threads);

SPLAT_DECLARE_KERNELS(float, f32)
SPLAT_DECLARE_KERNELS(double, f64)

// SPLAT_KERNEL_ABI_VERSION of the compiled library.
extern "C" int64_t splat_kernel_abi_version();
// "name(arg,...);..." for every kernel above, with arg codes i32 i64 f32 f64 and a trailing * for
// pointers (const dropped), e.g. "splat_sh_forward_f32(i64,i64,i32,f32*,i64,f32*,i64,f32*,f64*,f64,f32*,i32);".
extern "C" const char* splat_kernel_signatures();

#endif  // SPLAT_KERNEL_API_H_
