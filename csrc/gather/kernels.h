// The gather family's per-item kernels (kernel 2 itself, GatherKernel, is common/gather.h): kernel 2
// with the implicit-Euler system epilogue (SystemGatherKernel: the CG matvec from the padded partial
// force differentials) and the scatter of compact partial forces into the padded layout
// (ScatterKernel).
#pragma once

#include <cstdint>

#include "common/gather.h"
#include "common/kernel_io.h"
#include "common/system_epilogue.h"

namespace tensormass {

// Kernel 2 with the system epilogue (the CG matvec of A = c_M M - c_K K, two kernels):
// (K p)_i = sum_{s < incidences[i]} PartialForce[s][i], where PartialForce holds the partial
// force differentials (dF/du) p of kernel 1.
template <int D, typename S, typename I, bool HAS_FREE, bool HAS_NODE_K, bool HAS_ADD = false>
struct SystemGatherKernel {
  using Scalar = S;
  using Index = I;
  const S* partial;         // [N_n, V, D]
  const I* incidences;      // [V]
  const S* p;               // [V, D]
  int64_t num_nodes;
  SystemEpilogue<D, S, HAS_FREE, HAS_NODE_K, HAS_ADD> epilogue;

  // Ap_i and p_i . Ap_i (returned): the CG step-length kernels call this (cg_reduce.cuh).
  TM_HD S apply(int64_t i) const {
    S acc[D];
    sum_slots<D, S, I>(partial, incidences, num_nodes, i, acc);
    S pv[D];
    TM_UNROLL for (int a = 0; a < D; ++a) pv[a] = ld(p + i * D + a);
    return epilogue(i, pv, acc);
  }
  TM_HD void operator()(int64_t i) const { apply(i); }
};

// Scatter compact partial forces [N, NN, D] into the padded buffer (the write of kernel 1 for
// partial forces computed elsewhere, e.g. by the reference or by the element-level ops).
template <int NN, int D, typename S, typename I>
struct ScatterKernel {
  const S* partial;  // [N, NN, D]
  const I* index;    // [N, NN]
  Writer<NN, D, S, I, true> write;

  TM_HD void operator()(int64_t e) const {
    I idx[NN];
    load_block<NN, I>(index + e * NN, idx);
    S f[NN][D];
    load_matrix<NN, D, S>(partial + e * (NN * D), f);
    write(e, idx, f);
  }
};

}  // namespace tensormass
