// The CG reductions on the GPU, shared by the CG ops (cg/cuda.cu) and the matvec kernels that
// end in the step length (chunk_alpha_kernel): one block per chunk sums its chunk in a fixed
// pattern (strided per-thread sums, then a shuffle tree) into scratch[chunk]; the last block of
// an object to finish (elected by an atomic ticket on counter[object]) sums the object's chunk
// sums in the same fixed pattern and runs the scalar step. Which block is last changes from run
// to run; what it computes does not: deterministic.
#pragma once

#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>

#include <cstdint>

#include "common/cg.h"

namespace tensormass {

constexpr int kReduceBlock = 256;

// Sum over the block in a fixed order; the result is valid in thread 0.
__device__ inline double block_sum(double v) {
  __shared__ double warp_sums[kReduceBlock / 32];
  for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_down_sync(0xffffffffu, v, offset);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  if (lane == 0) warp_sums[warp] = v;
  __syncthreads();
  if (warp == 0) {
    v = lane < kReduceBlock / 32 ? warp_sums[lane] : 0.0;
    for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_down_sync(0xffffffffu, v, offset);
  }
  return v;
}

// Publishes this block's chunk sum and says whether this block is the object's last; if so,
// returns (in thread 0) the object's total over its chunks.
__device__ inline bool object_total(const CGPlan& plan, int64_t chunk, int64_t object, double chunk_total,
                                    double* scratch, int32_t* counter, double& total) {
  __shared__ bool is_last;
  if (threadIdx.x == 0) {
    scratch[chunk] = chunk_total;
    __threadfence();
    const int32_t chunks = static_cast<int32_t>(plan.object_chunk[object + 1] - plan.object_chunk[object]);
    is_last = atomicAdd(counter + object, 1) == chunks - 1;
  }
  __syncthreads();
  if (!is_last) return false;
  __threadfence();
  double acc = 0.0;
  for (int64_t c = plan.object_chunk[object] + threadIdx.x; c < plan.object_chunk[object + 1]; c += kReduceBlock) {
    acc += __ldcg(scratch + c);
  }
  total = block_sum(acc);
  if (threadIdx.x == 0) counter[object] = 0;
  return true;
}

// The end of an implicit Euler step's object sums (euler_update, hooke_node_solve_step): publishes
// this block's chunk sum of |v_new|^2 (valid in thread 0); the object's last block calls
// column(pos, total) in thread 0 to write its summary column, pos being the ring row (read
// before any object advanced it; -1 without a ring), and the block that finishes the last object
// advances ring_pos (counter[B] counts objects; zero again after).
template <typename S, class Column>
__device__ inline void finish_step_summary(const StepSummary<S>& out, const CGPlan& plan, int64_t chunk,
                                           int64_t object, double chunk_total, double* scratch, int32_t* counter,
                                           const Column& column) {
  double total = 0.0;
  if (object_total(plan, chunk, object, chunk_total, scratch, counter, total) && threadIdx.x == 0) {
    const int64_t pos = out.ring_pos != nullptr ? *reinterpret_cast<volatile int64_t*>(out.ring_pos) : -1;
    column(pos, total);
    __threadfence();
    const int32_t objects = static_cast<int32_t>(plan.num_objects);
    if (atomicAdd(counter + plan.num_objects, 1) == objects - 1) {  // every object has read ring_pos
      if (out.ring_pos != nullptr) *out.ring_pos = pos + 1;
      counter[plan.num_objects] = 0;
    }
  }
}

// A CG matvec that ends in the step length: node kernel k (k.apply(i) writes Ap_i and returns
// p_i . Ap_i) over the nodes of each chunk of an active object, then alpha as cg_alpha does,
// summing in cg_alpha's pattern (so alpha is bitwise cg_alpha's). Objects that are not active
// are skipped: their Ap is not computed (cg_update skips them too).
template <class K, typename S>
__global__ void __launch_bounds__(kReduceBlock) chunk_alpha_kernel(const K k, CGPlan plan, const S* __restrict__ rr,
                                                                  int32_t* status, S* alpha, double* scratch,
                                                                  int32_t* counter) {
  const int64_t chunk = blockIdx.x, object = plan.chunk_object[chunk];
  if (status[object] != kActive) return;
  double acc = 0.0;
  for (int64_t i = plan.chunk_start[chunk] + threadIdx.x; i < plan.chunk_start[chunk + 1]; i += kReduceBlock) {
    acc += static_cast<double>(k.apply(i));
  }
  const double chunk_total = block_sum(acc);
  double total = 0.0;
  if (object_total(plan, chunk, object, chunk_total, scratch, counter, total) && threadIdx.x == 0) {
    int32_t st = status[object];
    alpha[object] = cg_alpha_step<S>(total, rr[object], st);
    status[object] = st;
  }
}

template <class K, typename S>
void launch_chunk_alpha(const CGPlan& plan, const K& k, const S* rr, int32_t* status, S* alpha, double* scratch,
                        int32_t* counter) {
  if (plan.num_chunks == 0) return;
  chunk_alpha_kernel<K, S><<<static_cast<unsigned int>(plan.num_chunks), kReduceBlock, 0,
                             at::cuda::getCurrentCUDAStream()>>>(k, plan, rr, status, alpha, scratch, counter);
  C10_CUDA_KERNEL_LAUNCH_CHECK();
}

}  // namespace tensormass
