// The rigid correction's basis at a node (solver/rigid_modes.py), formed on the fly, written once
// for the multigrid family's transfers (multigrid/kernels.h) and the CG direction that adds the
// coarse part (cg/: cg_direction with a coarse term).
//
// At node i, Z'_i = N_i [I | -[a_i]x] (3 x 6), N_i = S^-1_i (block Jacobi's inverse scaling; 0 on
// a fixed node) or N_i = n_i I (a value a node: `scalar`; the free-node mask where the CG applies
// block Jacobi itself), a_i the node's lever arm about its body's centre; a body's six coarse
// unknowns are its translation t and rotation w. Reading N and a (12 values a node, 4 with a
// scalar N) where a stored Z' reads 18.
#pragma once

#include <cstdint>

#include "common/element_math.h"

namespace tensormass {

// out = N_i v (transpose: N_i^T v).
template <typename S>
TM_HD void rigid_node_apply(const S* node_inverse, bool scalar, int64_t i, const S (&v)[3], bool transpose,
                            S (&out)[3]) {
  if (scalar) {
    const S n = node_inverse[i];
    TM_UNROLL for (int k = 0; k < 3; ++k) out[k] = n * v[k];
    return;
  }
  const S* n = node_inverse + i * 9;
  TM_UNROLL for (int k = 0; k < 3; ++k) {
    out[k] = transpose ? n[k] * v[0] + n[3 + k] * v[1] + n[6 + k] * v[2]
                       : n[3 * k] * v[0] + n[3 * k + 1] * v[1] + n[3 * k + 2] * v[2];
  }
}

// A node's motion under its body's coarse unknowns, scaled: weight Z'_i c_b = weight N_i (t + w x
// a_i), c_b = coarse's six values of body node_body[i]. `coarse` nullptr: no coarse term.
template <typename S>
struct RigidMotion {
  const S* node_inverse;     // [V, 3, 3], or [V] (scalar)
  bool scalar;
  const S* arm;              // [V, 3]
  const int32_t* node_body;  // [V]
  const S* coarse;           // [B 6]: t, w a body
  S weight;

  TM_HD void at(int64_t i, S (&out)[3]) const {
    const S* c = coarse + static_cast<int64_t>(node_body[i]) * 6;
    const S* a = arm + i * 3;
    const S v[3] = {c[0] + c[4] * a[2] - c[5] * a[1], c[1] + c[5] * a[0] - c[3] * a[2],
                    c[2] + c[3] * a[1] - c[4] * a[0]};
    rigid_node_apply(node_inverse, scalar, i, v, false, out);
    TM_UNROLL for (int k = 0; k < 3; ++k) out[k] *= weight;
  }
};

}  // namespace tensormass
