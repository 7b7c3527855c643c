// Registration of the implementations of one backend (launcher L) under TORCH_LIBRARY_IMPL.
// The schemas are defined once, in ops.cpp. Split in three groups so that the CPU build can
// compile them in parallel translation units.
#pragma once

#include <torch/library.h>

#include "ops_impl.h"

namespace tensormass {

template <class L>
void register_stress_ops(torch::Library& m) {
  m.impl("stress_element_forces", &stress_element_forces<L>);
  m.impl("stress_element_dforces", &stress_element_dforces<L>);
  m.impl("stress_partial_forces", &stress_partial_forces<L>);
  m.impl("stress_partial_dforces", &stress_partial_dforces<L>);
  m.impl("stress_forces", &stress_forces<L>);
  m.impl("stress_dforces", &stress_dforces<L>);
  m.impl("corotational_rotations", &corotational_rotations<L>);
  m.impl("stress_tangent_node_k", &stress_tangent_node_k<L>);
}

template <class L>
void register_tensor_ops(torch::Library& m) {
  m.impl("tensor_hooke_element_forces", &tensor_hooke_element_forces<L>);
  m.impl("tensor_hooke_partial_forces", &tensor_hooke_partial_forces<L>);
  m.impl("tensor_hooke_forces", &tensor_hooke_forces<L>);
  m.impl("tensor_stvk_element_forces", &tensor_stvk_element_forces<L>);
  m.impl("tensor_stvk_element_dforces", &tensor_stvk_element_dforces<L>);
  m.impl("tensor_stvk_partial_forces", &tensor_stvk_partial_forces<L>);
  m.impl("tensor_stvk_partial_dforces", &tensor_stvk_partial_dforces<L>);
  m.impl("tensor_stvk_forces", &tensor_stvk_forces<L>);
  m.impl("tensor_stvk_dforces", &tensor_stvk_dforces<L>);
}

template <class L>
void register_gather_ops(torch::Library& m) {
  m.impl("gather_partial", &gather_partial<L>);
  m.impl("node_gather", &node_gather<L>);
  m.impl("gather_system", &gather_system<L>);
  m.impl("hooke_node_system", &hooke_node_system<L>);
  m.impl("gather_system_alpha", &gather_system_alpha<L>);
  m.impl("hooke_node_system_alpha", &hooke_node_system_alpha<L>);
  m.impl("hooke_node_cg", &hooke_node_cg<L>);
  m.impl("hooke_node_solve", &hooke_node_solve<L>);
  m.impl("hooke_node_solve_step", &hooke_node_solve_step<L>);
  m.impl("hooke_node_steps", &hooke_node_steps<L>);
  m.impl("hooke_node_step_rhs", &hooke_node_step_rhs<L>);
}

}  // namespace tensormass
