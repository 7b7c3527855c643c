// The CG reductions on the CPU, shared by the CG ops (cg_cpu.cpp) and the matvec kernels that
// end in the step length (chunk_alpha_cpu): chunks in parallel (at::parallel_for), then each
// object's chunk sums in chunk order, so the results do not depend on the thread count.
#pragma once

#include <ATen/Parallel.h>

#include <algorithm>
#include <cstdint>

#include "../cg.h"

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

}  // namespace tensormass
