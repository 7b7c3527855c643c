// CUDA implementations of the CG ops (common/cg.h, common/cg_checks.h). One block per chunk; the
// reductions (block sums, the last block of an object doing the object's sum and its scalar step):
// common/cg_reduce.cuh.
// Everything runs on the current stream with no host synchronisation, so an iteration can be
// captured in a CUDA graph.
#include <ATen/Dispatch.h>
#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>
#include <c10/cuda/CUDAGuard.h>
#include <torch/library.h>

#include "common/cg.h"
#include "common/cg_checks.h"
#include "common/cg_reduce.cuh"
#include "common/kernel_io.h"

namespace tensormass {
namespace {

constexpr int kBlock = kReduceBlock;

// cg_alpha is the step-length end of the fused matvecs over a "kernel" that only reads the
// per-node dots: the same sums, the same scalar step (chunk_alpha_kernel, cg_reduce.cuh).
template <typename S>
struct NodeDots {
  using Scalar = S;
  const S* p_dot_ap;  // [V]
  __device__ S apply(int64_t i) const { return ld(p_dot_ap + i); }
};

template <typename S>
__global__ void __launch_bounds__(kBlock) cg_update_kernel(S* __restrict__ x, S* __restrict__ r,
                                                           const S* __restrict__ p, const S* __restrict__ ap,
                                                           const S* __restrict__ alpha, CGPlan plan, int64_t d,
                                                           const S* __restrict__ threshold, int64_t max_iter, S* rr,
                                                           int32_t* status, S* beta, int32_t* iterations,
                                                           double* scratch, int32_t* counter,
                                                           const BlockUpdate<S> blocks) {
  const int64_t chunk = blockIdx.x, object = plan.chunk_object[chunk];
  if (status[object] != kActive) return;
  const S a = alpha[object];
  double acc = 0.0;
  if (blocks.inverse != nullptr) {  // preconditioned: a node a thread, r.z (BlockUpdate)
    for (int64_t i = plan.chunk_start[chunk] + threadIdx.x; i < plan.chunk_start[chunk + 1]; i += kBlock) {
      acc += blocks.apply(i, a);
    }
  } else {
    for (int64_t j = plan.chunk_start[chunk] * d + threadIdx.x; j < plan.chunk_start[chunk + 1] * d; j += kBlock) {
      x[j] += a * p[j];
      const S rj = r[j] - a * ap[j];
      r[j] = rj;
      acc += static_cast<double>(rj) * static_cast<double>(rj);
    }
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
                                                              CGPlan plan, int64_t d, const RigidMotion<S> coarse) {
  const int64_t chunk = blockIdx.x, object = plan.chunk_object[chunk];
  if (status[object] != kActive) return;
  const S bt = beta[object];
  if (coarse.coarse != nullptr) {  // p = z + weight Z' y + beta p, a node a thread (d = 3)
    for (int64_t i = plan.chunk_start[chunk] + threadIdx.x; i < plan.chunk_start[chunk + 1]; i += kBlock) {
      coarse_direction_node(i, r, bt, p, coarse);
    }
    return;
  }
  for (int64_t j = plan.chunk_start[chunk] * d + threadIdx.x; j < plan.chunk_start[chunk + 1] * d; j += kBlock) {
    p[j] = r[j] + bt * p[j];
  }
}

// cg_coarse_beta: a block an object sums u . v over its items (strided per-thread sums, then
// block_sum: a fixed order) and takes beta (common/cg.h: coarse_rz, pcg_beta_step).
template <typename S>
__global__ void __launch_bounds__(kBlock) cg_coarse_beta_kernel(const S* __restrict__ rr, const S* __restrict__ u,
                                                                const S* __restrict__ v,
                                                                const int64_t* __restrict__ item_ptr, int64_t k,
                                                                double weight, const int32_t* status, S* rz,
                                                                S* beta) {
  const int64_t object = blockIdx.x;
  if (status[object] != kActive) return;
  double acc = 0.0;
  for (int64_t j = item_ptr[object] * k + threadIdx.x; j < item_ptr[object + 1] * k; j += kBlock) {
    acc += static_cast<double>(u[j]) * static_cast<double>(v[j]);
  }
  const double total = block_sum(acc);
  if (threadIdx.x == 0) {
    S rz_b = rz[object];
    beta[object] = pcg_beta_step<S>(coarse_rz<S>(rr[object], total, weight), rz_b);
    rz[object] = rz_b;
  }
}

// cg_start_status, cg_round_end: a thread an object (common/cg.h: start_object, round_end_object).
template <typename S>
__global__ void __launch_bounds__(kBlock) cg_start_status_kernel(const S* __restrict__ rr, const S* __restrict__ rhs_sq,
                                                                 S tol_sq, int64_t max_iter, const S* floor,
                                                                 const int32_t* gate, int64_t objects, S* threshold,
                                                                 int32_t* status, int32_t* iterations, S* alpha,
                                                                 S* beta) {
  const int64_t o = static_cast<int64_t>(blockIdx.x) * kBlock + threadIdx.x;
  if (o >= objects) return;
  start_object<S>(rr[o], rhs_sq[o], tol_sq, max_iter, floor, gate, o, threshold[o], status[o], iterations[o],
                  alpha[o], beta[o]);
}

template <typename S>
__global__ void __launch_bounds__(kBlock) cg_round_end_kernel(const S* __restrict__ rr, const S* __restrict__ threshold,
                                                              const int32_t* __restrict__ round_status,
                                                              const int32_t* __restrict__ round_iterations,
                                                              int64_t objects, int32_t* status, int32_t* iterations) {
  const int64_t o = static_cast<int64_t>(blockIdx.x) * kBlock + threadIdx.x;
  if (o >= objects) return;
  round_end_object<S>(rr[o], threshold[o], round_status[o], round_iterations[o], status[o], iterations[o]);
}

// cg_pair_term in two passes: a thread a pair over every object's pairs (an object may hold
// hundreds of thousands: one block an object would walk them one after another), each pair's
// part of r.z into dots; then a block an object sums its pairs' dots (coalesced, block_sum: a fixed
// order) and takes its end (common/cg.h: pair_term_item, pair_rz_end).
template <typename S>
__global__ void __launch_bounds__(kBlock) cg_pair_term_kernel(const S* __restrict__ r, S* __restrict__ z,
                                                              const int64_t* __restrict__ nodes,
                                                              const S* __restrict__ blocks,
                                                              const int64_t* __restrict__ item_ptr, int64_t objects,
                                                              const int32_t* status, double* __restrict__ dots) {
  const int64_t k = static_cast<int64_t>(blockIdx.x) * kBlock + threadIdx.x;
  if (k >= item_ptr[objects]) return;
  int64_t lo = 0, hi = objects;  // the pair's object: item_ptr[lo] <= k < item_ptr[hi]
  while (hi - lo > 1) {
    const int64_t mid = (lo + hi) / 2;
    if (item_ptr[mid] <= k) {
      lo = mid;
    } else {
      hi = mid;
    }
  }
  if (status[lo] != kActive) return;
  dots[k] = pair_term_item<S>(k, nodes, blocks, r, z);
}

template <typename S>
__global__ void __launch_bounds__(kBlock) cg_pair_rz_kernel(const double* __restrict__ dots,
                                                            const int64_t* __restrict__ item_ptr,
                                                            const S* __restrict__ rr, const int32_t* status, S* rz,
                                                            S* beta, bool step) {
  const int64_t object = blockIdx.x;
  if (status[object] != kActive) return;
  double acc = 0.0;
  for (int64_t k = item_ptr[object] + threadIdx.x; k < item_ptr[object + 1]; k += kBlock) acc += dots[k];
  const double total = block_sum(acc);
  if (threadIdx.x == 0) {
    S rz_b = rz[object], beta_b = beta[object];
    pair_rz_end<S>(rr[object], total, step, rz_b, beta_b);
    rz[object] = rz_b;
    beta[object] = beta_b;
  }
}

// This block's chunk of a . b (float64, the block's fixed order of sums), in every thread.
template <typename S>
__device__ double chunk_dot_sum(const S* __restrict__ a, const S* __restrict__ b, const CGPlan& plan, int64_t chunk,
                                int64_t d) {
  double acc = 0.0;
  for (int64_t j = plan.chunk_start[chunk] * d + threadIdx.x; j < plan.chunk_start[chunk + 1] * d; j += kBlock) {
    acc += static_cast<double>(a[j]) * static_cast<double>(b[j]);
  }
  return block_sum(acc);
}

template <typename S>
__global__ void __launch_bounds__(kBlock) cg_dot_kernel(const S* __restrict__ a, const S* __restrict__ b, CGPlan plan,
                                                        int64_t d, S* out, double* scratch, int32_t* counter) {
  const int64_t chunk = blockIdx.x, object = plan.chunk_object[chunk];
  const double chunk_total = chunk_dot_sum(a, b, plan, chunk, d);
  double total = 0.0;
  if (object_total(plan, chunk, object, chunk_total, scratch, counter, total) && threadIdx.x == 0) {
    out[object] = static_cast<S>(total);
  }
}

// cg_dot_beta: cg_dot's sums over the chunks of active objects; the object's last block takes
// preconditioned CG's beta and r.z (pcg_beta_step).
template <typename S>
__global__ void __launch_bounds__(kBlock) cg_dot_beta_kernel(const S* __restrict__ a, const S* __restrict__ b,
                                                             CGPlan plan, int64_t d, const int32_t* status, S* rz,
                                                             S* beta, double* scratch, int32_t* counter) {
  const int64_t chunk = blockIdx.x, object = plan.chunk_object[chunk];
  if (status[object] != kActive) return;
  const double chunk_total = chunk_dot_sum(a, b, plan, chunk, d);
  double total = 0.0;
  if (object_total(plan, chunk, object, chunk_total, scratch, counter, total) && threadIdx.x == 0) {
    S rz_b = rz[object];
    beta[object] = pcg_beta_step<S>(static_cast<S>(total), rz_b);
    rz[object] = rz_b;
  }
}

// euler_update: one block per chunk; the object's last block writes its summary column (and ring
// row): finish_step_summary.
template <typename S>
__global__ void __launch_bounds__(kBlock) euler_update_kernel(const EulerUpdate<S> update, const StepSummary<S> out,
                                                              CGPlan plan, double* scratch, int32_t* counter) {
  const int64_t chunk = blockIdx.x, object = plan.chunk_object[chunk], d = update.d;
  double acc = 0.0;
  for (int64_t j = plan.chunk_start[chunk] * d + threadIdx.x; j < plan.chunk_start[chunk + 1] * d; j += kBlock) {
    const S vn = update(j);
    acc += static_cast<double>(vn) * static_cast<double>(vn);
  }
  finish_step_summary<S>(out, plan, chunk, object, block_sum(acc), scratch, counter,
                         [&](int64_t pos, double total) { out.write(object, plan.num_objects, total, pos); });
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
    launch_chunk_alpha<NodeDots<scalar_t>, scalar_t>(plan, NodeDots<scalar_t>{p_dot_ap.data_ptr<scalar_t>()},
                                                    rr.data_ptr<scalar_t>(), status.data_ptr<int32_t>(),
                                                    alpha.data_ptr<scalar_t>(), scratch.data_ptr<double>(),
                                                    counter.data_ptr<int32_t>());
  });
}

void cg_alpha_dot_cuda(const at::Tensor& p, at::Tensor ap, const c10::optional<at::Tensor>& free,
                       const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                       const at::Tensor& rr, at::Tensor status, at::Tensor alpha, at::Tensor scratch,
                       at::Tensor counter) {
  const CGPlan plan = check_cg_alpha_dot(p, ap, free, chunk_start, chunk_object, object_chunk, rr, status, alpha,
                                         scratch, counter);
  if (plan.num_chunks == 0) return;
  c10::cuda::CUDAGuard guard(p.device());
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "cg_alpha_dot", [&] {
    const ProjectedDots<scalar_t> dots = projected_dots<scalar_t>(p, ap, free);
    launch_chunk_alpha<ProjectedDots<scalar_t>, scalar_t>(plan, dots, rr.data_ptr<scalar_t>(),
                                                         status.data_ptr<int32_t>(), alpha.data_ptr<scalar_t>(),
                                                         scratch.data_ptr<double>(), counter.data_ptr<int32_t>());
  });
}

void cg_update_cuda(at::Tensor x, at::Tensor r, const at::Tensor& p, const at::Tensor& ap, const at::Tensor& alpha,
                    const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                    const at::Tensor& threshold, int64_t max_iter, at::Tensor rr, at::Tensor status, at::Tensor beta,
                    at::Tensor iterations, at::Tensor scratch, at::Tensor counter,
                    const c10::optional<at::Tensor>& inverse_blocks, const c10::optional<at::Tensor>& z) {
  const CGPlan plan = check_cg_update(x, r, p, ap, alpha, chunk_start, chunk_object, object_chunk, threshold, max_iter,
                                      rr, status, beta, iterations, scratch, counter, inverse_blocks, z);
  if (plan.num_chunks == 0) return;
  c10::cuda::CUDAGuard guard(x.device());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "cg_update", [&] {
    cg_update_kernel<scalar_t><<<grid_of(plan), kBlock, 0, at::cuda::getCurrentCUDAStream()>>>(
        x.data_ptr<scalar_t>(), r.data_ptr<scalar_t>(), p.data_ptr<scalar_t>(), ap.data_ptr<scalar_t>(),
        alpha.data_ptr<scalar_t>(), plan, values_per_node(x), threshold.data_ptr<scalar_t>(), max_iter,
        rr.data_ptr<scalar_t>(), status.data_ptr<int32_t>(), beta.data_ptr<scalar_t>(),
        iterations.data_ptr<int32_t>(), scratch.data_ptr<double>(), counter.data_ptr<int32_t>(),
        block_update_of<scalar_t>(x, r, p, ap, inverse_blocks, z));
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

void cg_direction_cuda(at::Tensor p, const at::Tensor& r, const at::Tensor& beta, const at::Tensor& status,
                       const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                       const c10::optional<at::Tensor>& node_inverse, const c10::optional<at::Tensor>& arm,
                       const c10::optional<at::Tensor>& node_body, const c10::optional<at::Tensor>& coarse,
                       double weight) {
  const CGPlan plan = check_cg_direction(p, r, beta, status, chunk_start, chunk_object, object_chunk);
  const bool with_coarse = check_coarse_term(p, node_inverse, arm, node_body, coarse);
  if (plan.num_chunks == 0) return;
  c10::cuda::CUDAGuard guard(p.device());
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "cg_direction", [&] {
    const RigidMotion<scalar_t> motion =
        with_coarse ? rigid_motion_of<scalar_t>(node_inverse, arm, node_body, coarse, weight) : RigidMotion<scalar_t>{};
    cg_direction_kernel<scalar_t><<<grid_of(plan), kBlock, 0, at::cuda::getCurrentCUDAStream()>>>(
        p.data_ptr<scalar_t>(), r.data_ptr<scalar_t>(), beta.data_ptr<scalar_t>(), status.data_ptr<int32_t>(), plan,
        values_per_node(p), motion);
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

void cg_coarse_beta_cuda(const at::Tensor& rr, const at::Tensor& u, const at::Tensor& v, const at::Tensor& item_ptr,
                         double weight, const at::Tensor& status, at::Tensor rz, at::Tensor beta) {
  const int64_t objects = check_cg_coarse_beta(rr, u, v, item_ptr, status, rz, beta);
  if (objects == 0) return;
  c10::cuda::CUDAGuard guard(rr.device());
  AT_DISPATCH_FLOATING_TYPES(rr.scalar_type(), "cg_coarse_beta", [&] {
    cg_coarse_beta_kernel<scalar_t><<<static_cast<unsigned int>(objects), kBlock, 0,
                                      at::cuda::getCurrentCUDAStream()>>>(
        rr.data_ptr<scalar_t>(), u.data_ptr<scalar_t>(), v.data_ptr<scalar_t>(), item_ptr.data_ptr<int64_t>(),
        u.size(1), weight, status.data_ptr<int32_t>(), rz.data_ptr<scalar_t>(), beta.data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

unsigned int object_grid(int64_t objects) { return static_cast<unsigned int>((objects + kBlock - 1) / kBlock); }

void cg_start_status_cuda(const at::Tensor& rr, const at::Tensor& rhs_sq, double tol_sq, int64_t max_iter,
                          at::Tensor threshold, at::Tensor status, at::Tensor iterations, at::Tensor alpha,
                          at::Tensor beta, const c10::optional<at::Tensor>& floor,
                          const c10::optional<at::Tensor>& gate) {
  const int64_t objects =
      check_cg_start_status(rr, rhs_sq, max_iter, threshold, status, iterations, alpha, beta, floor, gate);
  if (objects == 0) return;
  c10::cuda::CUDAGuard guard(rr.device());
  AT_DISPATCH_FLOATING_TYPES(rr.scalar_type(), "cg_start_status", [&] {
    const scalar_t* floor_b = floor.has_value() && floor->defined() ? floor->data_ptr<scalar_t>() : nullptr;
    const int32_t* gate_b = gate.has_value() && gate->defined() ? gate->data_ptr<int32_t>() : nullptr;
    cg_start_status_kernel<scalar_t><<<object_grid(objects), kBlock, 0, at::cuda::getCurrentCUDAStream()>>>(
        rr.data_ptr<scalar_t>(), rhs_sq.data_ptr<scalar_t>(), static_cast<scalar_t>(tol_sq), max_iter, floor_b, gate_b,
        objects, threshold.data_ptr<scalar_t>(), status.data_ptr<int32_t>(), iterations.data_ptr<int32_t>(),
        alpha.data_ptr<scalar_t>(), beta.data_ptr<scalar_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

void cg_round_end_cuda(const at::Tensor& rr, const at::Tensor& threshold, const at::Tensor& round_status,
                       const at::Tensor& round_iterations, at::Tensor status, at::Tensor iterations) {
  const int64_t objects = check_cg_round_end(rr, threshold, round_status, round_iterations, status, iterations);
  if (objects == 0) return;
  c10::cuda::CUDAGuard guard(rr.device());
  AT_DISPATCH_FLOATING_TYPES(rr.scalar_type(), "cg_round_end", [&] {
    cg_round_end_kernel<scalar_t><<<object_grid(objects), kBlock, 0, at::cuda::getCurrentCUDAStream()>>>(
        rr.data_ptr<scalar_t>(), threshold.data_ptr<scalar_t>(), round_status.data_ptr<int32_t>(),
        round_iterations.data_ptr<int32_t>(), objects, status.data_ptr<int32_t>(), iterations.data_ptr<int32_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

void cg_pair_term_cuda(const at::Tensor& r, at::Tensor z, const at::Tensor& nodes, const at::Tensor& blocks,
                       const at::Tensor& item_ptr, const at::Tensor& rr, const at::Tensor& status, at::Tensor rz,
                       at::Tensor beta, at::Tensor dots, bool step) {
  const int64_t objects = check_cg_pair_term(r, z, nodes, blocks, item_ptr, rr, status, rz, beta, dots);
  if (objects == 0) return;
  c10::cuda::CUDAGuard guard(r.device());
  const auto stream = at::cuda::getCurrentCUDAStream();
  AT_DISPATCH_FLOATING_TYPES(r.scalar_type(), "cg_pair_term", [&] {
    const int64_t pairs = nodes.size(0);
    if (pairs > 0) {
      cg_pair_term_kernel<scalar_t><<<static_cast<unsigned int>((pairs + kBlock - 1) / kBlock), kBlock, 0, stream>>>(
          r.data_ptr<scalar_t>(), z.data_ptr<scalar_t>(), nodes.data_ptr<int64_t>(), blocks.data_ptr<scalar_t>(),
          item_ptr.data_ptr<int64_t>(), objects, status.data_ptr<int32_t>(), dots.data_ptr<double>());
      C10_CUDA_KERNEL_LAUNCH_CHECK();
    }
    cg_pair_rz_kernel<scalar_t><<<static_cast<unsigned int>(objects), kBlock, 0, stream>>>(
        dots.data_ptr<double>(), item_ptr.data_ptr<int64_t>(), rr.data_ptr<scalar_t>(), status.data_ptr<int32_t>(),
        rz.data_ptr<scalar_t>(), beta.data_ptr<scalar_t>(), step);
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

void cg_dot_beta_cuda(const at::Tensor& r, const at::Tensor& z, const at::Tensor& chunk_start,
                      const at::Tensor& chunk_object, const at::Tensor& object_chunk, const at::Tensor& status,
                      at::Tensor rz, at::Tensor beta, at::Tensor scratch, at::Tensor counter) {
  const CGPlan plan = check_cg_dot_beta(r, z, chunk_start, chunk_object, object_chunk, status, rz, beta, scratch,
                                        counter);
  if (plan.num_chunks == 0) return;
  c10::cuda::CUDAGuard guard(r.device());
  AT_DISPATCH_FLOATING_TYPES(r.scalar_type(), "cg_dot_beta", [&] {
    cg_dot_beta_kernel<scalar_t><<<grid_of(plan), kBlock, 0, at::cuda::getCurrentCUDAStream()>>>(
        r.data_ptr<scalar_t>(), z.data_ptr<scalar_t>(), plan, values_per_node(r), status.data_ptr<int32_t>(),
        rz.data_ptr<scalar_t>(), beta.data_ptr<scalar_t>(), scratch.data_ptr<double>(), counter.data_ptr<int32_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

void euler_update_cuda(at::Tensor x, at::Tensor v, const at::Tensor& dv, const c10::optional<at::Tensor>& dv_imposed,
                       double h, at::Tensor x_new, at::Tensor v_new, const at::Tensor& chunk_start,
                       const at::Tensor& chunk_object, const at::Tensor& object_chunk, const at::Tensor& status,
                       const at::Tensor& iterations, const at::Tensor& rr, const at::Tensor& rhs_sq, at::Tensor norms,
                       at::Tensor summary, at::Tensor scratch, at::Tensor counter,
                       const c10::optional<at::Tensor>& ring, const c10::optional<at::Tensor>& ring_pos, bool carry,
                       double h_old) {
  const CGPlan plan = check_euler_update(x, v, dv, dv_imposed, x_new, v_new, chunk_start, chunk_object, object_chunk,
                                         status, iterations, rr, rhs_sq, norms, summary, scratch, counter, ring,
                                         ring_pos);
  if (plan.num_chunks == 0) return;
  c10::cuda::CUDAGuard guard(x.device());
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "euler_update", [&] {
    euler_update_kernel<scalar_t><<<grid_of(plan), kBlock, 0, at::cuda::getCurrentCUDAStream()>>>(
        euler_update_of<scalar_t>(x, v, dv, dv_imposed, h, x_new, v_new, carry, h_old),
        step_summary_of<scalar_t>(status, iterations, rr, rhs_sq, norms, summary, ring, ring_pos), plan,
        scratch.data_ptr<double>(), counter.data_ptr<int32_t>());
    C10_CUDA_KERNEL_LAUNCH_CHECK();
  });
}

}  // namespace
}  // namespace tensormass

TORCH_LIBRARY_IMPL(tensormass, CUDA, m) {
  m.impl("euler_update", &tensormass::euler_update_cuda);
  m.impl("cg_dot", &tensormass::cg_dot_cuda);
  m.impl("cg_dot_beta", &tensormass::cg_dot_beta_cuda);
  m.impl("cg_alpha", &tensormass::cg_alpha_cuda);
  m.impl("cg_alpha_dot", &tensormass::cg_alpha_dot_cuda);
  m.impl("cg_update", &tensormass::cg_update_cuda);
  m.impl("cg_direction", &tensormass::cg_direction_cuda);
  m.impl("cg_coarse_beta", &tensormass::cg_coarse_beta_cuda);
  m.impl("cg_start_status", &tensormass::cg_start_status_cuda);
  m.impl("cg_round_end", &tensormass::cg_round_end_cuda);
  m.impl("cg_pair_term", &tensormass::cg_pair_term_cuda);
}
