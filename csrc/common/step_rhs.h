// Implicit Euler's right-hand side of the hooke tensor form, per node: the displacement it is taken
// at (step_displacement), the contact planes' penalties (PenaltyPlanes), a node's own terms
// (step_rhs_node), and the host-side check of the planes (StepPlanes). Shared by the node graph's
// hooke_node_step_rhs (node_graph/: NodeHookeStepRhsKernel) and the solve that computes its
// right-hand side itself (solve/: hooke_node_steps, cg_pipelined.cuh).
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/Optional.h>

#include <cstdint>
#include <string>

#include "common/checks.h"
#include "common/element_math.h"
#include "common/kernel_io.h"

namespace tensormass {

// The displacement an implicit Euler step's right-hand side is taken at, w = (x - rest) + c v
// (one expression for every kernel that forms it: their right-hand sides agree bitwise).
template <typename S>
TM_HD S step_displacement(S x, S rest, S v, S c) {
  return (x - rest) + c * v;
}

// step_displacement read through the pointer into x that the node graph computes (q = x + offset).
template <typename S>
struct StepDisplacementLoader {
  const S* x;
  const S* rest;
  const S* v;
  S c;
  TM_HD S operator()(const S* q) const {
    const int64_t o = q - x;
    return step_displacement(ld(x + o), ld(rest + o), ld(v + o), c);
  }
};

// Penalty planes n.x >= offset (contact.Planes): P planes of normals [P, 3], offsets [P] and
// stiffness [P]; 3-D only.
template <typename S>
struct PenaltyPlanes {
  const S* normals;
  const S* offsets;
  const S* stiffness;
  int64_t count;

  // The force on a node at x (sum of k (offset - n.x) n over the planes it is below) and its
  // stiffness -(df/dx) (sum of k n n^T over those planes).
  TM_HD void linearize(const S (&x)[3], S (&force)[3], S (&k)[3][3]) const {
    TM_UNROLL for (int a = 0; a < 3; ++a) {
      force[a] = S(0);
      TM_UNROLL for (int b = 0; b < 3; ++b) k[a][b] = S(0);
    }
    for (int64_t q = 0; q < count; ++q) {
      const S n[3] = {ld(normals + 3 * q), ld(normals + 3 * q + 1), ld(normals + 3 * q + 2)};
      const S depth = ld(offsets + q) - (x[0] * n[0] + x[1] * n[1] + x[2] * n[2]);
      if (!(depth > S(0))) continue;
      const S kq = ld(stiffness + q);
      TM_UNROLL for (int a = 0; a < 3; ++a) {
        force[a] += depth * kq * n[a];
        TM_UNROLL for (int b = 0; b < 3; ++b) k[a][b] += kq * n[a] * n[b];
      }
    }
  }
};

// A node's own terms of implicit Euler's right-hand side, given its elastic force sum `total`
// over the node graph (the force of w = (x - rest) + c_w v) and damping = r_M m_i:
//   rhs = h (total + external + contact(x) - Kc (c_w v) - damping v)
// and the contact stiffness Kc at x (HAS_PLANES, 3-D; `total` is updated). Shared by the
// right-hand side's kernel and the solve that computes it itself (solve/cg_pipelined.cuh).
template <int D, typename S, bool HAS_PLANES>
TM_HD void step_rhs_node(const PenaltyPlanes<S>& planes, S h, S c_w, S damping, const S (&x)[D], const S (&v)[D],
                         const S (&external)[D], S (&total)[D], S (&k_contact)[D][D], S (&rhs)[D]) {
  TM_UNROLL for (int a = 0; a < D; ++a) total[a] += external[a];
  if constexpr (HAS_PLANES && D == 3) {
    S force[3];
    planes.linearize(x, force, k_contact);
    TM_UNROLL for (int a = 0; a < 3; ++a) {
      S kw = S(0);
      TM_UNROLL for (int b = 0; b < 3; ++b) kw += k_contact[a][b] * (c_w * v[b]);
      total[a] += force[a] - kw;
    }
  }
  TM_UNROLL for (int a = 0; a < D; ++a) rhs[a] = h * (total[a] - damping * v[a]);
}

// The contact planes of a step's right-hand side (normals [P, 3], offsets [P], stiffness [P];
// 3-D) and the contact stiffness it writes (node_stiffness [V, 3, 3]), checked against x [V, d]:
// all of them or none.
struct StepPlanes {
  bool given = false;
  at::Tensor normals, offsets, stiffness, node_stiffness;

  StepPlanes(const at::Tensor& x, const c10::optional<at::Tensor>& plane_normals,
             const c10::optional<at::Tensor>& plane_offsets, const c10::optional<at::Tensor>& plane_stiffness,
             const c10::optional<at::Tensor>& node_stiffness_out) {
    given = plane_normals.has_value() && plane_normals->defined();
    if (!given) {
      TORCH_CHECK(!(plane_offsets.has_value() && plane_offsets->defined()) &&
                      !(plane_stiffness.has_value() && plane_stiffness->defined()),
                  "tensormass: plane_offsets and plane_stiffness need plane_normals");
      return;
    }
    TORCH_CHECK(x.size(1) == 3, "tensormass: contact planes need 3-D positions, got d = ", std::to_string(x.size(1)));
    normals = *plane_normals;
    TORCH_CHECK(normals.dim() == 2, "tensormass: plane_normals must be [P, 3], got shape ", shape_str(normals.sizes()));
    const int64_t count = normals.size(0);
    check_node_tensor(normals, "plane_normals", x, {count, 3}, "x");
    TORCH_CHECK(plane_offsets.has_value() && plane_offsets->defined() && plane_stiffness.has_value() &&
                    plane_stiffness->defined() && node_stiffness_out.has_value() && node_stiffness_out->defined(),
                "tensormass: plane_normals needs plane_offsets, plane_stiffness and node_stiffness");
    offsets = *plane_offsets;
    stiffness = *plane_stiffness;
    node_stiffness = *node_stiffness_out;
    check_node_tensor(offsets, "plane_offsets", x, {count}, "x");
    check_node_tensor(stiffness, "plane_stiffness", x, {count}, "x");
    check_node_tensor(node_stiffness, "node_stiffness", x, {x.size(0), 3, 3}, "x");
  }
};

}  // namespace tensormass
