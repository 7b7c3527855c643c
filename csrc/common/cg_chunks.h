// The CG reductions on the CPU, shared by the CG ops (cg/cpu.cpp), the matvec kernels that end in
// the step length (chunk_alpha_cpu) and the CPU's whole solve (cg_run_cpu, solve/cpu.cpp): chunks
// in parallel (at::parallel_for), then each object's chunk sums in chunk order, so the results do
// not depend on the thread count.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>

#include "common/cg.h"

namespace tensormass {

template <typename S>
double chunk_dot(const S* a, const S* b, int64_t begin, int64_t end) {
  double acc = 0.0;
  for (int64_t j = begin; j < end; ++j) acc += static_cast<double>(a[j]) * static_cast<double>(b[j]);
  return acc;
}

inline double object_sum(const double* scratch, const int64_t* object_chunk, int64_t b) {
  double acc = 0.0;
  for (int64_t c = object_chunk[b]; c < object_chunk[b + 1]; ++c) acc += scratch[c];
  return acc;
}

// Chunks per task: at least ~32k values each, so that small systems run on the calling thread
// (an OpenMP region costs more than a CG update of a few thousand values).
inline int64_t chunk_grain(const CGPlan& plan, int64_t values_per_node) {
  const int64_t values = plan.num_nodes * values_per_node;
  const int64_t per_chunk = std::max<int64_t>(1, values / std::max<int64_t>(1, plan.num_chunks));
  return std::max<int64_t>(1, (int64_t{1} << 15) / per_chunk);
}

template <class F>
void for_each_chunk(const CGPlan& plan, int64_t values_per_node, const int32_t* status, const F& f) {
  at::parallel_for(0, plan.num_chunks, chunk_grain(plan, values_per_node), [&](int64_t begin, int64_t end) {
    for (int64_t c = begin; c < end; ++c) {
      if (status[plan.chunk_object[c]] == kActive) f(c, plan.chunk_start[c], plan.chunk_start[c + 1]);
    }
  });
}

// After the per-chunk sums of p . Ap: each active object's step length (cg_alpha's scalar step).
template <typename S>
void alpha_from_chunk_sums(const CGPlan& plan, const double* sums, const S* rr, int32_t* status, S* alpha) {
  for (int64_t b = 0; b < plan.num_objects; ++b) {
    if (status[b] != kActive) continue;
    alpha[b] = cg_alpha_step<S>(object_sum(sums, plan.object_chunk, b), rr[b], status[b]);
  }
}

// A CG matvec that ends in the step length: node kernel k (k.apply(i) writes Ap_i and returns
// p_i . Ap_i) over the nodes of the active objects' chunks, summed in node order per chunk (as
// cg_alpha sums p_dot_ap), then alpha.
// A node of a matvec costs about what 16 values of a CG update do (a dozen slots of a 3x3 product):
// weighted so, the grain gives tasks of ~2k nodes, as the plain node kernels (kNodeBlock).
constexpr int64_t kMatvecNodeWeight = 16;

template <class K, typename S>
void chunk_alpha_cpu(const CGPlan& plan, const K& k, const S* rr, int32_t* status, S* alpha, double* scratch) {
  for_each_chunk(plan, kMatvecNodeWeight, status, [&](int64_t c, int64_t begin, int64_t end) {
    double acc = 0.0;
    for (int64_t i = begin; i < end; ++i) acc += static_cast<double>(k.apply(i));
    scratch[c] = acc;
  });
  alpha_from_chunk_sums(plan, scratch, rr, status, alpha);
}

// cg_update: x += alpha p, r -= alpha Ap on the active objects' chunks, then each active object's
// r.r, convergence, iteration cap and beta.
template <typename S>
void update_cpu(const CGPlan& plan, int64_t d, S* x, S* r, const S* p, const S* ap, const S* alpha,
                const S* threshold, int64_t max_iter, S* rr, int32_t* status, S* beta, int32_t* iterations,
                double* sums) {
  for_each_chunk(plan, d, status, [&](int64_t c, int64_t begin, int64_t end) {
    const S a = alpha[plan.chunk_object[c]];
    for (int64_t j = begin * d; j < end * d; ++j) {
      x[j] += a * p[j];
      r[j] -= a * ap[j];
    }
    sums[c] = chunk_dot(r, r, begin * d, end * d);
  });
  for (int64_t b = 0; b < plan.num_objects; ++b) {
    if (status[b] != kActive) continue;
    beta[b] = cg_beta_step<S>(object_sum(sums, plan.object_chunk, b), rr[b], threshold[b], max_iter, status[b],
                              iterations[b]);
  }
}

// cg_update with inverse blocks (BlockUpdate): node by node, then each active object's r.z,
// convergence, iteration cap and beta as update_cpu's.
template <typename S>
void block_update_cpu(const CGPlan& plan, const BlockUpdate<S>& update, const S* alpha, const S* threshold,
                      int64_t max_iter, S* rr, int32_t* status, S* beta, int32_t* iterations, double* sums) {
  for_each_chunk(plan, update.d * (update.d + 2), status, [&](int64_t c, int64_t begin, int64_t end) {
    const S a = alpha[plan.chunk_object[c]];
    double acc = 0.0;
    for (int64_t i = begin; i < end; ++i) acc += update.apply(i, a);
    sums[c] = acc;
  });
  for (int64_t b = 0; b < plan.num_objects; ++b) {
    if (status[b] != kActive) continue;
    beta[b] = cg_beta_step<S>(object_sum(sums, plan.object_chunk, b), rr[b], threshold[b], max_iter, status[b],
                              iterations[b]);
  }
}

// cg_direction: p = r + beta p on the active objects' chunks; with a coarse term, p = r + weight Z' c
// + beta p (coarse_direction_node).
template <typename S>
void direction_cpu(const CGPlan& plan, int64_t d, S* p, const S* r, const S* beta, const int32_t* status,
                   const RigidMotion<S>* coarse = nullptr) {
  for_each_chunk(plan, d, status, [&](int64_t c, int64_t begin, int64_t end) {
    const S bt = beta[plan.chunk_object[c]];
    if (coarse != nullptr) {  // p = z + weight Z' y + beta p (d = 3)
      for (int64_t i = begin; i < end; ++i) coarse_direction_node(i, r, bt, p, *coarse);
      return;
    }
    for (int64_t j = begin * d; j < end * d; ++j) p[j] = r[j] + bt * p[j];
  });
}

// cg_dot: per-object a . b of [V, d] fields into out [B] (every chunk, active or not).
template <typename S>
void object_dots_cpu(const CGPlan& plan, int64_t d, const S* a, const S* b, S* out, double* sums) {
  at::parallel_for(0, plan.num_chunks, chunk_grain(plan, d), [&](int64_t begin, int64_t end) {
    for (int64_t c = begin; c < end; ++c) sums[c] = chunk_dot(a, b, plan.chunk_start[c] * d, plan.chunk_start[c + 1] * d);
  });
  for (int64_t o = 0; o < plan.num_objects; ++o) out[o] = static_cast<S>(object_sum(sums, plan.object_chunk, o));
}

// A whole CG solve (hooke_node_cg on the CPU): the start from x0 = 0 when s.rhs is given, then up
// to s.count iterations, each the matvec ending in alpha (node kernel k), cg_update and
// cg_direction, stopping early once no object is active. The same functions as the CG ops, in
// the same order: bitwise the solve CGSolver runs op by op.
template <class K, typename S>
void cg_run_cpu(const CGPlan& plan, const K& k, const CGRun<S>& s) {
  const int64_t d = s.d;
  if (s.rhs != nullptr) {
    at::parallel_for(0, plan.num_nodes, 2048, [&](int64_t begin, int64_t end) {
      for (int64_t j = begin * d; j < end * d; ++j) {
        const S b = s.free != nullptr ? s.rhs[j] * s.free[j / d] : s.rhs[j];
        s.x[j] = S(0);
        s.r[j] = b;
        s.p[j] = b;
      }
    });
    object_dots_cpu(plan, d, s.r, s.r, s.rhs_sq, s.sums);
    for (int64_t b = 0; b < plan.num_objects; ++b) {
      s.rr[b] = s.rhs_sq[b];
      s.threshold[b] = s.rhs_sq[b] * s.tol_sq;
      s.status[b] = cg_start_status(s.rr[b], s.threshold[b], s.max_iter);
      s.iterations[b] = 0;
      s.alpha[b] = S(0);
      s.beta[b] = S(0);
    }
  }
  for (int64_t t = 0; t < s.count; ++t) {
    bool any_active = false;
    for (int64_t b = 0; b < plan.num_objects && !any_active; ++b) any_active = s.status[b] == kActive;
    if (!any_active) break;
    chunk_alpha_cpu<K, S>(plan, k, s.rr, s.status, s.alpha, s.sums);
    update_cpu<S>(plan, d, s.x, s.r, s.p, s.ap, s.alpha, s.threshold, s.max_iter, s.rr, s.status, s.beta,
                  s.iterations, s.sums);
    direction_cpu<S>(plan, d, s.p, s.r, s.beta, s.status);
  }
}

}  // namespace tensormass
