// The ABI version and the signature table of the kernels declared in kernel_api.h. The table is
// generated from the declarations' types, so it always describes the compiled functions.

#include <cstdint>
#include <string>
#include <type_traits>

#include "kernel_api.h"

namespace {

template <typename T>
struct Code;
template <>
struct Code<int32_t> {
  static std::string get() { return "i32"; }
};
template <>
struct Code<int64_t> {
  static std::string get() { return "i64"; }
};
template <>
struct Code<float> {
  static std::string get() { return "f32"; }
};
template <>
struct Code<double> {
  static std::string get() { return "f64"; }
};
template <typename T>
struct Code<T*> {
  static std::string get() { return Code<std::remove_const_t<T>>::get() + "*"; }
};

template <typename... A>
std::string signature(const char* name, void (*)(A...)) {
  std::string out = std::string(name) + "(";
  bool first = true;
  ((out += (first ? "" : ","), out += Code<A>::get(), first = false), ...);
  return out + ");";
}

#define SPLAT_SIGNATURE(fn) signature(#fn, &fn)

const std::string& table() {
  static const std::string text = SPLAT_SIGNATURE(splat_composite_forward_f32) +
                                  SPLAT_SIGNATURE(splat_composite_forward_f64) +
                                  SPLAT_SIGNATURE(splat_composite_backward_f32) +
                                  SPLAT_SIGNATURE(splat_composite_backward_f64) +
                                  SPLAT_SIGNATURE(splat_composite_gather_f32) +
                                  SPLAT_SIGNATURE(splat_composite_gather_f64) +
                                  SPLAT_SIGNATURE(splat_sh_forward_f32) + SPLAT_SIGNATURE(splat_sh_forward_f64) +
                                  SPLAT_SIGNATURE(splat_sh_backward_f32) + SPLAT_SIGNATURE(splat_sh_backward_f64) +
                                  SPLAT_SIGNATURE(splat_project_forward_f32) +
                                  SPLAT_SIGNATURE(splat_project_forward_f64) +
                                  SPLAT_SIGNATURE(splat_project_backward_f32) +
                                  SPLAT_SIGNATURE(splat_project_backward_f64) +
                                  SPLAT_SIGNATURE(splat_tiles_count_f32) + SPLAT_SIGNATURE(splat_tiles_count_f64) +
                                  SPLAT_SIGNATURE(splat_tiles_fill_f32) + SPLAT_SIGNATURE(splat_tiles_fill_f64) +
                                  SPLAT_SIGNATURE(splat_photometric_loss_f32) +
                                  SPLAT_SIGNATURE(splat_photometric_loss_f64);
  return text;
}

}  // namespace

extern "C" int64_t splat_kernel_abi_version() { return SPLAT_KERNEL_ABI_VERSION; }

extern "C" const char* splat_kernel_signatures() { return table().c_str(); }
