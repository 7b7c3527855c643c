// The CPU backend: a per-item functor (a family's kernels.h, or common/) run over n items with
// at::parallel_for (OpenMP). Each item is written by exactly one iteration, so the results do not
// depend on the number of threads. The whole solves' entry points (run_cg, run_solve) are the
// solve family's: solve/cpu.cpp derives its launcher from this one.
#pragma once

#include <ATen/Parallel.h>
#include <c10/core/Device.h>

#include <cstdint>

#include "common/cg_chunks.h"

namespace tensormass {

struct CpuLauncher {
  struct Guard {
    explicit Guard(const c10::Device&) {}
  };
  // grain sizes (items per task)
  static constexpr int64_t kElementBlock = 512;
  static constexpr int64_t kNodeBlock = 2048;

  template <class K>
  static void run(int64_t n, const K& k, int64_t grain) {
    if (n <= 0) return;
    at::parallel_for(0, n, grain, [&](int64_t begin, int64_t end) {
      for (int64_t i = begin; i < end; ++i) k(i);
    });
  }

  // A node kernel with apply(i) -> p_i . Ap_i over the chunks of a CG plan, ending in alpha.
  template <class K, typename S>
  static void run_alpha(const CGPlan& plan, const K& k, const S* rr, int32_t* status, S* alpha, double* scratch,
                        int32_t*) {
    chunk_alpha_cpu<K, S>(plan, k, rr, status, alpha, scratch);
  }
};

}  // namespace tensormass
