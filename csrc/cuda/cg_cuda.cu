// CUDA implementations of the CG ops (cg.h). One block per chunk: the block sums its chunk in a
// fixed pattern (strided per-thread sums, then a shuffle tree) into scratch[chunk]; the last
// block of an object to finish (elected by an atomic ticket on counter[object]) sums the
// object's chunk sums in the same fixed pattern, runs the scalar step and resets the ticket.
// Which block is last changes from run to run; what it computes does not: deterministic.
// Everything runs on the current stream with no host synchronisation, so an iteration can be
// captured in a CUDA graph.
#include <ATen/Dispatch.h>
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include "cg.h"

namespace tensormass {
namespace {

constexpr int kBlock = 256;

// Sum over the block in a fixed order; the result is valid in thread 0.
__device__ double block_sum(double v) {
  __shared__ double warp_sums[kBlock / 32];
  for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_down_sync(0xffffffffu, v, offset);
  const int lane = threadIdx.x & 31, warp = threadIdx.x >> 5;
  if (lane == 0) warp_sums[warp] = v;
  __syncthreads();
  if (warp == 0) {
    v = lane < kBlock / 32 ? warp_sums[lane] : 0.0;
    for (int offset = 16; offset > 0; offset >>= 1) v += __shfl_down_sync(0xffffffffu, v, offset);
  }
  return v;
}

// Publishes this block's chunk sum and says whether this block is the object's last; if so,
// returns (in thread 0) the object's total over its chunks.
__device__ bool object_total(const CGPlan& plan, int64_t chunk, int64_t object, double chunk_total, double* scratch,
                             int32_t* counter, double& total) {
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
  for (int64_t c = plan.object_chunk[object] + threadIdx.x; c < plan.object_chunk[object + 1]; c += kBlock) {
    acc += __ldcg(scratch + c);
  }
  total = block_sum(acc);
  if (threadIdx.x == 0) counter[object] = 0;
  return true;
}

template <typename S>
__global__ void __launch_bounds__(kBlock) cg_alpha_kernel(const S* __restrict__ p_dot_ap, CGPlan plan,
                                                          const S* __restrict__ rr, int32_t* status, S* alpha,
                                                          double* scratch, int32_t* counter) {
  const int64_t chunk = blockIdx.x, object = plan.chunk_object[chunk];
  if (status[object] != kActive) return;
  double acc = 0.0;
  for (int64_t i = plan.chunk_start[chunk] + threadIdx.x; i < plan.chunk_start[chunk + 1]; i += kBlock) {
    acc += static_cast<double>(p_dot_ap[i]);
  }
  const double chunk_total = block_sum(acc);
  double total = 0.0;
  if (object_total(plan, chunk, object, chunk_total, scratch, counter, total) && threadIdx.x == 0) {
    int32_t st = status[object];
    alpha[object] = cg_alpha_step<S>(total, rr[object], st);
    status[object] = st;
  }
}

template <typename S>
__global__ void __launch_bounds__(kBlock) cg_update_kernel(S* __restrict__ x, S* __restrict__ r,
                                                           const S* __restrict__ p, const S* __restrict__ ap,
                                                           const S* __restrict__ alpha, CGPlan plan, int64_t d,
                                                           const S* __restrict__ threshold, int64_t max_iter, S* rr,
                                                           int32_t* status, S* beta, int32_t* iterations,
                                                           double* scratch, int32_t* counter) {
  const int64_t chunk = blockIdx.x, object = plan.chunk_object[chunk];
  if (status[object] != kActive) return;
  const S a = alpha[object];
  double acc = 0.0;
  for (int64_t j = plan.chunk_start[chunk] * d + threadIdx.x; j < plan.chunk_start[chunk + 1] * d; j += kBlock) {
    x[j] += a * p[j];
    const S rj = r[j] - a * ap[j];
    r[j] = rj;
    acc += static_cast<double>(rj) * static_cast<double>(rj);
  }
  const double chunk_total = block_sum(acc);
  double total = 0.0;
  if (object_total(plan, chunk, object, chunk_total, scratch, counter, total) && threadIdx.x == 0) {
    int32_t st = status[object], it = iterations[object];
    S rr_b = rr[object];
    beta[object] = cg_beta_step<S>(total, rr_b, threshold[object], max_iter, st, it);
    rr[object] = rr_b;
    status[object] = st;
    iterations[object] = it;
  }
}

template <typename S>
__global__ void __launch_bounds__(kBlock) cg_direction_kernel(S* __restrict__ p, const S* __restrict__ r,
                                                              const S* __restrict__ beta, const int32_t* status,
                                                              CGPlan plan, int64_t d) {
  const int64_t chunk = blockIdx.x, object = plan.chunk_object[chunk];
  if (status[object] != kActive) return;
  const S bt = beta[object];
  for (int64_t j = plan.chunk_start[chunk] * d + threadIdx.x; j < plan.chunk_start[chunk + 1] * d; j += kBlock) {
    p[j] = r[j] + bt * p[j];
  }
}

template <typename S>
__global__ void __launch_bounds__(kBlock) cg_dot_kernel(const S* __restrict__ a, const S* __restrict__ b, CGPlan plan,
                                                        int64_t d, S* out, double* scratch, int32_t* counter) {
  const int64_t chunk = blockIdx.x, object = plan.chunk_object[chunk];
  double acc = 0.0;
  for (int64_t j = plan.chunk_start[chunk] * d + threadIdx.x; j < plan.chunk_start[chunk + 1] * d; j += kBlock) {
    acc += static_cast<double>(a[j]) * static_cast<double>(b[j]);
  }
  const double chunk_total = block_sum(acc);
  double total = 0.0;
  if (object_total(plan, chunk, object, chunk_total, scratch, counter, total) && threadIdx.x == 0) {
    out[object] = static_cast<S>(total);
  }
}

unsigned int grid_of(const CGPlan& plan) { return static_cast<unsigned int>(plan.num_chunks); }

void cg_alpha_cuda(const at::Tensor& p_dot_ap, const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                   const at::Tensor& object_chunk, const at::Tensor& rr, at::Tensor status, at::Tensor alpha,
                   at::Tensor scratch, at::Tensor counter) {
  const CGPlan plan = check_cg_alpha(p_dot_ap, chunk_start, chunk_object, object_chunk, rr, status, alpha, scratch,
                                     counter);
  if (plan.num_chunks == 0) return;
  c10::cuda::CUDAGuard guard(p_dot_ap.device());
  AT_DISPATCH_FLOATING_TYPES(p_dot_ap.scalar_type(), "cg_alpha", [&] {
    cg_alpha_kernel<scalar_t><<<grid_of(plan), kBlock, 0, at::cuda::getCurrentCUDAStream()>>>(
        p_dot_ap.data_ptr<scalar_t>(), plan, rr.data_ptr<scalar_t>(), status.data_ptr<int32_t>(),
        alpha.data_ptr<scalar_t>(), scratch.data_ptr<double>(), counter.data_ptr<int32_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

void cg_update_cuda(at::Tensor x, at::Tensor r, const at::Tensor& p, const at::Tensor& ap, const at::Tensor& alpha,
                    const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                    const at::Tensor& threshold, int64_t max_iter, at::Tensor rr, at::Tensor status, at::Tensor beta,
                    at::Tensor iterations, at::Tensor scratch, at::Tensor counter) {
  const CGPlan plan = check_cg_update(x, r, p, ap, alpha, chunk_start, chunk_object, object_chunk, threshold, max_iter,
                                      rr, status, beta, iterations, scratch, counter);
  if (plan.num_chunks == 0) return;
  c10::cuda::CUDAGuard guard(x.device());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "cg_update", [&] {
    cg_update_kernel<scalar_t><<<grid_of(plan), kBlock, 0, at::cuda::getCurrentCUDAStream()>>>(
        x.data_ptr<scalar_t>(), r.data_ptr<scalar_t>(), p.data_ptr<scalar_t>(), ap.data_ptr<scalar_t>(),
        alpha.data_ptr<scalar_t>(), plan, values_per_node(x), threshold.data_ptr<scalar_t>(), max_iter,
        rr.data_ptr<scalar_t>(), status.data_ptr<int32_t>(), beta.data_ptr<scalar_t>(),
        iterations.data_ptr<int32_t>(), scratch.data_ptr<double>(), counter.data_ptr<int32_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

void cg_direction_cuda(at::Tensor p, const at::Tensor& r, const at::Tensor& beta, const at::Tensor& status,
                       const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk) {
  const CGPlan plan = check_cg_direction(p, r, beta, status, chunk_start, chunk_object, object_chunk);
  if (plan.num_chunks == 0) return;
  c10::cuda::CUDAGuard guard(p.device());
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "cg_direction", [&] {
    cg_direction_kernel<scalar_t><<<grid_of(plan), kBlock, 0, at::cuda::getCurrentCUDAStream()>>>(
        p.data_ptr<scalar_t>(), r.data_ptr<scalar_t>(), beta.data_ptr<scalar_t>(), status.data_ptr<int32_t>(), plan,
        values_per_node(p));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

void cg_dot_cuda(const at::Tensor& a, const at::Tensor& b, const at::Tensor& chunk_start,
                 const at::Tensor& chunk_object, const at::Tensor& object_chunk, at::Tensor out, at::Tensor scratch,
                 at::Tensor counter) {
  const CGPlan plan = check_cg_dot(a, b, chunk_start, chunk_object, object_chunk, out, scratch, counter);
  if (plan.num_chunks == 0) return;
  c10::cuda::CUDAGuard guard(a.device());
  AT_DISPATCH_FLOATING_TYPES(a.scalar_type(), "cg_dot", [&] {
    cg_dot_kernel<scalar_t><<<grid_of(plan), kBlock, 0, at::cuda::getCurrentCUDAStream()>>>(
        a.data_ptr<scalar_t>(), b.data_ptr<scalar_t>(), plan, values_per_node(a), out.data_ptr<scalar_t>(),
        scratch.data_ptr<double>(), counter.data_ptr<int32_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

}  // namespace
}  // namespace tensormass

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) {
  m.impl("cg_dot", &tensormass::cg_dot_cuda);
  m.impl("cg_alpha", &tensormass::cg_alpha_cuda);
  m.impl("cg_update", &tensormass::cg_update_cuda);
  m.impl("cg_direction", &tensormass::cg_direction_cuda);
}
