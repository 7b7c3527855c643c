// A whole batched CG solve in ONE kernel launch (the GPU side of hooke_node_cg): a persistent,
// cooperatively launched grid whose blocks walk the chunks of the plan, with grid-wide barriers
// where the per-iteration launches were. Iteration t is two phases:
//
//   M  the step before's beta (from its r.r chunk sums: convergence, cap, beta_{t-1}) and the
//      matvec along the new direction p_t = r + beta_{t-1} p, formed on the fly wherever the
//      node kernel reads p (the stored p is still the old one: other blocks read it); the chunk
//      sums of p_t.Ap; the count of objects still active
//   U  alpha, then on the block's own nodes p = p_t (stored now: no other block reads p in this
//      phase), x += alpha p, r -= alpha Ap, and the chunk sums of r.r
//
// cg_direction's work is thus split between M (read) and U (write), and one barrier per iteration
// is saved (there were three phases: matvec, update, direction). When the count read after M's
// barrier is zero, every block leaves the loop together: convergence is decided on the device,
// with no host round trip. After the last iteration, a last beta step and direction (D). The
// optional start phase (r = p = b, x = 0, b.b, thresholds, statuses) runs first.
//
// Every sum is taken in the pattern of the per-iteration kernels (cg_reduce.cuh: per thread
// strided over the chunk, then block_sum; the object total strided over its chunk sums, then
// block_sum), the scalar steps are cg.h's and the direction is formed with cg_direction's
// expression, so the iterates are bitwise those of the matvec-alpha / cg_update / cg_direction
// sequence. Where a per-object scalar is needed by many blocks, every block computes it from the
// chunk sums itself (deterministic: the same value everywhere); the first chunk's block writes
// it, into the other parity of the scalars (CGRun), never into values other blocks may still read.
#pragma once

#include <cooperative_groups.h>

#include <ATen/cuda/CUDAContext.h>
#include <c10/cuda/CUDAException.h>

#include <cstdint>
#include <cstdlib>

#include "common/cg.h"
#include "common/cg_reduce.cuh"
#include "common/kernel_io.h"
#include "common/node_graph.h"

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

// Resident blocks per SM the kernel is compiled for (a budget of 128 registers per thread: 3
// blocks, 85 registers, made the matvec along r + beta p spill): 264 blocks on an H100, one wave
// for the paper beam's 220 chunks of 256 nodes; larger plans loop over their chunks.
constexpr int kPersistentBlocksPerSM = 2;

// Slots of each node's neighbour list kept in shared memory for the whole solve (32 KB a block):
// the graph does not change between iterations, and its neighbour indices were the first of the
// two dependent global loads of every slot batch (neighbour, then its p). Nodes with more slots
// read the rest from the graph.
constexpr int kCachedSlots = 32;

// The neighbours of this thread's node: its column of the block's cache (cached[s * kReduceBlock]),
// then the graph's arrays (G: HookeNodeGraph::GlobalNeighbors).
template <class G>
struct SharedNeighbors {
  const int32_t* cached;
  G graph;
  __device__ int64_t operator()(int64_t s, int64_t i) const {
    return s < kCachedSlots ? static_cast<int64_t>(cached[s * kReduceBlock]) : graph(s, i);
  }
};

// The per-object scalars of one parity.
template <typename S>
struct CGScalars {
  S* rr;
  int32_t* status;
  int32_t* iterations;
};

// p as the matvec of iteration t reads it: the stored p when fresh (the first iteration of a
// call: its direction is already stored), else the new direction r + beta p, formed exactly as
// cg_direction forms it. Plain loads: p and r change during the kernel.
template <typename S>
struct DirectionLoader {
  const S* p;
  const S* r;
  S beta;
  bool fresh;
  TM_HD S operator()(const S* q) const { return fresh ? *q : r[q - p] + beta * *q; }
};

// An object's state after the beta step that ends an iteration (from the state before it, the
// status after its step length and the chunk sums of r.r); beta is set when the step ran.
template <typename S>
struct BetaStep {
  int32_t status;
  S rr;
  int32_t iterations;
  S beta;
  bool stepped;
};

template <typename S>
__device__ BetaStep<S> beta_step(const CGPlan& plan, const CGRun<S>& s, const CGScalars<S>& before, int64_t b,
                                 const int32_t* status_after_alpha, const double* sums_rr) {
  BetaStep<S> out{before.status[b], before.rr[b], before.iterations[b], S(0), false};
  if (out.status == kActive) out.status = status_after_alpha[b];
  if (out.status != kActive) return out;  // stopped before or at its step length: carried over
  out.beta = cg_beta_step<S>(object_chunk_total(plan, b, sums_rr), out.rr, s.threshold[b], s.max_iter, out.status,
                             out.iterations);
  out.stepped = true;
  return out;
}

template <typename S>
__device__ void write_scalars(const CGRun<S>& s, const CGScalars<S>& to, int64_t b, const BetaStep<S>& st) {
  to.status[b] = st.status;
  to.rr[b] = st.rr;
  to.iterations[b] = st.iterations;
  if (st.stepped) s.beta[b] = st.beta;
}

template <class K, typename S>
__global__ void __launch_bounds__(kReduceBlock, kPersistentBlocksPerSM) persistent_cg_kernel(const K k, const CGPlan plan,
                                                                                       const CGRun<S> s) {
  namespace coop = cooperative_groups;
  coop::grid_group grid = coop::this_grid();
  const int64_t d = s.d, num_chunks = plan.num_chunks, num_objects = plan.num_objects;
  const unsigned tid = threadIdx.x;
  double* sums_pap = s.sums;
  double* sums_rr = s.sums + num_chunks;
  int32_t* status_after_alpha = s.work + 2 * num_objects;
  int32_t* active_count = s.work + 3 * num_objects;  // [2], one per parity
  const CGScalars<S> even{s.rr, s.status, s.iterations}, odd{s.rr_swap, s.work, s.work + num_objects};

  // The first M counts the active objects into active_count[0]: zeroed here, before a barrier.
  if (blockIdx.x == 0 && tid == 0) active_count[0] = 0;
  if (s.rhs == nullptr) grid.sync();
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

  // One chunk per block with at most a node per thread (the one-wave plans that
  // ops.solve.persistent_cg_fits launches; a thread takes the node graph's row, whose node is one of
  // the object's, HookeNodeGraph): each thread keeps its row's slot count in a register
  // and its neighbours in its own column of shared memory (written and read by that thread only).
  using Global = typename decltype(k.graph)::GlobalNeighbors;
  __shared__ int32_t neighbor_cache[kCachedSlots * kReduceBlock];
  const int64_t own_begin = plan.chunk_start[blockIdx.x];
  const bool cached = s.cache_neighbors && num_chunks <= static_cast<int64_t>(gridDim.x) &&
                      plan.chunk_start[blockIdx.x + 1] - own_begin <= kReduceBlock && plan.num_nodes <= INT32_MAX;
  int64_t own_count = 0;
  if (cached && own_begin + tid < plan.chunk_start[blockIdx.x + 1]) {
    const Global graph{k.graph.neighbor, k.graph.num_nodes};
    own_count = static_cast<int64_t>(ld(k.graph.incidences + own_begin + tid));
    for (int64_t slot = 0; slot < own_count && slot < kCachedSlots; ++slot) {
      neighbor_cache[slot * kReduceBlock + tid] = static_cast<int32_t>(graph(slot, own_begin + tid));
    }
  }
  const SharedNeighbors<Global> own_neighbors{neighbor_cache + tid, Global{k.graph.neighbor, k.graph.num_nodes}};

  int64_t done = 0;
  bool stopped = false;  // every object stopped (read after M's barrier: the same in every block)
  while (done < s.count) {
    // The scalars before this iteration (written by the last M, or the caller's) and those the
    // last iteration started from, for its beta step.
    const CGScalars<S> now = (done & 1) ? odd : even, last = (done & 1) ? even : odd;
    int32_t* now_active = active_count + (done & 1);
    // M
    if (blockIdx.x == 0 && tid == 0) active_count[(done + 1) & 1] = 0;  // counted by the next M
    int64_t known = -1;
    BetaStep<S> step{};
    for (int64_t c = blockIdx.x; c < num_chunks; c += gridDim.x) {
      const int64_t b = plan.chunk_object[c];
      if (b != known) {  // consecutive chunks of a block mostly share their object
        if (done > 0) {
          step = beta_step(plan, s, last, b, status_after_alpha, sums_rr);
        } else {
          step = BetaStep<S>{now.status[b], S(0), 0, S(0), false};
        }
        known = b;
      }
      if (tid == 0 && c == plan.object_chunk[b]) {
        if (done > 0) write_scalars(s, now, b, step);
        if (step.status == kActive) atomicAdd(now_active, 1);
      }
      if (step.status != kActive) continue;
      const DirectionLoader<S> direction{s.p, s.r, step.beta, done == 0};
      double acc = 0.0;
      if (cached) {  // c is the block's own chunk
        if (own_begin + tid < plan.chunk_start[c + 1]) {
          acc = static_cast<double>(k.apply(own_begin + tid, own_count, own_neighbors, direction));
        }
      } else {
        for (int64_t i = plan.chunk_start[c] + tid; i < plan.chunk_start[c + 1]; i += kReduceBlock) {
          acc += static_cast<double>(k.apply(i, direction));
        }
      }
      const double total = block_total(acc);
      if (tid == 0) sums_pap[c] = total;
    }
    grid.sync();
    if (*reinterpret_cast<volatile int32_t*>(now_active) == 0) {
      stopped = true;
      break;
    }
    // U
    known = -1;
    S alpha = S(0), beta = S(0);
    int32_t status = kActive;
    for (int64_t c = blockIdx.x; c < num_chunks; c += gridDim.x) {
      const int64_t b = plan.chunk_object[c];
      if (now.status[b] != kActive) continue;
      if (b != known) {
        status = kActive;
        alpha = cg_alpha_step<S>(object_chunk_total(plan, b, sums_pap), now.rr[b], status);
        beta = done > 0 ? s.beta[b] : S(0);
        known = b;
      }
      if (tid == 0 && c == plan.object_chunk[b]) {
        s.alpha[b] = alpha;
        status_after_alpha[b] = status;
      }
      double acc = 0.0;
      for (int64_t j = plan.chunk_start[c] * d + tid; j < plan.chunk_start[c + 1] * d; j += kReduceBlock) {
        S pj = s.p[j];
        const S rj = s.r[j];
        if (done > 0) {  // the direction M read on the fly, stored now (also when alpha stops the object)
          pj = rj + beta * pj;
          s.p[j] = pj;
        }
        if (status != kActive) continue;
        s.x[j] += alpha * pj;
        const S r_new = rj - alpha * s.ap[j];
        s.r[j] = r_new;
        acc += static_cast<double>(r_new) * static_cast<double>(r_new);
      }
      if (status != kActive) continue;
      const double total = block_total(acc);
      if (tid == 0) sums_rr[c] = total;
    }
    grid.sync();
    ++done;
  }

  // D: the last iteration's beta step and direction (when the loop ended on the count; when it
  // stopped, M made that step and no object needs a direction).
  if (!stopped && done > 0) {
    const CGScalars<S> now = (done & 1) ? odd : even, last = (done & 1) ? even : odd;
    int64_t known = -1;
    BetaStep<S> step{};
    for (int64_t c = blockIdx.x; c < num_chunks; c += gridDim.x) {
      const int64_t b = plan.chunk_object[c];
      if (b != known) {
        step = beta_step(plan, s, last, b, status_after_alpha, sums_rr);
        known = b;
      }
      if (tid == 0 && c == plan.object_chunk[b]) write_scalars(s, now, b, step);
      if (step.status != kActive) continue;
      for (int64_t j = plan.chunk_start[c] * d + tid; j < plan.chunk_start[c + 1] * d; j += kReduceBlock) {
        s.p[j] = s.r[j] + step.beta * s.p[j];
      }
    }
  }

  if (done & 1) {  // the scalars ended in the other parity: back into the caller's buffers (each
                   // object's by the thread that wrote them)
    for (int64_t c = blockIdx.x; c < num_chunks; c += gridDim.x) {
      const int64_t b = plan.chunk_object[c];
      if (tid == 0 && c == plan.object_chunk[b]) {
        s.rr[b] = odd.rr[b];
        s.status[b] = odd.status[b];
        s.iterations[b] = odd.iterations[b];
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
