// Work-stealing loop shared by the compositor (one item per tile) and the SSIM loss (one item per
// channel row): `fn(i)` for i in [0, n) on up to `num_threads` threads, the calling thread included.
// Items are handed out one at a time from an atomic counter, so uneven items balance; each item is
// processed by exactly one thread, so per-item outputs need no synchronisation.

#ifndef SPLAT_PARALLEL_H_
#define SPLAT_PARALLEL_H_

#include <algorithm>
#include <atomic>
#include <cstdint>
#include <thread>
#include <vector>

namespace splat_parallel {

template <typename F>
void dynamic_for(int64_t n, int num_threads, F fn) {
  if (num_threads <= 1 || n <= 1) {
    for (int64_t i = 0; i < n; ++i) fn(i);
    return;
  }
  std::atomic<int64_t> next{0};
  auto worker = [&]() {
    for (int64_t i = next.fetch_add(1); i < n; i = next.fetch_add(1)) fn(i);
  };
  std::vector<std::thread> pool;
  const int extra = int(std::min<int64_t>(num_threads, n)) - 1;
  pool.reserve(extra);
  for (int i = 0; i < extra; ++i) pool.emplace_back(worker);
  worker();
  for (auto& th : pool) th.join();
}

}  // namespace splat_parallel

#endif  // SPLAT_PARALLEL_H_
