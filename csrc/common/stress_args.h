// The stress form's inputs: checked on the host (StressArgs, from the ops' tensors) and read by its
// element kernels (StressInputs: an element's nodes, shape vectors, measure, Lame parameters,
// tangent plane and displacements). Shared by the stress family and the tangent on the node graph
// (node_graph/: stress_tangent_node_k).
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/Optional.h>

#include <cstdint>
#include <string>

#include "common/checks.h"
#include "common/dispatch.h"
#include "common/element_math.h"
#include "common/kernel_io.h"

namespace tensormass {

template <typename S, typename I>
struct StressInputs {
  const S* u;              // [V, D]
  const S* du;             // [V, D] (dforces only)
  const I* elements;       // [N, NN]
  const S* shape_vectors;  // [N, NN, D]
  const S* measure;        // [N]
  const S* lam;            // [N]
  const S* mu;             // [N]
  const S* projector;      // [N, D, D] (membranes only)
  const S* rest;           // [N, NN, D] rest element nodes (corotational QR recomputed per call; D = 3)
  const S* rotations;      // [N, D, D] element rotations (corotational; nullptr: QR frame from rest)

  // What every stress-form element kernel starts from: element e's node ids, shape vectors,
  // measure, Lame parameters, tangent plane (the projector of a membrane) and displacements.
  template <int NN, int D, bool M>
  TM_HD void load_element(int64_t e, I (&idx)[NN], S (&m)[NN][D], S& vol, S& lam_e, S& mu_e,
                          Plane<D, S, M>& plane, S (&u_e)[NN][D]) const {
    load_block<NN, I>(elements + e * NN, idx);
    load_matrix<NN, D, S>(shape_vectors + e * (NN * D), m);
    vol = ld(measure + e);
    lam_e = ld(lam + e);
    mu_e = ld(mu + e);
    if constexpr (M) load_matrix<D, D, S>(projector + e * (D * D), plane.p);
    gather_nodes<NN, D, S, I>(u, idx, u_e);
  }
};

// The stress-form inputs, checked. `du` is undefined for forces.
struct StressArgs {
  at::Tensor u, du, elements, shape_vectors, measure, lam, mu;
  c10::optional<at::Tensor> projector;
  int64_t model;
  at::Tensor rest;       // [N, n, 3] rest element nodes (corotational, QR recomputed per call)
  at::Tensor rotations;  // [N, d, d] element rotations (corotational: used instead of rest)
  int64_t num_elements, nodes_per_element, dim, num_nodes;
  at::ScalarType index_type;

  StressArgs(const at::Tensor& u_, const c10::optional<at::Tensor>& du_, const at::Tensor& elements_,
             const at::Tensor& shape_vectors_, const at::Tensor& measure_, const at::Tensor& lam_,
             const at::Tensor& mu_, const c10::optional<at::Tensor>& projector_, int64_t model_,
             const c10::optional<at::Tensor>& rest_, const c10::optional<at::Tensor>& rotations_)
      : u(u_), elements(elements_), shape_vectors(shape_vectors_), measure(measure_), lam(lam_), mu(mu_),
        projector(projector_), model(model_) {
    check_values(u, "u");
    num_nodes = u.size(0);
    dim = u.size(1);
    index_type = index_type_of(elements, "elements");
    TORCH_CHECK(elements.dim() == 2, "tensormass: elements must be [N, n], got shape ", shape_str(elements.sizes()));
    num_elements = elements.size(0);
    nodes_per_element = elements.size(1);
    check_index_tensor(elements, "elements", u, index_type, {num_elements, nodes_per_element});
    if (du_.has_value() && du_->defined()) {
      du = *du_;
      check_float_tensor(du, "du", u, u.sizes());
    }
    check_float_tensor(shape_vectors, "shape_vectors", u, {num_elements, nodes_per_element, dim});
    check_float_tensor(measure, "measure", u, {num_elements});
    check_float_tensor(lam, "lam", u, {num_elements});
    check_float_tensor(mu, "mu", u, {num_elements});
    dispatch_kind(nodes_per_element, dim, [](auto, auto) {});  // validates the kind
    dispatch_model(model, [](auto) {});
    const bool membrane = nodes_per_element - 1 < dim;
    const bool has_projector = projector.has_value() && projector->defined();
    TORCH_CHECK(has_projector == membrane, "tensormass: the projector must be given for membranes (triangles "
                "in 3-D) and only for them (nodes per element ", std::to_string(nodes_per_element), ", dimension ", std::to_string(dim), ")");
    if (has_projector) check_float_tensor(*projector, "projector", u, {num_elements, dim, dim});
    const bool has_rest = rest_.has_value() && rest_->defined();
    const bool has_rotations = rotations_.has_value() && rotations_->defined();
    if (model == kCorotational && has_rotations) {
      rotations = *rotations_;
      check_float_tensor(rotations, "rotations", u, {num_elements, dim, dim});
      if (has_rest) check_float_tensor(*rest_, "rest_elements", u, {num_elements, nodes_per_element, dim});
    } else if (model == kCorotational) {
      TORCH_CHECK(dim == 3, "tensormass: the corotational model without rotations recomputes SOFA's QR frame, "
                  "which needs 3-D elements (got dimension ", std::to_string(dim), "); pass rotations [N, d, d]");
      TORCH_CHECK(has_rest, "tensormass: the corotational model needs rotations [N, d, d] or rest_elements "
                  "[N, n, 3] (QR frame recomputed from them)");
      rest = *rest_;
      check_float_tensor(rest, "rest_elements", u, {num_elements, nodes_per_element, dim});
    } else {
      TORCH_CHECK(!has_rest, "tensormass: rest_elements is for the corotational model (model 2) only");
      TORCH_CHECK(!has_rotations, "tensormass: rotations is for the corotational model (model 2) only");
    }
  }

  template <typename S, typename I>
  StressInputs<S, I> inputs() const {
    StressInputs<S, I> in;
    in.u = u.data_ptr<S>();
    in.du = du.defined() ? du.data_ptr<S>() : nullptr;
    in.elements = elements.data_ptr<I>();
    in.shape_vectors = shape_vectors.data_ptr<S>();
    in.measure = measure.data_ptr<S>();
    in.lam = lam.data_ptr<S>();
    in.mu = mu.data_ptr<S>();
    in.projector = ptr_or_null<S>(projector);
    in.rest = rest.defined() ? rest.data_ptr<S>() : nullptr;
    in.rotations = rotations.defined() ? rotations.data_ptr<S>() : nullptr;
    return in;
  }
};

}  // namespace tensormass
