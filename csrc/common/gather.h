// Kernel 2 of the paper's Algorithm 1 (common/kernel_io.h): each node's total, the sum of its used
// slots of the padded PartialForce [N_n, V, d] in slot order (sum_slots, GatherKernel), and its host
// side (run_gather). Shared by the fused force ops of the stress and tensor forms and the gather ops.
#pragma once

#include <ATen/core/Tensor.h>

#include <cstdint>

#include "common/dispatch.h"
#include "common/kernel_io.h"

namespace tensormass {

// Kernel 2's core: acc = sum of node i's used slots of PartialForce [N_n, V, D], in slot order
// (the fixed order that makes the result bitwise reproducible).
template <int D, typename S, typename I>
TM_HD void sum_slots(const S* partial, const I* incidences, int64_t num_nodes, int64_t i, S (&acc)[D]) {
  TM_UNROLL for (int a = 0; a < D; ++a) acc[a] = S(0);
  const int64_t count = static_cast<int64_t>(ld(incidences + i));
  const S* q = partial + i * D;
  const int64_t stride = num_nodes * D;
  for (int64_t s = 0; s < count; ++s) {
    TM_UNROLL for (int a = 0; a < D; ++a) acc[a] += ld(q + a);
    q += stride;
  }
}

// TotalForce[i] = sum_{s < incidences[i]} PartialForce[s][i] (+ node_term[i]).
template <int D, typename S, typename I>
struct GatherKernel {
  const S* partial;     // [N_n, V, D]
  const I* incidences;  // [V]
  const S* node_term;   // [V, D] added as is, or nullptr
  S* out;               // [V, D]
  int64_t num_nodes;

  TM_HD void operator()(int64_t i) const {
    S acc[D];
    sum_slots<D, S, I>(partial, incidences, num_nodes, i, acc);
    if (node_term != nullptr) {
      TM_UNROLL for (int a = 0; a < D; ++a) acc[a] += ld(node_term + i * D + a);
    }
    TM_UNROLL for (int a = 0; a < D; ++a) out[i * D + a] = acc[a];
  }
};

// Kernel 2: out [V, d] = sum of the used slots of partial [N_n, V, d] (+ node_term [V, d]).
template <class L>
void run_gather(const at::Tensor& partial, const at::Tensor& incidences, const at::Tensor& node_term,
                at::Tensor& out) {
  const int64_t num_nodes = out.size(0);
  dispatch_scalar(out.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(incidences.scalar_type(), [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_dim(out.size(1), [&](auto d_c) {
        constexpr int D = decltype(d_c)::value;
        GatherKernel<D, S, I> k;
        k.partial = partial.numel() ? partial.data_ptr<S>() : nullptr;
        k.incidences = incidences.data_ptr<I>();
        k.node_term = node_term.defined() ? node_term.data_ptr<S>() : nullptr;
        k.out = out.data_ptr<S>();
        k.num_nodes = num_nodes;
        L::run(num_nodes, k, L::kNodeBlock);
      });
    });
  });
}

}  // namespace tensormass
