// The end of a CG matvec in the step length (alpha_launch), shared by gather_system_alpha (gather/)
// and hooke_node_system_alpha (node_graph/).
//
// The CG iteration's matvec fused with cg_alpha (one kernel fewer per iteration): Ap written into
// `ap` [V, d] in place, then per object alpha = rr / sum p . Ap (or the object stops: breakdown /
// non-finite), exactly as cg_alpha over the plan's chunks; objects that are not active are
// skipped (their Ap is not computed). Arguments: those of gather_system / hooke_node_system, then
// ap and cg_alpha's (chunk plan, rr, status, alpha, scratch, counter).
#pragma once

#include <ATen/core/Tensor.h>

#include <cstdint>
#include <type_traits>

#include "common/cg.h"
#include "common/cg_checks.h"

namespace tensormass {

template <class L>
auto alpha_launch(const at::Tensor& like, const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                  const at::Tensor& object_chunk, const at::Tensor& rr, at::Tensor& status, at::Tensor& alpha,
                  at::Tensor& scratch, at::Tensor& counter) {
  const CGPlan plan = cg_plan(chunk_start, chunk_object, object_chunk, like, like.size(0));
  cg_check_scalars(rr, "rr", like, plan.num_objects);
  cg_check_scalars(alpha, "alpha", like, plan.num_objects);
  cg_check_state(status, "status", like, plan.num_objects);
  cg_check(scratch, "scratch", like, at::kDouble, {plan.num_chunks});
  cg_check_state(counter, "counter", like, plan.num_objects);
  TORCH_CHECK(plan.num_chunks == 0 || like.size(0) > 0, "tensormass: a chunk plan over no nodes");
  return [=, &rr, &status, &alpha, &scratch, &counter](const auto& k, int64_t) {
    using S = typename std::decay_t<decltype(k)>::Scalar;
    L::run_alpha(plan, k, rr.data_ptr<S>(), status.data_ptr<int32_t>(), alpha.data_ptr<S>(),
                 scratch.data_ptr<double>(), counter.data_ptr<int32_t>());
  };
}

}  // namespace tensormass
