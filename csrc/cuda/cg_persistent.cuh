// A whole batched CG solve in ONE kernel launch (the GPU side of hooke_node_cg): a persistent,
// cooperatively launched grid whose blocks walk the chunks of the plan, with grid-wide barriers
// where the per-iteration launches were. Each iteration is three phases:
//
//   M  matvec: Ap and the chunk sums of p.Ap            (node kernel k)
//   U  alpha (from the object's chunk sums), x += alpha p, r -= alpha Ap, chunk sums of r.r
//   D  beta, convergence / cap, p = r + beta p; the count of objects still active
//
// then, when no object is active, every block leaves the loop together (the count is read after
// the barrier): convergence is decided on the device, with no host round trip. The optional
// start phase (r = p = b, x = 0, b.b, thresholds, statuses) runs first.
//
// Every sum is taken in the pattern of the per-iteration kernels (cg_reduce.cuh: per thread
// strided over the chunk, then block_sum; the object total strided over its chunk sums, then
// block_sum), and the scalar steps are cg.h's, so the iterates are bitwise those of the
// matvec-alpha / cg_update / cg_direction sequence. Where a per-object scalar is read by many
// blocks in a phase, every block computes it from the chunk sums itself (deterministic: the same
// value everywhere); the first chunk's block writes it, into the other parity of the scalars
// (CGRun), never into the values other blocks may still be reading.
#pragma once

#include <cooperative_groups.h>

#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>

#include <cstdint>

#include "../cg.h"
#include "../kernels.h"
#include "cg_reduce.cuh"

namespace tensormass {

// block_sum, its result in every thread; ends with a barrier so that it can be called again.
__device__ inline double block_total(double v) {
  __shared__ double total;
  v = block_sum(v);
  if (threadIdx.x == 0) total = v;
  __syncthreads();
  const double out = total;
  __syncthreads();
  return out;
}

// The object's total over its chunk sums, in object_total's pattern, in every thread.
__device__ inline double object_chunk_total(const CGPlan& plan, int64_t object, const double* sums) {
  double acc = 0.0;
  for (int64_t c = plan.object_chunk[object] + threadIdx.x; c < plan.object_chunk[object + 1]; c += kReduceBlock) {
    acc += sums[c];
  }
  return block_total(acc);
}

// The per-object scalars of one parity.
template <typename S>
struct CGScalars {
  S* rr;
  int32_t* status;
  int32_t* iterations;
};

// Resident blocks per SM the kernel is compiled for (a register budget of 85 per thread): with
// 2 (98 registers), the SOFA beam's 304 chunks did not fit in one wave of an H100's 132 SMs.
constexpr int kPersistentBlocksPerSM = 3;

template <class K, typename S>
__global__ void __launch_bounds__(kReduceBlock, kPersistentBlocksPerSM) persistent_cg_kernel(const K k, const CGPlan plan, const CGRun<S> s) {
  namespace coop = cooperative_groups;
  coop::grid_group grid = coop::this_grid();
  const int64_t d = s.d, num_chunks = plan.num_chunks, num_objects = plan.num_objects;
  const unsigned tid = threadIdx.x;
  double* sums_pap = s.sums;
  double* sums_rr = s.sums + num_chunks;
  int32_t* status_after_alpha = s.work + 2 * num_objects;
  int32_t* active_count = s.work + 3 * num_objects;  // [2], one per parity
  const CGScalars<S> even{s.rr, s.status, s.iterations}, odd{s.rr_swap, s.work, s.work + num_objects};

  if (s.rhs != nullptr) {  // start from x0 = 0: r = p = projected b, and b.b per chunk
    for (int64_t c = blockIdx.x; c < num_chunks; c += gridDim.x) {
      double acc = 0.0;
      for (int64_t j = plan.chunk_start[c] * d + tid; j < plan.chunk_start[c + 1] * d; j += kReduceBlock) {
        const S b = s.free != nullptr ? s.rhs[j] * s.free[j / d] : s.rhs[j];
        s.x[j] = S(0);
        s.r[j] = b;
        s.p[j] = b;
        acc += static_cast<double>(b) * static_cast<double>(b);
      }
      const double total = block_total(acc);
      if (tid == 0) sums_pap[c] = total;
    }
    grid.sync();
    for (int64_t c = blockIdx.x; c < num_chunks; c += gridDim.x) {
      const int64_t b = plan.chunk_object[c];
      if (c != plan.object_chunk[b]) continue;  // the object's first chunk sets its scalars
      const S bb = static_cast<S>(object_chunk_total(plan, b, sums_pap));
      if (tid == 0) {
        const S threshold = bb * s.tol_sq;
        s.rhs_sq[b] = bb;
        s.rr[b] = bb;
        s.threshold[b] = threshold;
        s.status[b] = cg_start_status(bb, threshold, s.max_iter);
        s.iterations[b] = 0;
        s.alpha[b] = S(0);
        s.beta[b] = S(0);
      }
    }
    grid.sync();
  }

  int64_t done = 0;
  while (done < s.count) {
    const CGScalars<S> cur = (done & 1) ? odd : even, next = (done & 1) ? even : odd;
    int32_t* next_active = active_count + ((done + 1) & 1);
    // M: Ap, chunk sums of p.Ap (p read coherently: phase D of the last iteration wrote it)
    if (blockIdx.x == 0 && tid == 0) *next_active = 0;
    for (int64_t c = blockIdx.x; c < num_chunks; c += gridDim.x) {
      if (cur.status[plan.chunk_object[c]] != kActive) continue;
      double acc = 0.0;
      for (int64_t i = plan.chunk_start[c] + tid; i < plan.chunk_start[c + 1]; i += kReduceBlock) {
        acc += static_cast<double>(k.apply(i, CoherentLoader()));
      }
      const double total = block_total(acc);
      if (tid == 0) sums_pap[c] = total;
    }
    grid.sync();
    // U: alpha, x and r, chunk sums of r.r
    int64_t known = -1;
    S alpha = S(0);
    int32_t status = kActive;
    for (int64_t c = blockIdx.x; c < num_chunks; c += gridDim.x) {
      const int64_t b = plan.chunk_object[c];
      if (cur.status[b] != kActive) continue;
      if (b != known) {  // consecutive chunks of a block mostly share their object
        status = kActive;
        alpha = cg_alpha_step<S>(object_chunk_total(plan, b, sums_pap), cur.rr[b], status);
        known = b;
      }
      if (tid == 0 && c == plan.object_chunk[b]) {
        s.alpha[b] = alpha;
        status_after_alpha[b] = status;
      }
      if (status != kActive) continue;
      double acc = 0.0;
      for (int64_t j = plan.chunk_start[c] * d + tid; j < plan.chunk_start[c + 1] * d; j += kReduceBlock) {
        s.x[j] += alpha * s.p[j];
        const S rj = s.r[j] - alpha * s.ap[j];
        s.r[j] = rj;
        acc += static_cast<double>(rj) * static_cast<double>(rj);
      }
      const double total = block_total(acc);
      if (tid == 0) sums_rr[c] = total;
    }
    grid.sync();
    // D: beta, the object's new status, p; the scalars into the other parity
    known = -1;
    S beta = S(0), rr = S(0);
    int32_t iterations = 0;
    for (int64_t c = blockIdx.x; c < num_chunks; c += gridDim.x) {
      const int64_t b = plan.chunk_object[c];
      const bool first = c == plan.object_chunk[b];
      const int32_t before = cur.status[b];
      const int32_t after_alpha = before == kActive ? status_after_alpha[b] : before;
      if (after_alpha != kActive) {  // stopped before or at this step length: carried over
        if (first && tid == 0) {
          next.status[b] = after_alpha;
          next.rr[b] = cur.rr[b];
          next.iterations[b] = cur.iterations[b];
        }
        continue;
      }
      if (b != known) {
        status = kActive;
        rr = cur.rr[b];
        iterations = cur.iterations[b];
        beta = cg_beta_step<S>(object_chunk_total(plan, b, sums_rr), rr, s.threshold[b], s.max_iter, status,
                               iterations);
        known = b;
      }
      if (first && tid == 0) {
        next.status[b] = status;
        next.rr[b] = rr;
        next.iterations[b] = iterations;
        s.beta[b] = beta;
        if (status == kActive) atomicAdd(next_active, 1);
      }
      if (status != kActive) continue;
      for (int64_t j = plan.chunk_start[c] * d + tid; j < plan.chunk_start[c + 1] * d; j += kReduceBlock) {
        s.p[j] = s.r[j] + beta * s.p[j];
      }
    }
    grid.sync();
    ++done;
    if (*reinterpret_cast<volatile int32_t*>(next_active) == 0) break;  // the same value in every block
  }

  if (done & 1) {  // the scalars ended in the other parity: back into the caller's buffers
    const CGScalars<S>& last = odd;
    for (int64_t c = blockIdx.x; c < num_chunks; c += gridDim.x) {
      const int64_t b = plan.chunk_object[c];
      if (tid == 0 && c == plan.object_chunk[b]) {
        s.rr[b] = last.rr[b];
        s.status[b] = last.status[b];
        s.iterations[b] = last.iterations[b];
      }
    }
  }
}

// Launches the persistent CG with as many blocks as can be resident at once (at most one per
// chunk): a cooperative launch, which guarantees that residency (the grid barriers need it) or
// fails.
template <class K, typename S>
void launch_persistent_cg(const CGPlan& plan, const K& k, const CGRun<S>& s) {
  if (plan.num_chunks == 0 || (s.rhs == nullptr && s.count == 0)) return;
  static int blocks_per_sm = -1;  // per kernel instantiation
  static int sm_count = 0;
  if (blocks_per_sm < 0) {
    const auto* props = at::cuda::getCurrentDeviceProperties();
    sm_count = props->multiProcessorCount;
    C10_CUDA_CHECK(cudaOccupancyMaxActiveBlocksPerMultiprocessor(&blocks_per_sm, persistent_cg_kernel<K, S>,
                                                                 kReduceBlock, 0));
  }
  TORCH_CHECK(blocks_per_sm > 0, "tensormass: the persistent CG kernel cannot be resident on this device");
  const int64_t resident = static_cast<int64_t>(blocks_per_sm) * sm_count;
  const unsigned grid = static_cast<unsigned>(plan.num_chunks < resident ? plan.num_chunks : resident);
  K kernel_k = k;
  CGPlan kernel_plan = plan;
  CGRun<S> kernel_s = s;
  void* args[] = {&kernel_k, &kernel_plan, &kernel_s};
  C10_CUDA_CHECK(cudaLaunchCooperativeKernel(reinterpret_cast<const void*>(&persistent_cg_kernel<K, S>),
                                             dim3(grid), dim3(kReduceBlock), args, 0,
                                             at::cuda::getCurrentCUDAStream()));
}

}  // namespace tensormass
