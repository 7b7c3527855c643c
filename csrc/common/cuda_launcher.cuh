// The CUDA backend: a per-item functor (a family's kernels.h, or common/) run with one thread per
// item, on the current stream (so that CUDA graphs and user streams work), with the launch
// checked. The whole solves' entry points (run_cg, run_solve) are the solve family's:
// solve/cuda.cu derives its launcher from this one.
#pragma once

#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>

#include <cstdint>

#include "common/cg_reduce.cuh"

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
};

}  // namespace tensormass
