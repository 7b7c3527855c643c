// The CPU backend: a functor of kernels.h run over n items with at::parallel_for (OpenMP).
// Each item is written by exactly one iteration, so the results do not depend on the
// number of threads.
#pragma once

#include <ATen/Parallel.h>
#include <c10/core/Device.h>

#include <cstdint>

#include "cpu/cg_chunks.h"

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

  // A whole CG solve with node kernel K as its matvec: the CG ops' functions in a loop.
  template <class K, typename S>
  static void run_cg(const CGPlan& plan, const K& k, const CGRun<S>& s) {
    cg_run_cpu<K, S>(plan, k, s);
  }

  // The pipelined CG is a GPU kernel (its point is one grid barrier an iteration); the CPU solves
  // with run_cg: false, nothing done.
  template <class K, typename S>
  static bool run_solve(const CGPlan&, const K&, const PipelinedSolve<S>&) {
    return false;
  }
};

}  // namespace tensormass
