// The CUDA backend: a functor of kernels.h run with one thread per item, on the current stream
// (so that CUDA graphs and user streams work), with the launch checked.
#pragma once

#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>

#include <cstdint>

#include "cuda/cg_persistent.cuh"
#include "cuda/cg_pipelined.cuh"
#include "cuda/cg_reduce.cuh"

namespace tensormass {

template <class K>
__global__ void __launch_bounds__(256) for_each_item(const K k, int64_t n) {
  const int64_t i = static_cast<int64_t>(blockIdx.x) * blockDim.x + threadIdx.x;
  if (i < n) k(i);
}

struct CudaLauncher {
  using Guard = c10::cuda::CUDAGuard;
  // threads per block: element kernels use many registers, node kernels few
  static constexpr int64_t kElementBlock = 128;
  static constexpr int64_t kNodeBlock = 256;

  template <class K>
  static void run(int64_t n, const K& k, int64_t block) {
    if (n <= 0) return;
    const int64_t grid = (n + block - 1) / block;
    for_each_item<K><<<static_cast<unsigned int>(grid), static_cast<unsigned int>(block), 0,
                       at::cuda::getCurrentCUDAStream()>>>(k, n);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  }

  // A node kernel with apply(i) -> p_i . Ap_i over the chunks of a CG plan, ending in alpha.
  template <class K, typename S>
  static void run_alpha(const CGPlan& plan, const K& k, const S* rr, int32_t* status, S* alpha, double* scratch,
                        int32_t* counter) {
    launch_chunk_alpha<K, S>(plan, k, rr, status, alpha, scratch, counter);
  }

  // A whole CG solve with node kernel K as its matvec: one persistent kernel (cg_persistent.cuh).
  template <class K, typename S>
  static void run_cg(const CGPlan& plan, const K& k, const CGRun<S>& s) {
    launch_persistent_cg<K, S>(plan, k, s);
  }

  // A whole solve by the pipelined CG (cg_pipelined.cuh); false where it does not fit one wave.
  template <class K, typename S>
  static bool run_solve(const CGPlan& plan, const K& k, const PipelinedSolve<S>& s) {
    return launch_pipelined_cg<K, S>(plan, k, s);
  }
};

}  // namespace tensormass
