// Host side of every op, written once for the CPU and CUDA: input checks, allocation and
// compile-time dispatch (element kind, model, scalar type, index type) onto the per-item
// functors of kernels.h. The backend is a template parameter `L` (a "launcher") that runs a
// functor over n items: cpu/ops_cpu.cpp (at::parallel_for) and cuda/ops_cuda.cu (one thread
// per item, on the current stream) instantiate these functions and register them.
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/MemoryOverlap.h>
#include <ATen/ops/empty.h>
#include <c10/util/Optional.h>

#include <cstdint>
#include <string>
#include <tuple>
#include <type_traits>

#include "cg.h"
#include "kernels.h"

namespace tensormass {

template <int V>
using IC = std::integral_constant<int, V>;

// ------------------------------------------------------------------ checks

// Error messages pass only strings to TORCH_CHECK (std::to_string for numbers, these helpers
// for shapes, dtypes and devices): on the GPU machine (torch 2.11, CUDA build) every check that
// streamed an integer (directly or inside sizes()) crashed the process with SIGSEGV instead of
// raising, while checks whose message held only strings raised cleanly. Integer formatting
// through an ostream there goes through locale facets that did not survive; to_string does not.
inline const char* dtype_str(at::ScalarType t) { return c10::toString(t); }

inline std::string shape_str(at::IntArrayRef shape) {
  std::string out = "[";
  for (size_t i = 0; i < shape.size(); ++i) {
    if (i) out += ", ";
    out += std::to_string(shape[i]);
  }
  return out + "]";
}

inline void check_float_tensor(const at::Tensor& t, const char* name, const at::Tensor& like,
                               at::IntArrayRef shape) {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.device() == like.device(), "tensormass: ", name, " is on ", t.device().str(), " but u is on ",
              like.device().str());
  TORCH_CHECK(t.scalar_type() == like.scalar_type(), "tensormass: ", name, " is ", dtype_str(t.scalar_type()),
              " but u is ", dtype_str(like.scalar_type()), " (all floating inputs must have one dtype)");
  TORCH_CHECK(t.sizes() == shape, "tensormass: ", name, " has shape ", shape_str(t.sizes()), "; expected ", shape_str(shape));
  TORCH_CHECK(t.is_contiguous(), "tensormass: ", name, " must be contiguous (call .contiguous())");
}

inline void check_index_tensor(const at::Tensor& t, const char* name, const at::Tensor& like,
                               at::ScalarType index_type, at::IntArrayRef shape, const char* like_name = "u") {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.device() == like.device(), "tensormass: ", name, " is on ", t.device().str(), " but ", like_name,
              " is on ", like.device().str());
  TORCH_CHECK(t.scalar_type() == index_type, "tensormass: ", name, " is ", dtype_str(t.scalar_type()), "; expected ",
              dtype_str(index_type), " (index tensors must all be int32 or all int64)");
  TORCH_CHECK(t.sizes() == shape, "tensormass: ", name, " has shape ", shape_str(t.sizes()), "; expected ", shape_str(shape));
  TORCH_CHECK(t.is_contiguous(), "tensormass: ", name, " must be contiguous (call .contiguous())");
}

inline void check_values(const at::Tensor& u, const char* name) {
  TORCH_CHECK(u.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(u.dim() == 2, "tensormass: ", name, " must be [V, d], got shape ", shape_str(u.sizes()));
  TORCH_CHECK(u.scalar_type() == at::kFloat || u.scalar_type() == at::kDouble, "tensormass: ", name,
              " must be float32 or float64, got ", dtype_str(u.scalar_type()));
  TORCH_CHECK(u.is_contiguous(), "tensormass: ", name, " must be contiguous (call .contiguous())");
}

inline at::ScalarType index_type_of(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.scalar_type() == at::kLong || t.scalar_type() == at::kInt, "tensormass: ", name,
              " must be int64 or int32, got ", dtype_str(t.scalar_type()));
  return t.scalar_type();
}

// ------------------------------------------------------------------ compile-time dispatch

template <class F>
void dispatch_scalar(at::ScalarType t, F&& f) {
  if (t == at::kDouble) {
    f(double{});
  } else if (t == at::kFloat) {
    f(float{});
  } else {
    TORCH_CHECK(false, "tensormass: unsupported dtype ", dtype_str(t), " (float32 or float64)");
  }
}

template <class F>
void dispatch_index(at::ScalarType t, F&& f) {
  if (t == at::kLong) {
    f(int64_t{});
  } else if (t == at::kInt) {
    f(int32_t{});
  } else {
    TORCH_CHECK(false, "tensormass: unsupported index dtype ", dtype_str(t), " (int32 or int64)");
  }
}

template <class F>
void dispatch_model(int64_t model, F&& f) {
  if (model == kHooke) {
    f(IC<kHooke>{});
  } else if (model == kStvk) {
    f(IC<kStvk>{});
  } else if (model == kCorotational) {
    f(IC<kCorotational>{});
  } else if (model == kStvkDefinite) {
    f(IC<kStvkDefinite>{});
  } else {
    TORCH_CHECK(false, "tensormass: unknown model id ", std::to_string(model),
                " (0 = hooke, 1 = stvk, 2 = corotational, 3 = stvk with a definite tangent)");
  }
}

// Element kinds: (nodes per element, dimension) = (4, 3) tetrahedra, (3, 2) planar triangles,
// (3, 3) membranes.
template <class F>
void dispatch_kind(int64_t nn, int64_t d, F&& f) {
  if (nn == 4 && d == 3) {
    f(IC<4>{}, IC<3>{});
  } else if (nn == 3 && d == 2) {
    f(IC<3>{}, IC<2>{});
  } else if (nn == 3 && d == 3) {
    f(IC<3>{}, IC<3>{});
  } else {
    TORCH_CHECK(false, "tensormass: unsupported element kind: ", std::to_string(nn), " nodes per element in dimension ", std::to_string(d),
                " (tetrahedra in 3-D, triangles in 2-D or 3-D)");
  }
}

template <class F>
void dispatch_dim(int64_t d, F&& f) {
  if (d == 3) {
    f(IC<3>{});
  } else if (d == 2) {
    f(IC<2>{});
  } else {
    TORCH_CHECK(false, "tensormass: unsupported dimension ", std::to_string(d), " (2 or 3)");
  }
}

template <class F>
void dispatch_bool(bool b, F&& f) {
  if (b) {
    f(std::true_type{});
  } else {
    f(std::false_type{});
  }
}

template <typename T>
const T* ptr_or_null(const c10::optional<at::Tensor>& t) {
  return (t.has_value() && t->defined()) ? t->data_ptr<T>() : nullptr;
}

// ------------------------------------------------------------------ argument bundles

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

inline void check_plan(const at::Tensor& u, const at::Tensor& force_index, int64_t num_slots,
                       at::ScalarType index_type, at::IntArrayRef items_shape) {
  check_index_tensor(force_index, "force_index", u, index_type, items_shape);
  TORCH_CHECK(num_slots >= 0, "tensormass: num_slots must be >= 0, got ", std::to_string(num_slots));
  TORCH_CHECK(items_shape[0] == 0 || num_slots > 0, "tensormass: num_slots is 0 but there are items");
}

inline void check_incidences(const at::Tensor& u, const at::Tensor& incidences, at::ScalarType index_type) {
  check_index_tensor(incidences, "incidences", u, index_type, {u.size(0)});
}

// ------------------------------------------------------------------ kernel 1 launchers

// Padded writers also need the slots and V.
template <int NN, int D, typename S, typename I>
void set_padded(Writer<NN, D, S, I, false>&, const at::Tensor&, int64_t) {}

template <int NN, int D, typename S, typename I>
void set_padded(Writer<NN, D, S, I, true>& w, const at::Tensor& force_index, int64_t num_nodes) {
  w.force_index = force_index.data_ptr<I>();
  w.num_nodes = num_nodes;
}

// One instantiation of kernel 1 of the stress form.
template <class L, int MODEL, bool DFORCE, int NN, int D, typename S, typename I>
void launch_stress_kernel1(const StressArgs& a, bool padded, const at::Tensor& force_index, at::Tensor& out) {
  dispatch_bool(padded, [&](auto padded_c) {
    constexpr bool PADDED = decltype(padded_c)::value;
    StressElementKernel<MODEL, DFORCE, NN, D, S, I, PADDED> k;
    k.in = a.template inputs<S, I>();
    k.write.out = out.template data_ptr<S>();
    set_padded(k.write, force_index, a.num_nodes);
    L::run(a.num_elements, k, L::kElementBlock);
  });
}

// Runs kernel 1 of the stress form into `out`: compact [N, n, d] (force_index undefined) or
// padded [N_n, V, d].
template <class L, bool DFORCE>
void run_stress_kernel1(const StressArgs& a, const at::Tensor& force_index, at::Tensor& out) {
  const bool padded = force_index.defined();
  dispatch_scalar(a.u.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(a.index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_kind(a.nodes_per_element, a.dim, [&](auto nn_c, auto d_c) {
        constexpr int NN = decltype(nn_c)::value;
        constexpr int D = decltype(d_c)::value;
        dispatch_model(a.model, [&](auto model_c) {
          constexpr int MODEL = decltype(model_c)::value;
          launch_stress_kernel1<L, MODEL, DFORCE, NN, D, S, I>(a, padded, force_index, out);
        });
      });
    });
  });
}

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

// ------------------------------------------------------------------ stress-form ops

template <class L>
at::Tensor stress_element_forces(const at::Tensor& u, const at::Tensor& elements, const at::Tensor& shape_vectors,
                                 const at::Tensor& measure, const at::Tensor& lam, const at::Tensor& mu,
                                 const c10::optional<at::Tensor>& projector, int64_t model,
                                 const c10::optional<at::Tensor>& rest_elements,
                                 const c10::optional<at::Tensor>& rotations) {
  StressArgs a(u, c10::nullopt, elements, shape_vectors, measure, lam, mu, projector, model, rest_elements, rotations);
  typename L::Guard guard(u.device());
  at::Tensor out = at::empty({a.num_elements, a.nodes_per_element, a.dim}, u.options());
  run_stress_kernel1<L, false>(a, at::Tensor(), out);
  return out;
}

template <class L>
at::Tensor stress_element_dforces(const at::Tensor& u, const at::Tensor& du, const at::Tensor& elements,
                                  const at::Tensor& shape_vectors, const at::Tensor& measure, const at::Tensor& lam,
                                  const at::Tensor& mu, const c10::optional<at::Tensor>& projector, int64_t model,
                                 const c10::optional<at::Tensor>& rest_elements,
                                 const c10::optional<at::Tensor>& rotations) {
  StressArgs a(u, du, elements, shape_vectors, measure, lam, mu, projector, model, rest_elements, rotations);
  typename L::Guard guard(u.device());
  at::Tensor out = at::empty({a.num_elements, a.nodes_per_element, a.dim}, u.options());
  run_stress_kernel1<L, true>(a, at::Tensor(), out);
  return out;
}

template <class L, bool DFORCE>
at::Tensor stress_partial_impl(const StressArgs& a, const at::Tensor& force_index, int64_t num_slots) {
  check_plan(a.u, force_index, num_slots, a.index_type, {a.num_elements, a.nodes_per_element});
  typename L::Guard guard(a.u.device());
  // Unused slots are left uninitialised: kernel 2 never reads them.
  at::Tensor partial = at::empty({num_slots, a.num_nodes, a.dim}, a.u.options());
  run_stress_kernel1<L, DFORCE>(a, force_index, partial);
  return partial;
}

template <class L>
at::Tensor stress_partial_forces(const at::Tensor& u, const at::Tensor& elements, const at::Tensor& force_index,
                                 int64_t num_slots, const at::Tensor& shape_vectors, const at::Tensor& measure,
                                 const at::Tensor& lam, const at::Tensor& mu,
                                 const c10::optional<at::Tensor>& projector, int64_t model,
                                 const c10::optional<at::Tensor>& rest_elements,
                                 const c10::optional<at::Tensor>& rotations) {
  StressArgs a(u, c10::nullopt, elements, shape_vectors, measure, lam, mu, projector, model, rest_elements, rotations);
  return stress_partial_impl<L, false>(a, force_index, num_slots);
}

template <class L>
at::Tensor stress_partial_dforces(const at::Tensor& u, const at::Tensor& du, const at::Tensor& elements,
                                  const at::Tensor& force_index, int64_t num_slots, const at::Tensor& shape_vectors,
                                  const at::Tensor& measure, const at::Tensor& lam, const at::Tensor& mu,
                                  const c10::optional<at::Tensor>& projector, int64_t model,
                                 const c10::optional<at::Tensor>& rest_elements,
                                 const c10::optional<at::Tensor>& rotations) {
  StressArgs a(u, du, elements, shape_vectors, measure, lam, mu, projector, model, rest_elements, rotations);
  return stress_partial_impl<L, true>(a, force_index, num_slots);
}

template <class L, bool DFORCE>
at::Tensor stress_fused_impl(const StressArgs& a, const at::Tensor& force_index, int64_t num_slots,
                             const at::Tensor& incidences) {
  check_plan(a.u, force_index, num_slots, a.index_type, {a.num_elements, a.nodes_per_element});
  check_incidences(a.u, incidences, a.index_type);
  typename L::Guard guard(a.u.device());
  at::Tensor partial = at::empty({num_slots, a.num_nodes, a.dim}, a.u.options());
  run_stress_kernel1<L, DFORCE>(a, force_index, partial);
  at::Tensor out = at::empty({a.num_nodes, a.dim}, a.u.options());
  run_gather<L>(partial, incidences, at::Tensor(), out);
  return out;
}

template <class L>
at::Tensor stress_forces(const at::Tensor& u, const at::Tensor& elements, const at::Tensor& force_index,
                         int64_t num_slots, const at::Tensor& incidences, const at::Tensor& shape_vectors,
                         const at::Tensor& measure, const at::Tensor& lam, const at::Tensor& mu,
                         const c10::optional<at::Tensor>& projector, int64_t model,
                                 const c10::optional<at::Tensor>& rest_elements,
                                 const c10::optional<at::Tensor>& rotations) {
  StressArgs a(u, c10::nullopt, elements, shape_vectors, measure, lam, mu, projector, model, rest_elements, rotations);
  return stress_fused_impl<L, false>(a, force_index, num_slots, incidences);
}

template <class L>
at::Tensor stress_dforces(const at::Tensor& u, const at::Tensor& du, const at::Tensor& elements,
                          const at::Tensor& force_index, int64_t num_slots, const at::Tensor& incidences,
                          const at::Tensor& shape_vectors, const at::Tensor& measure, const at::Tensor& lam,
                          const at::Tensor& mu, const c10::optional<at::Tensor>& projector, int64_t model,
                                 const c10::optional<at::Tensor>& rest_elements,
                                 const c10::optional<at::Tensor>& rotations) {
  StressArgs a(u, du, elements, shape_vectors, measure, lam, mu, projector, model, rest_elements, rotations);
  return stress_fused_impl<L, true>(a, force_index, num_slots, incidences);
}

// ------------------------------------------------------------------ corotational rotations

// The element rotations R [N, d, d] at u (once per linearisation; the stress ops read them back
// through their `rotations` argument). method 0 = SOFA's QR frame (3-D, needs rest_elements),
// 1 = polar (shape_vectors; membranes also need projector and rest_elements: their normals).
template <class L>
at::Tensor corotational_rotations(const at::Tensor& u, const at::Tensor& elements, const at::Tensor& shape_vectors,
                                  const c10::optional<at::Tensor>& projector,
                                  const c10::optional<at::Tensor>& rest_elements, int64_t method) {
  check_values(u, "u");
  const int64_t dim = u.size(1);
  const at::ScalarType index_type = index_type_of(elements, "elements");
  TORCH_CHECK(elements.dim() == 2, "tensormass: elements must be [N, n], got shape ", shape_str(elements.sizes()));
  const int64_t n_elem = elements.size(0), nn = elements.size(1);
  check_index_tensor(elements, "elements", u, index_type, {n_elem, nn});
  dispatch_kind(nn, dim, [](auto, auto) {});
  TORCH_CHECK(method == kQr || method == kPolar, "tensormass: unknown rotation method ", std::to_string(method),
              " (0 = qr, 1 = polar)");
  check_float_tensor(shape_vectors, "shape_vectors", u, {n_elem, nn, dim});
  const bool membrane = nn - 1 < dim;
  const bool has_projector = projector.has_value() && projector->defined();
  TORCH_CHECK(has_projector == membrane, "tensormass: the projector must be given for membranes (triangles "
              "in 3-D) and only for them (nodes per element ", std::to_string(nn), ", dimension ", std::to_string(dim), ")");
  if (has_projector) check_float_tensor(*projector, "projector", u, {n_elem, dim, dim});
  const bool has_rest = rest_elements.has_value() && rest_elements->defined();
  if (method == kQr) {
    TORCH_CHECK(dim == 3, "tensormass: the QR rotation frame needs 3-D elements, got dimension ", std::to_string(dim));
  }
  if (method == kQr || membrane) {
    TORCH_CHECK(has_rest, "tensormass: rest_elements [N, n, 3] is needed by the ",
                method == kQr ? "QR frame" : "polar rotation of membranes (their rest normals)");
  }
  if (has_rest) check_float_tensor(*rest_elements, "rest_elements", u, {n_elem, nn, dim});
  typename L::Guard guard(u.device());
  at::Tensor out = at::empty({n_elem, dim, dim}, u.options());
  dispatch_scalar(u.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_kind(nn, dim, [&](auto nn_c, auto d_c) {
        constexpr int NN = decltype(nn_c)::value;
        constexpr int D = decltype(d_c)::value;
        auto launch = [&](auto method_c) {
          constexpr int METHOD = decltype(method_c)::value;
          RotationKernel<METHOD, NN, D, S, I> k;
          k.u = u.data_ptr<S>();
          k.elements = elements.data_ptr<I>();
          k.shape_vectors = shape_vectors.data_ptr<S>();
          k.projector = ptr_or_null<S>(projector);
          k.rest = ptr_or_null<S>(rest_elements);
          k.out = out.data_ptr<S>();
          L::run(n_elem, k, L::kElementBlock);
        };
        if constexpr (D == 3) {
          if (method == kQr) {
            launch(IC<kQr>{});
            return;
          }
        }
        launch(IC<kPolar>{});
      });
    });
  });
  return out;
}

// ------------------------------------------------------------------ the tangent on the node graph

// stress_tangent_node_k: the force differential of a stress-form group at u as the node graph's
// slot tensors (kernels.h TangentElementKernel, TangentEdgeKernel, TangentSlotKernel): node_k
// [N_n, V, d, d] (in place; slots beyond a node's incidences [V] are not written) such that
// hooke_node_system over (neighbor, node_k, incidences) of the edge plan is this group's CG
// product. The edges (topology.EdgeGraph): element_edges / edge_slots [N, P] (the edge of each
// local pair and its slot among the edge's elements: edge_counts [Ed], num_edge_slots the most)
// and slot_edge [N_n, V] (the edge of each slot of the node graph: g, or ~g where the node is the
// edge's second). edge_partial [num_edge_slots, Ed, 12] (3-D; [.., 4] in 2-D: each d x d block
// padded to 16 bytes): kernels 1 and 2's buffer. The corotational model needs its rotations (held
// fixed, as its dforces).
template <class L>
void stress_tangent_node_k(const at::Tensor& u, const at::Tensor& elements, const at::Tensor& shape_vectors,
                           const at::Tensor& measure, const at::Tensor& lam, const at::Tensor& mu,
                           const c10::optional<at::Tensor>& projector, int64_t model,
                           const c10::optional<at::Tensor>& rotations, const at::Tensor& element_edges,
                           const at::Tensor& edge_slots, int64_t num_edge_slots, const at::Tensor& edge_counts,
                           const at::Tensor& slot_edge, const at::Tensor& incidences, at::Tensor node_k,
                           at::Tensor edge_partial) {
  TORCH_CHECK(model != kCorotational || (rotations.has_value() && rotations->defined()),
              "tensormass: the corotational tangent needs the rotations of its linearisation [N, d, d]");
  StressArgs a(u, c10::nullopt, elements, shape_vectors, measure, lam, mu, projector, model, c10::nullopt, rotations);
  const int64_t n = a.nodes_per_element, pairs = n * (n - 1) / 2, d = a.dim, V = a.num_nodes;
  TORCH_CHECK(edge_counts.dim() == 1, "tensormass: edge_counts must be [Ed], got shape ",
              shape_str(edge_counts.sizes()));
  const int64_t num_edges = edge_counts.size(0);
  check_index_tensor(edge_counts, "edge_counts", u, a.index_type, {num_edges});
  check_index_tensor(element_edges, "element_edges", u, a.index_type, {a.num_elements, pairs});
  check_index_tensor(edge_slots, "edge_slots", u, a.index_type, {a.num_elements, pairs});
  TORCH_CHECK(slot_edge.dim() == 2, "tensormass: slot_edge must be [N_n, V], got shape ", shape_str(slot_edge.sizes()));
  const int64_t num_slots = slot_edge.size(0);
  check_index_tensor(slot_edge, "slot_edge", u, a.index_type, {num_slots, V});
  check_index_tensor(incidences, "incidences", u, a.index_type, {V});
  TORCH_CHECK(num_edge_slots >= 0, "tensormass: num_edge_slots must be >= 0, got ", std::to_string(num_edge_slots));
  TORCH_CHECK(a.num_elements == 0 || (num_edge_slots > 0 && num_slots > 0),
              "tensormass: num_edge_slots or the slots of slot_edge are 0 but there are elements");
  check_float_tensor(node_k, "node_k", u, {num_slots, V, d, d});
  check_float_tensor(edge_partial, "edge_partial", u, {num_edge_slots, num_edges, d == 3 ? 12 : 4});
  typename L::Guard guard(u.device());
  if (a.num_elements == 0) return;
  dispatch_scalar(u.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(a.index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_kind(n, d, [&](auto nn_c, auto d_c) {
        constexpr int NN = decltype(nn_c)::value;
        constexpr int D = decltype(d_c)::value;
        dispatch_model(model, [&](auto model_c) {
          constexpr int MODEL = decltype(model_c)::value;
          TangentElementKernel<MODEL, NN, D, S, I> k1;
          k1.in = a.template inputs<S, I>();
          k1.element_edges = element_edges.data_ptr<I>();
          k1.edge_slots = edge_slots.data_ptr<I>();
          k1.num_edges = num_edges;
          k1.edge_partial = edge_partial.data_ptr<S>();
          L::run(a.num_elements * (NN - 1), k1, L::kElementBlock);
        });
        TangentEdgeKernel<D, S, I> k2;
        k2.edge_partial = edge_partial.data_ptr<S>();
        k2.edge_counts = edge_counts.data_ptr<I>();
        k2.num_edges = num_edges;
        L::run(num_edges, k2, L::kNodeBlock);
        TangentSlotKernel<D, S, I> k3;
        k3.edge_sums = edge_partial.data_ptr<S>();
        k3.slot_edge = slot_edge.data_ptr<I>();
        k3.incidences = incidences.data_ptr<I>();
        k3.num_nodes = V;
        k3.node_k = node_k.data_ptr<S>();
        L::run(V * d * d, k3, L::kNodeBlock);
      });
    });
  });
}

// ------------------------------------------------------------------ gather ops

// Kernel 2 alone: partial [N_n, V, d] (only the slots below incidences[i] are read) -> [V, d].
template <class L>
at::Tensor gather_partial(const at::Tensor& partial, const at::Tensor& incidences,
                          const c10::optional<at::Tensor>& node_term) {
  TORCH_CHECK(partial.dim() == 3, "tensormass: partial must be [N_n, V, d], got shape ", shape_str(partial.sizes()));
  TORCH_CHECK(partial.scalar_type() == at::kFloat || partial.scalar_type() == at::kDouble,
              "tensormass: partial must be float32 or float64, got ", dtype_str(partial.scalar_type()));
  TORCH_CHECK(partial.is_contiguous(), "tensormass: partial must be contiguous (call .contiguous())");
  const int64_t num_nodes = partial.size(1), dim = partial.size(2);
  index_type_of(incidences, "incidences");
  TORCH_CHECK(incidences.device() == partial.device(), "tensormass: incidences is on ", incidences.device().str(),
              " but partial is on ", partial.device().str());
  TORCH_CHECK(incidences.sizes() == at::IntArrayRef({num_nodes}), "tensormass: incidences has shape ",
              shape_str(incidences.sizes()), "; expected [", std::to_string(num_nodes), "]");
  TORCH_CHECK(incidences.is_contiguous(), "tensormass: incidences must be contiguous");
  at::Tensor term;
  if (node_term.has_value() && node_term->defined()) {
    term = *node_term;
    TORCH_CHECK(term.device() == partial.device() && term.scalar_type() == partial.scalar_type(),
                "tensormass: node_term must have the dtype and device of partial");
    TORCH_CHECK(term.sizes() == at::IntArrayRef({num_nodes, dim}), "tensormass: node_term has shape ",
                shape_str(term.sizes()), "; expected [", std::to_string(num_nodes), ", ", std::to_string(dim), "]");
    TORCH_CHECK(term.is_contiguous(), "tensormass: node_term must be contiguous");
  }
  typename L::Guard guard(partial.device());
  at::Tensor out = at::empty({num_nodes, dim}, partial.options());
  run_gather<L>(partial, incidences, term, out);
  return out;
}

// Kernel 2 on compact partial forces: partial [N, n, d] scattered to the padded buffer through
// (force_index, index), then summed per node (+ node_term [V, d]).
template <class L>
at::Tensor node_gather(const at::Tensor& partial, const at::Tensor& index, const at::Tensor& force_index,
                       int64_t num_slots, const at::Tensor& incidences, const c10::optional<at::Tensor>& node_term) {
  TORCH_CHECK(partial.dim() == 3, "tensormass: partial must be [N, n, d], got shape ", shape_str(partial.sizes()));
  TORCH_CHECK(partial.scalar_type() == at::kFloat || partial.scalar_type() == at::kDouble,
              "tensormass: partial must be float32 or float64, got ", dtype_str(partial.scalar_type()));
  TORCH_CHECK(partial.is_contiguous(), "tensormass: partial must be contiguous (call .contiguous())");
  const int64_t n_items = partial.size(0), nn = partial.size(1), dim = partial.size(2);
  const at::ScalarType index_type = index_type_of(index, "index");
  const int64_t num_nodes = incidences.dim() == 1 ? incidences.size(0) : -1;
  TORCH_CHECK(num_nodes >= 0, "tensormass: incidences must be [V], got shape ", shape_str(incidences.sizes()));
  TORCH_CHECK(index.device() == partial.device() && force_index.device() == partial.device() &&
                  incidences.device() == partial.device(),
              "tensormass: index, force_index and incidences must be on the device of partial (", partial.device().str(),
              ")");
  TORCH_CHECK(index.scalar_type() == index_type && force_index.scalar_type() == index_type &&
                  incidences.scalar_type() == index_type,
              "tensormass: index, force_index and incidences must have one dtype (int32 or int64)");
  TORCH_CHECK(index.sizes() == at::IntArrayRef({n_items, nn}) && force_index.sizes() == index.sizes(),
              "tensormass: index and force_index must be [N, n] = [", std::to_string(n_items), ", ", std::to_string(nn), "], got ",
              shape_str(index.sizes()), " and ", shape_str(force_index.sizes()));
  TORCH_CHECK(index.is_contiguous() && force_index.is_contiguous() && incidences.is_contiguous(),
              "tensormass: index, force_index and incidences must be contiguous");
  TORCH_CHECK(num_slots >= 0 && (n_items == 0 || num_slots > 0), "tensormass: bad num_slots ", std::to_string(num_slots));
  at::Tensor term;
  if (node_term.has_value() && node_term->defined()) {
    term = *node_term;
    TORCH_CHECK(term.device() == partial.device() && term.scalar_type() == partial.scalar_type(),
                "tensormass: node_term must have the dtype and device of partial");
    TORCH_CHECK(term.sizes() == at::IntArrayRef({num_nodes, dim}), "tensormass: node_term has shape ",
                shape_str(term.sizes()), "; expected [", std::to_string(num_nodes), ", ", std::to_string(dim), "]");
    TORCH_CHECK(term.is_contiguous(), "tensormass: node_term must be contiguous");
  }
  typename L::Guard guard(partial.device());
  at::Tensor padded = at::empty({num_slots, num_nodes, dim}, partial.options());
  dispatch_scalar(partial.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      auto launch = [&](auto nn_c, auto d_c) {
        constexpr int NN = decltype(nn_c)::value;
        constexpr int D = decltype(d_c)::value;
        ScatterKernel<NN, D, S, I> k;
        k.partial = partial.data_ptr<S>();
        k.index = index.data_ptr<I>();
        k.write.out = padded.data_ptr<S>();
        k.write.force_index = force_index.data_ptr<I>();
        k.write.num_nodes = num_nodes;
        L::run(n_items, k, L::kNodeBlock);
      };
      // items: elements (4 or 3 nodes) or edges (2 nodes)
      dispatch_dim(dim, [&](auto d_c) {
        if (nn == 4) {
          launch(IC<4>{}, d_c);
        } else if (nn == 3) {
          launch(IC<3>{}, d_c);
        } else if (nn == 2) {
          launch(IC<2>{}, d_c);
        } else {
          TORCH_CHECK(false, "tensormass: node_gather supports 2, 3 or 4 nodes per item, got ", std::to_string(nn));
        }
      });
    });
  });
  at::Tensor out = at::empty({num_nodes, dim}, partial.options());
  run_gather<L>(padded, incidences, term, out);
  return out;
}

// Kernel 2 with the implicit-Euler epilogue (SystemGatherKernel): from the padded partial force
// differentials [N_n, V, d] of p, Ap = free * (c_mass * mass * p - c_stiff * K p) [V, d] and the
// per-node dots p . Ap [V].
inline void check_node_tensor(const at::Tensor& t, const char* name, const at::Tensor& like,
                              at::IntArrayRef shape, const char* like_name = "partial") {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.device() == like.device(), "tensormass: ", name, " is on ", t.device().str(),
              " but ", like_name, " is on ", like.device().str());
  TORCH_CHECK(t.scalar_type() == like.scalar_type(), "tensormass: ", name, " is ", dtype_str(t.scalar_type()),
              " but ", like_name, " is ", dtype_str(like.scalar_type()), " (all floating inputs must have one dtype)");
  TORCH_CHECK(t.sizes() == shape, "tensormass: ", name, " has shape ", shape_str(t.sizes()), "; expected ",
              shape_str(shape));
  TORCH_CHECK(t.is_contiguous(), "tensormass: ", name, " must be contiguous (call .contiguous())");
}

// The epilogue's pointers and coefficients (fr, nk: undefined when absent).
template <int D, typename S, bool HAS_FREE, bool HAS_NODE_K>
void set_epilogue(SystemEpilogue<D, S, HAS_FREE, HAS_NODE_K>& e, const at::Tensor& mass, const at::Tensor& fr,
                  const at::Tensor& nk, double c_mass, double c_stiff, at::Tensor& ap, at::Tensor& p_dot_ap) {
  e.mass = mass.data_ptr<S>();
  e.free = HAS_FREE ? fr.data_ptr<S>() : nullptr;
  e.node_stiffness = HAS_NODE_K ? nk.data_ptr<S>() : nullptr;
  e.c_mass = static_cast<S>(c_mass);
  e.c_stiff = static_cast<S>(c_stiff);
  e.ap = ap.data_ptr<S>();
  e.p_dot_ap = p_dot_ap.defined() ? p_dot_ap.data_ptr<S>() : nullptr;
}

// The optional epilogue inputs, checked against `like` ([V, d]): free [V], node_stiffness [V, d, d].
inline std::tuple<at::Tensor, at::Tensor> optional_epilogue_inputs(
    const c10::optional<at::Tensor>& free, const c10::optional<at::Tensor>& node_stiffness, const at::Tensor& like,
    int64_t num_nodes, int64_t dim, const char* like_name) {
  at::Tensor fr, nk;
  if (free.has_value() && free->defined()) {
    fr = *free;
    check_node_tensor(fr, "free", like, {num_nodes}, like_name);
  }
  if (node_stiffness.has_value() && node_stiffness->defined()) {
    nk = *node_stiffness;
    check_node_tensor(nk, "node_stiffness", like, {num_nodes, dim, dim}, like_name);
  }
  return std::make_tuple(fr, nk);
}

// The dispatch of the system kernels (K = SystemGatherKernel or NodeHookeSystemKernel): scalar S,
// index I, dimension D and the epilogue's HAS_FREE / HAS_NODE_K (fr, nk defined or not); f gets
// the kernel with its epilogue set, to fill in its own inputs and launch.
template <template <int, typename, typename, bool, bool> class K, class F>
void dispatch_system(at::ScalarType scalar, at::ScalarType index, int64_t dim, const at::Tensor& mass,
                     const at::Tensor& fr, const at::Tensor& nk, double c_mass, double c_stiff, at::Tensor& ap,
                     at::Tensor& p_dot_ap, const F& f) {
  dispatch_scalar(scalar, [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(index, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_dim(dim, [&](auto d_c) {
        constexpr int D = decltype(d_c)::value;
        dispatch_bool(fr.defined(), [&](auto free_c) {
          dispatch_bool(nk.defined(), [&](auto node_k_c) {
            K<D, S, I, decltype(free_c)::value, decltype(node_k_c)::value> k;
            set_epilogue(k.epilogue, mass, fr, nk, c_mass, c_stiff, ap, p_dot_ap);
            f(k);
          });
        });
      });
    });
  });
}

// The system gather's kernel, set up and handed to `launch` (a node loop, or the chunked loop
// that ends in the CG step length); p_dot_ap may be undefined (then the dots are only returned
// by the kernel's apply).
template <class L, class Launch>
void run_gather_system(const at::Tensor& partial, const at::Tensor& incidences, const at::Tensor& p,
                       const at::Tensor& mass, const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                       const c10::optional<at::Tensor>& node_stiffness, at::Tensor& ap, at::Tensor& p_dot_ap,
                       const Launch& launch) {
  TORCH_CHECK(partial.defined(), "tensormass: partial is undefined");
  TORCH_CHECK(partial.dim() == 3, "tensormass: partial must be [N_n, V, d], got shape ", shape_str(partial.sizes()));
  TORCH_CHECK(partial.scalar_type() == at::kFloat || partial.scalar_type() == at::kDouble,
              "tensormass: partial must be float32 or float64, got ", dtype_str(partial.scalar_type()));
  TORCH_CHECK(partial.is_contiguous(), "tensormass: partial must be contiguous (call .contiguous())");
  const int64_t num_nodes = partial.size(1), dim = partial.size(2);
  const at::ScalarType index_type = index_type_of(incidences, "incidences");
  TORCH_CHECK(incidences.device() == partial.device(), "tensormass: incidences is on ", incidences.device().str(),
              " but partial is on ", partial.device().str());
  TORCH_CHECK(incidences.sizes() == at::IntArrayRef({num_nodes}), "tensormass: incidences has shape ",
              shape_str(incidences.sizes()), "; expected [", std::to_string(num_nodes), "]");
  TORCH_CHECK(incidences.is_contiguous(), "tensormass: incidences must be contiguous");
  check_node_tensor(p, "p", partial, {num_nodes, dim});
  check_node_tensor(mass, "mass", partial, {num_nodes});
  at::Tensor fr, nk;
  std::tie(fr, nk) = optional_epilogue_inputs(free, node_stiffness, partial, num_nodes, dim, "partial");
  dispatch_dim(dim, [](auto) {});
  typename L::Guard guard(partial.device());
  if (!ap.defined()) ap = at::empty({num_nodes, dim}, partial.options());
  check_node_tensor(ap, "ap", partial, {num_nodes, dim});
  dispatch_system<SystemGatherKernel>(partial.scalar_type(), index_type, dim, mass, fr, nk, c_mass, c_stiff, ap,
                                      p_dot_ap, [&](auto& k) {
    using Kernel = std::decay_t<decltype(k)>;
    using S = typename Kernel::Scalar;
    using I = typename Kernel::Index;
    k.partial = partial.numel() ? partial.data_ptr<S>() : nullptr;
    k.incidences = incidences.data_ptr<I>();
    k.p = p.data_ptr<S>();
    k.num_nodes = num_nodes;
    launch(k, num_nodes);
  });
}

template <class L>
std::tuple<at::Tensor, at::Tensor> gather_system(const at::Tensor& partial, const at::Tensor& incidences,
                                                 const at::Tensor& p, const at::Tensor& mass,
                                                 const c10::optional<at::Tensor>& free, double c_mass,
                                                 double c_stiff,
                                                 const c10::optional<at::Tensor>& node_stiffness) {
  at::Tensor ap;
  at::Tensor p_dot_ap = at::empty({partial.dim() == 3 ? partial.size(1) : 0}, partial.options());
  run_gather_system<L>(partial, incidences, p, mass, free, c_mass, c_stiff, node_stiffness, ap, p_dot_ap,
                       [](const auto& k, int64_t n) { L::run(n, k, L::kNodeBlock); });
  return std::make_tuple(ap, p_dot_ap);
}

// ------------------------------------------------------------------ tensor form, hooke

struct HookeTensorArgs {
  at::Tensor u, edges, edge_k;
  int64_t num_edges, dim;
  at::ScalarType index_type;
  HookeTensorArgs(const at::Tensor& u_, const at::Tensor& edges_, const at::Tensor& edge_k_)
      : u(u_), edges(edges_), edge_k(edge_k_) {
    check_values(u, "u");
    dim = u.size(1);
    index_type = index_type_of(edges, "edges");
    TORCH_CHECK(edges.dim() == 2 && edges.size(1) == 2, "tensormass: edges must be [Ed, 2], got shape ",
                shape_str(edges.sizes()));
    num_edges = edges.size(0);
    check_index_tensor(edges, "edges", u, index_type, {num_edges, 2});
    check_float_tensor(edge_k, "edge_k", u, {num_edges, dim, dim});
    dispatch_dim(dim, [](auto) {});
  }
};

template <class L>
void run_hooke_kernel1(const HookeTensorArgs& a, const at::Tensor& force_index, at::Tensor& out) {
  dispatch_scalar(a.u.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(a.index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_dim(a.dim, [&](auto d_c) {
        constexpr int D = decltype(d_c)::value;
        dispatch_bool(force_index.defined(), [&](auto padded_c) {
          constexpr bool PADDED = decltype(padded_c)::value;
          TensorHookeEdgeKernel<D, S, I, PADDED> k;
          k.u = a.u.data_ptr<S>();
          k.edges = a.edges.data_ptr<I>();
          k.edge_k = a.edge_k.data_ptr<S>();
          k.write.out = out.data_ptr<S>();
          set_padded(k.write, force_index, a.u.size(0));
          L::run(a.num_edges, k, L::kElementBlock);
        });
      });
    });
  });
}

template <class L>
at::Tensor tensor_hooke_element_forces(const at::Tensor& u, const at::Tensor& edges, const at::Tensor& edge_k) {
  HookeTensorArgs a(u, edges, edge_k);
  typename L::Guard guard(u.device());
  at::Tensor out = at::empty({a.num_edges, 2, a.dim}, u.options());
  run_hooke_kernel1<L>(a, at::Tensor(), out);
  return out;
}

template <class L>
at::Tensor tensor_hooke_partial_forces(const at::Tensor& u, const at::Tensor& edges, const at::Tensor& force_index,
                                       int64_t num_slots, const at::Tensor& edge_k) {
  HookeTensorArgs a(u, edges, edge_k);
  check_plan(u, force_index, num_slots, a.index_type, {a.num_edges, 2});
  typename L::Guard guard(u.device());
  at::Tensor partial = at::empty({num_slots, u.size(0), a.dim}, u.options());
  run_hooke_kernel1<L>(a, force_index, partial);
  return partial;
}

// F_i = -sum_j K_ij (u_j - u_i) (linear: the dforces along du are tensor_hooke_forces(du)).
template <class L>
at::Tensor tensor_hooke_forces(const at::Tensor& u, const at::Tensor& edges, const at::Tensor& force_index,
                               int64_t num_slots, const at::Tensor& incidences, const at::Tensor& edge_k) {
  HookeTensorArgs a(u, edges, edge_k);
  check_plan(u, force_index, num_slots, a.index_type, {a.num_edges, 2});
  check_incidences(u, incidences, a.index_type);
  typename L::Guard guard(u.device());
  at::Tensor partial = at::empty({num_slots, u.size(0), a.dim}, u.options());
  run_hooke_kernel1<L>(a, force_index, partial);
  at::Tensor out = at::empty({u.size(0), a.dim}, u.options());
  run_gather<L>(partial, incidences, at::Tensor(), out);
  return out;
}

// The node graph of the hooke tensor form (HookeNodeGraph): the slot-major arrays neighbor
// [N_n, V] (int32/int64, as incidences) and node_k [N_n, V, d, d] (Kdir of each slot; slots >=
// incidences[i] are never read), checked against the [V, d] field `like`; returns the index type.
inline at::ScalarType check_hooke_node_graph(const at::Tensor& like, const char* like_name, const at::Tensor& neighbor,
                                             const at::Tensor& node_k, const at::Tensor& incidences,
                                             const c10::optional<at::Tensor>& row_node) {
  const int64_t num_nodes = like.size(0), dim = like.size(1);
  const at::ScalarType index_type = index_type_of(neighbor, "neighbor");
  TORCH_CHECK(neighbor.dim() == 2, "tensormass: neighbor must be [N_n, V], got shape ", shape_str(neighbor.sizes()));
  const int64_t num_slots = neighbor.size(0);
  check_index_tensor(neighbor, "neighbor", like, index_type, {num_slots, num_nodes}, like_name);
  check_index_tensor(incidences, "incidences", like, index_type, {num_nodes}, like_name);
  check_node_tensor(node_k, "node_k", like, {num_slots, num_nodes, dim, dim}, like_name);
  if (row_node.has_value() && row_node->defined()) {
    check_index_tensor(*row_node, "row_node", like, index_type, {num_nodes}, like_name);
  }
  return index_type;
}

template <int D, typename S, typename I>
void set_hooke_node_graph(HookeNodeGraph<D, S, I>& graph, const at::Tensor& neighbor, const at::Tensor& node_k,
                          const at::Tensor& incidences, const c10::optional<at::Tensor>& row_node) {
  graph.neighbor = neighbor.numel() ? neighbor.data_ptr<I>() : nullptr;
  graph.node_k = node_k.numel() ? node_k.data_ptr<S>() : nullptr;
  graph.incidences = incidences.data_ptr<I>();
  graph.row_node = row_node.has_value() && row_node->defined() ? row_node->data_ptr<I>() : nullptr;
  graph.num_nodes = incidences.size(0);
}

// The CG matvec of the hooke tensor form in one kernel (NodeHookeSystemKernel) over the node
// graph: Ap [V, d] and the per-node dots p . Ap [V], with the epilogue of gather_system. Bitwise
// equal to tensor_hooke_partial_forces + gather_system over the same plan.
template <class L, class Launch>
void run_hooke_node_system(const at::Tensor& p, const at::Tensor& neighbor, const at::Tensor& node_k,
                           const at::Tensor& incidences, const c10::optional<at::Tensor>& row_node,
                           const at::Tensor& mass,
                           const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                           const c10::optional<at::Tensor>& node_stiffness, at::Tensor& ap, at::Tensor& p_dot_ap,
                           const Launch& launch) {
  check_values(p, "p");
  const int64_t num_nodes = p.size(0), dim = p.size(1);
  dispatch_dim(dim, [](auto) {});
  const at::ScalarType index_type = check_hooke_node_graph(p, "p", neighbor, node_k, incidences, row_node);
  check_node_tensor(mass, "mass", p, {num_nodes}, "p");
  at::Tensor fr, nk;
  std::tie(fr, nk) = optional_epilogue_inputs(free, node_stiffness, p, num_nodes, dim, "p");
  typename L::Guard guard(p.device());
  if (!ap.defined()) ap = at::empty({num_nodes, dim}, p.options());
  check_node_tensor(ap, "ap", p, {num_nodes, dim}, "p");
  dispatch_system<NodeHookeSystemKernel>(p.scalar_type(), index_type, dim, mass, fr, nk, c_mass, c_stiff, ap,
                                         p_dot_ap, [&](auto& k) {
    using Kernel = std::decay_t<decltype(k)>;
    using S = typename Kernel::Scalar;
    k.p = p.data_ptr<S>();
    set_hooke_node_graph(k.graph, neighbor, node_k, incidences, row_node);
    launch(k, num_nodes);
  });
}

template <class L>
std::tuple<at::Tensor, at::Tensor> hooke_node_system(const at::Tensor& p, const at::Tensor& neighbor,
                                                     const at::Tensor& node_k, const at::Tensor& incidences,
                                                     const c10::optional<at::Tensor>& row_node,
                                                     const at::Tensor& mass, const c10::optional<at::Tensor>& free,
                                                     double c_mass, double c_stiff,
                                                     const c10::optional<at::Tensor>& node_stiffness) {
  at::Tensor ap;
  at::Tensor p_dot_ap = at::empty({p.dim() >= 1 ? p.size(0) : 0}, p.options());
  run_hooke_node_system<L>(p, neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff, node_stiffness, ap,
                           p_dot_ap, [](const auto& k, int64_t n) { L::run(n, k, L::kNodeBlock); });
  return std::make_tuple(ap, p_dot_ap);
}

// ------------------------------------------------------------------ implicit Euler's right-hand side

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

// hooke_node_step_rhs: the right-hand side of an implicit Euler step of the hooke tensor form in
// one pass over the nodes (NodeHookeStepRhsKernel), at positions x and velocities v [V, d]:
//   rhs = h (f((x - rest) + w_coef v) + external + contact(x) - Kc(x) (w_coef v) - r_M mass v)
// (w_coef = h + r_K), and what the step's CG matvec needs: u = x - rest [V, d] and, with planes
// (normals [P, 3], offsets [P], stiffness [P]; d = 3), the contact stiffness node_stiffness
// [V, 3, 3]. Outputs in place (u, rhs, node_stiffness), so that a CUDA graph replays into them.
template <class L>
void hooke_node_step_rhs(const at::Tensor& x, const at::Tensor& v, const at::Tensor& rest, const at::Tensor& neighbor,
                         const at::Tensor& node_k, const at::Tensor& incidences,
                         const c10::optional<at::Tensor>& row_node, const at::Tensor& mass,
                         const at::Tensor& external, const c10::optional<at::Tensor>& plane_normals,
                         const c10::optional<at::Tensor>& plane_offsets,
                         const c10::optional<at::Tensor>& plane_stiffness, double h, double w_coef,
                         double rayleigh_mass, at::Tensor u, at::Tensor rhs,
                         const c10::optional<at::Tensor>& node_stiffness) {
  check_values(x, "x");
  const int64_t num_nodes = x.size(0), dim = x.size(1);
  dispatch_dim(dim, [](auto) {});
  const std::pair<const at::Tensor*, const char*> fields[] = {{&v, "v"}, {&rest, "rest"}, {&external, "external"},
                                                              {&u, "u"}, {&rhs, "rhs"}};
  for (const auto& named : fields) check_node_tensor(*named.first, named.second, x, {num_nodes, dim}, "x");
  check_node_tensor(mass, "mass", x, {num_nodes}, "x");
  const at::ScalarType index_type = check_hooke_node_graph(x, "x", neighbor, node_k, incidences, row_node);
  const StepPlanes planes(x, plane_normals, plane_offsets, plane_stiffness, node_stiffness);
  const bool has_planes = planes.given;
  const at::Tensor &normals = planes.normals, &offsets = planes.offsets, &stiffness = planes.stiffness,
                   &node_k_out = planes.node_stiffness;
  typename L::Guard guard(x.device());
  dispatch_scalar(x.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_dim(dim, [&](auto d_c) {
        constexpr int D = decltype(d_c)::value;
        dispatch_bool(has_planes, [&](auto planes_c) {
          NodeHookeStepRhsKernel<D, S, I, decltype(planes_c)::value> k;
          k.x = x.data_ptr<S>();
          k.v = v.data_ptr<S>();
          k.rest = rest.data_ptr<S>();
          k.mass = mass.data_ptr<S>();
          k.external = external.data_ptr<S>();
          set_hooke_node_graph(k.graph, neighbor, node_k, incidences, row_node);
          k.planes = PenaltyPlanes<S>{has_planes ? normals.data_ptr<S>() : nullptr,
                                      has_planes ? offsets.data_ptr<S>() : nullptr,
                                      has_planes ? stiffness.data_ptr<S>() : nullptr,
                                      has_planes ? normals.size(0) : 0};
          k.h = static_cast<S>(h);
          k.c_w = static_cast<S>(w_coef);
          k.rayleigh_mass = static_cast<S>(rayleigh_mass);
          k.u = u.data_ptr<S>();
          k.rhs = rhs.data_ptr<S>();
          k.node_stiffness = has_planes ? node_k_out.data_ptr<S>() : nullptr;
          L::run(num_nodes, k, L::kNodeBlock);
        });
      });
    });
  });
}

// ------------------------------------------------------------------ matvecs ending in alpha
//
// The CG iteration's matvec fused with cg_alpha (one kernel fewer per iteration): Ap written into
// `ap` [V, d] in place, then per object alpha = rr / sum p . Ap (or the object stops: breakdown /
// non-finite), exactly as cg_alpha over the plan's chunks; objects that are not active are
// skipped (their Ap is not computed). Arguments: those of gather_system / hooke_node_system, then
// ap and cg_alpha's (chunk plan, rr, status, alpha, scratch, counter).

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

template <class L>
void gather_system_alpha(const at::Tensor& partial, const at::Tensor& incidences, const at::Tensor& p,
                         const at::Tensor& mass, const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                         const c10::optional<at::Tensor>& node_stiffness, at::Tensor ap,
                         const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                         const at::Tensor& rr, at::Tensor status, at::Tensor alpha, at::Tensor scratch,
                         at::Tensor counter) {
  check_values(p, "p");
  TORCH_CHECK(ap.defined(), "tensormass: ap is undefined");
  at::Tensor no_dots;
  run_gather_system<L>(partial, incidences, p, mass, free, c_mass, c_stiff, node_stiffness, ap, no_dots,
                       alpha_launch<L>(p, chunk_start, chunk_object, object_chunk, rr, status, alpha, scratch,
                                       counter));
}

template <class L>
void hooke_node_system_alpha(const at::Tensor& p, const at::Tensor& neighbor, const at::Tensor& node_k,
                             const at::Tensor& incidences, const c10::optional<at::Tensor>& row_node,
                             const at::Tensor& mass,
                             const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                             const c10::optional<at::Tensor>& node_stiffness, at::Tensor ap,
                             const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                             const at::Tensor& object_chunk, const at::Tensor& rr, at::Tensor status,
                             at::Tensor alpha, at::Tensor scratch, at::Tensor counter) {
  check_values(p, "p");
  TORCH_CHECK(ap.defined(), "tensormass: ap is undefined");
  at::Tensor no_dots;
  run_hooke_node_system<L>(p, neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff, node_stiffness, ap,
                           no_dots, alpha_launch<L>(p, chunk_start, chunk_object, object_chunk, rr, status, alpha,
                                                    scratch, counter));
}

// ------------------------------------------------------------------ a whole CG solve in one op

// The checks every whole-solve op makes of its iterates [V, d] (like `like`), per-object scalars
// [B] and cap; returns the chunk plan.
inline CGPlan check_cg_iterates(const at::Tensor& like, const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                                const at::Tensor& object_chunk, const at::Tensor& x, const at::Tensor& r,
                                const at::Tensor& threshold, const at::Tensor& rhs_sq, const at::Tensor& rr,
                                const at::Tensor& alpha, const at::Tensor& beta, const at::Tensor& status,
                                const at::Tensor& iterations, int64_t max_iter) {
  TORCH_CHECK(max_iter >= 0, "tensormass: max_iter must be >= 0, got ", std::to_string(max_iter));
  const CGPlan plan = cg_plan(chunk_start, chunk_object, object_chunk, like, like.size(0));
  TORCH_CHECK(plan.num_chunks == 0 || like.size(0) > 0, "tensormass: a chunk plan over no nodes");
  cg_check(x, "x", like, like.scalar_type(), like.sizes());
  cg_check(r, "r", like, like.scalar_type(), like.sizes());
  for (const auto& named : {std::make_pair(&threshold, "threshold"), std::make_pair(&rhs_sq, "rhs_sq"),
                            std::make_pair(&rr, "rr"), std::make_pair(&alpha, "alpha"), std::make_pair(&beta, "beta")}) {
    cg_check_scalars(*named.first, named.second, like, plan.num_objects);
  }
  cg_check_state(status, "status", like, plan.num_objects);
  cg_check_state(iterations, "iterations", like, plan.num_objects);
  return plan;
}

// The iterates and per-object scalars of a whole-solve op, from its tensors (checked by the op).
template <typename S>
void set_cg_iterates(CGIterates<S>& s, const at::Tensor& x, const at::Tensor& r, const at::Tensor& p,
                     const S* rhs, double tol_sq, const at::Tensor& threshold, const at::Tensor& rhs_sq,
                     const at::Tensor& rr, const at::Tensor& alpha, const at::Tensor& beta, const at::Tensor& status,
                     const at::Tensor& iterations, int64_t max_iter) {
  s.x = x.data_ptr<S>();
  s.r = r.data_ptr<S>();
  s.p = p.data_ptr<S>();
  s.rhs = rhs;
  s.tol_sq = static_cast<S>(tol_sq);
  s.threshold = threshold.data_ptr<S>();
  s.rhs_sq = rhs_sq.data_ptr<S>();
  s.rr = rr.data_ptr<S>();
  s.alpha = alpha.data_ptr<S>();
  s.beta = beta.data_ptr<S>();
  s.status = status.data_ptr<int32_t>();
  s.iterations = iterations.data_ptr<int32_t>();
  s.max_iter = max_iter;
}
//
// hooke_node_cg: up to `count` CG iterations whose matvec is hooke_node_system's (A = c_M M -
// c_K K over the node graph, projected on `free`), preceded, when `rhs` is given, by the start
// from x0 = 0 (x = 0, r = p = free * rhs, rhs_sq = b.b, threshold = tol_sq b.b, statuses); it
// stops early once no object is active. On the GPU one persistent kernel (no launch and no host
// round trip per iteration); on the CPU the CG ops' functions in a loop. Either way the result is
// bitwise the op-by-op solve (hooke_node_system_alpha, cg_update, cg_direction) over the same
// chunk plan. Buffers: the CG state (x, r, p [V, d]; threshold, rhs_sq, rr, alpha, beta [B];
// status, iterations [B] int32), ap [V, d], and the persistent kernel's work: rr_swap [B],
// work [3B + 2] int32, sums [2K] float64.
template <class L>
void hooke_node_cg(at::Tensor p, const at::Tensor& neighbor, const at::Tensor& node_k, const at::Tensor& incidences,
                   const c10::optional<at::Tensor>& row_node, const at::Tensor& mass, const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                   const c10::optional<at::Tensor>& node_stiffness, at::Tensor ap, at::Tensor x, at::Tensor r,
                   const c10::optional<at::Tensor>& rhs, double tol_sq, const at::Tensor& chunk_start,
                   const at::Tensor& chunk_object, const at::Tensor& object_chunk, at::Tensor threshold,
                   at::Tensor rhs_sq, int64_t max_iter, int64_t count, at::Tensor rr, at::Tensor status,
                   at::Tensor alpha, at::Tensor beta, at::Tensor iterations, at::Tensor rr_swap, at::Tensor work,
                   at::Tensor sums) {
  check_values(p, "p");
  TORCH_CHECK(ap.defined(), "tensormass: ap is undefined");
  TORCH_CHECK(count >= 0, "tensormass: count must be >= 0, got ", std::to_string(count));
  const CGPlan plan = check_cg_iterates(p, chunk_start, chunk_object, object_chunk, x, r, threshold, rhs_sq, rr, alpha,
                                        beta, status, iterations, max_iter);
  const bool start = rhs.has_value() && rhs->defined();
  if (start) cg_check(*rhs, "rhs", p, p.scalar_type(), p.sizes());
  cg_check_scalars(rr_swap, "rr_swap", p, plan.num_objects);
  cg_check(work, "work", p, at::kInt, {3 * plan.num_objects + 2});
  cg_check(sums, "sums", p, at::kDouble, {2 * plan.num_chunks});
  at::Tensor no_dots;
  run_hooke_node_system<L>(p, neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff, node_stiffness, ap,
                           no_dots, [&](const auto& k, int64_t) {
    using S = typename std::decay_t<decltype(k)>::Scalar;
    CGRun<S> s;
    set_cg_iterates<S>(s, x, r, p, start ? rhs->data_ptr<S>() : nullptr, tol_sq, threshold, rhs_sq, rr, alpha, beta,
                       status, iterations, max_iter);
    s.ap = ap.data_ptr<S>();
    s.free = k.epilogue.free;
    s.rr_swap = rr_swap.data_ptr<S>();
    s.work = work.data_ptr<int32_t>();
    s.sums = sums.data_ptr<double>();
    s.d = p.size(1);
    s.count = count;
    L::run_cg(plan, k, s);
  });
}

// hooke_node_solve: a whole CG solve from x0 = 0 of hooke_node_system's system (A = c_M M - c_K K
// over the node graph, projected on `free`) by the pipelined CG (Chronopoulos-Gear: one
// reduction an iteration; on the GPU one persistent kernel with one grid barrier an iteration,
// cuda/cg_pipelined.cuh): the same iterates as CG in exact arithmetic, the same stopping rule
// and statuses (relative tolerance tol_sq = tol^2 on r.r, max_iter, breakdown, non-finite), not
// bitwise the two-reduction CG of hooke_node_cg. The plan's chunks must hold at most chunk_nodes
// nodes and chunk_slots slots (the sum of incidences over a chunk's nodes): a chunk beyond that
// ends its object as non-finite. chunk_nodes picks the layout: <= SOLVE_CHUNK_NODES (128) the
// chunks' slots may sit in shared memory, <= STREAM_CHUNK_NODES (256) they are read from the
// graph each iteration (chunk_slots unused). Returns whether it ran: false, having changed
// nothing, where the solve does not fit the device in one wave in either layout, or chunk_nodes
// exceeds both (or on the CPU, which has no such kernel); then the caller solves with
// hooke_node_cg. Buffers: the CG state
// (x, r, p [V, d]; threshold, rhs_sq, rr, alpha, beta [B]; status, iterations [B] int32) and
// the work: exchange [2, V, 4d], sums [4K] float64, counters [3] int32.
// The step's end handed to hooke_node_solve_step (euler_update's tensors; dv is the solve's x).
struct StepEndTensors {
  at::Tensor x, v;
  c10::optional<at::Tensor> dv_imposed;
  double h;
  at::Tensor x_new, v_new, norms, summary, sums, counter;
  c10::optional<at::Tensor> ring, ring_pos;
  bool carry;
};

// The right-hand side that hooke_node_steps computes before each solve (StepRhs).
struct StepRhsTensors {
  at::Tensor rest, external;
  double w_coef, rayleigh_mass;
  const StepPlanes& planes;  // its node_stiffness is the solve's
  at::Tensor u;
  int64_t steps;
};

inline void check_no_overlap(const at::Tensor& written, const char* written_name, const at::Tensor& other,
                             const char* other_name) {
  TORCH_CHECK(at::get_overlap_status(written, other) == at::MemOverlapStatus::No, "tensormass: ", written_name,
              " shares memory with ", other_name, "; they must be separate tensors");
}

template <class L>
bool run_hooke_node_solve(const at::Tensor& neighbor, const at::Tensor& node_k, const at::Tensor& incidences,
                          const c10::optional<at::Tensor>& row_node, const at::Tensor& mass,
                          const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                          const c10::optional<at::Tensor>& node_stiffness, const at::Tensor& rhs, double tol_sq,
                          const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                          int64_t chunk_nodes, int64_t chunk_slots, int64_t max_iter, at::Tensor x, at::Tensor r,
                          at::Tensor p, at::Tensor threshold, at::Tensor rhs_sq, at::Tensor rr, at::Tensor status,
                          at::Tensor alpha, at::Tensor beta, at::Tensor iterations, at::Tensor exchange,
                          at::Tensor sums, at::Tensor counters, StepEndTensors* end,
                          const StepRhsTensors* step_rhs = nullptr) {
  check_values(rhs, "rhs");
  TORCH_CHECK(chunk_nodes >= 1, "tensormass: chunk_nodes must be >= 1, got ", std::to_string(chunk_nodes));
  TORCH_CHECK(chunk_slots >= 0, "tensormass: chunk_slots must be >= 0, got ", std::to_string(chunk_slots));
  const CGPlan plan = check_cg_iterates(rhs, chunk_start, chunk_object, object_chunk, x, r, threshold, rhs_sq, rr, alpha,
                                        beta, status, iterations, max_iter);
  cg_check(p, "p", rhs, rhs.scalar_type(), rhs.sizes());
  const int64_t dim = rhs.size(1);
  cg_check(exchange, "exchange", rhs, rhs.scalar_type(), {2, rhs.size(0), 4 * dim});
  cg_check(sums, "sums", rhs, at::kDouble, {4 * plan.num_chunks});
  cg_check(counters, "counters", rhs, at::kInt, {3});
  if (end != nullptr) {  // euler_update's checks, with the solve's x as dv and its plan
    cg_check(end->x, "state_x", rhs, rhs.scalar_type(), rhs.sizes());
    cg_check(end->v, "state_v", rhs, rhs.scalar_type(), rhs.sizes());
    cg_check(end->sums, "end_sums", rhs, at::kDouble, {plan.num_chunks});
    cg_check(end->counter, "end_counter", rhs, at::kInt, {plan.num_objects + 1});
    check_euler_update(end->x, end->v, x, end->dv_imposed, end->x_new, end->v_new, chunk_start, chunk_object,
                       object_chunk, status, iterations, rr, rhs_sq, end->norms, end->summary, end->sums, end->counter,
                       end->ring, end->ring_pos);
  }
  if (step_rhs != nullptr) {  // hooke_node_step_rhs's checks, at the state the step end carries
    TORCH_CHECK(end != nullptr, "tensormass: a solve that computes its right-hand side must end the step");
    TORCH_CHECK(step_rhs->steps >= 1, "tensormass: steps must be >= 1, got ", std::to_string(step_rhs->steps));
    TORCH_CHECK(step_rhs->steps == 1 || end->carry,
                "tensormass: steps > 1 needs carry (each step starts from the state the last one carried)");
    cg_check(step_rhs->rest, "rest", rhs, rhs.scalar_type(), rhs.sizes());
    cg_check(step_rhs->external, "external", rhs, rhs.scalar_type(), rhs.sizes());
    cg_check(step_rhs->u, "u", rhs, rhs.scalar_type(), rhs.sizes());
    const std::pair<const at::Tensor*, const char*> read[] = {{&end->x, "state_x"}, {&end->v, "state_v"},
                                                              {&step_rhs->rest, "rest"},
                                                              {&step_rhs->external, "external"}};
    for (const auto& named : read) {
      check_no_overlap(step_rhs->u, "u", *named.first, named.second);
      check_no_overlap(rhs, "rhs", *named.first, named.second);
    }
    check_no_overlap(rhs, "rhs", step_rhs->u, "u");
    if (step_rhs->planes.given) {
      for (const auto& named : read) {
        check_no_overlap(step_rhs->planes.node_stiffness, "node_stiffness", *named.first, named.second);
      }
    }
  }
  at::Tensor no_dots;
  bool ran = false;
  run_hooke_node_system<L>(rhs, neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff, node_stiffness,
                           r, no_dots, [&](const auto& k, int64_t) {
    using S = typename std::decay_t<decltype(k)>::Scalar;
    PipelinedSolve<S> s;
    set_cg_iterates<S>(s, x, r, p, rhs.data_ptr<S>(), tol_sq, threshold, rhs_sq, rr, alpha, beta, status, iterations,
                       max_iter);
    s.exchange = exchange.data_ptr<S>();
    s.sums = sums.data_ptr<double>();
    s.counters = counters.data_ptr<int32_t>();
    s.chunk_nodes = chunk_nodes;
    s.chunk_slots = chunk_slots;
    s.max_slots = neighbor.size(0);
    if (end != nullptr) {
      s.end.update = euler_update_of<S>(end->x, end->v, x, end->dv_imposed, end->h, end->x_new, end->v_new, end->carry);
      s.end.summary = step_summary_of<S>(status, iterations, rr, rhs_sq, end->norms, end->summary, end->ring,
                                         end->ring_pos);
      s.end.sums = end->sums.data_ptr<double>();
      s.end.counter = end->counter.data_ptr<int32_t>();
    }
    if (step_rhs != nullptr) {
      s.step_rhs.rest = step_rhs->rest.data_ptr<S>();
      s.step_rhs.external = step_rhs->external.data_ptr<S>();
      s.step_rhs.h = static_cast<S>(end->h);
      s.step_rhs.c_w = static_cast<S>(step_rhs->w_coef);
      s.step_rhs.rayleigh_mass = static_cast<S>(step_rhs->rayleigh_mass);
      if (step_rhs->planes.given) {
        s.step_rhs.plane_normals = step_rhs->planes.normals.data_ptr<S>();
        s.step_rhs.plane_offsets = step_rhs->planes.offsets.data_ptr<S>();
        s.step_rhs.plane_stiffness = step_rhs->planes.stiffness.data_ptr<S>();
        s.step_rhs.planes = step_rhs->planes.normals.size(0);
        s.step_rhs.node_stiffness = step_rhs->planes.node_stiffness.data_ptr<S>();
      }
      s.step_rhs.u = step_rhs->u.data_ptr<S>();
      s.step_rhs.rhs = rhs.data_ptr<S>();
      s.steps = step_rhs->steps;
    }
    ran = L::run_solve(plan, k, s);
  });
  return ran;
}

template <class L>
bool hooke_node_solve(const at::Tensor& neighbor, const at::Tensor& node_k, const at::Tensor& incidences,
                      const c10::optional<at::Tensor>& row_node, const at::Tensor& mass, const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                      const c10::optional<at::Tensor>& node_stiffness, const at::Tensor& rhs, double tol_sq,
                      const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                      int64_t chunk_nodes, int64_t chunk_slots, int64_t max_iter, at::Tensor x, at::Tensor r, at::Tensor p,
                      at::Tensor threshold, at::Tensor rhs_sq, at::Tensor rr, at::Tensor status, at::Tensor alpha,
                      at::Tensor beta, at::Tensor iterations, at::Tensor exchange, at::Tensor sums,
                      at::Tensor counters) {
  return run_hooke_node_solve<L>(neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff, node_stiffness,
                                 rhs, tol_sq, chunk_start, chunk_object, object_chunk, chunk_nodes, chunk_slots,
                                 max_iter, x, r, p, threshold, rhs_sq, rr, status, alpha, beta, iterations, exchange,
                                 sums, counters, nullptr);
}

// hooke_node_solve_step: hooke_node_solve, then the step's end as euler_update does it with the
// solution as dv (v_new = v + dv (+ dv_imposed), x_new = x + h v_new; with `carry` also into x,
// v; the object's |v_new|^2 into norms, the summary [5, B], ring row ring_pos, ring_pos
// advanced), in the same kernel: one launch a step fewer. end_sums [K] float64 over the plan's
// chunks and end_counter [B + 1] int32 (zero between calls) are its work. Returns whether it ran:
// false, having changed nothing, where hooke_node_solve would (then neither is done).
template <class L>
bool hooke_node_solve_step(const at::Tensor& neighbor, const at::Tensor& node_k, const at::Tensor& incidences,
                           const c10::optional<at::Tensor>& row_node, const at::Tensor& mass,
                           const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                           const c10::optional<at::Tensor>& node_stiffness, const at::Tensor& rhs, double tol_sq,
                           const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                           const at::Tensor& object_chunk, int64_t chunk_nodes, int64_t chunk_slots, int64_t max_iter,
                           at::Tensor x, at::Tensor r, at::Tensor p, at::Tensor threshold, at::Tensor rhs_sq,
                           at::Tensor rr, at::Tensor status, at::Tensor alpha, at::Tensor beta, at::Tensor iterations,
                           at::Tensor exchange, at::Tensor sums, at::Tensor counters, at::Tensor state_x,
                           at::Tensor state_v, const c10::optional<at::Tensor>& dv_imposed, double h,
                           at::Tensor x_new, at::Tensor v_new, at::Tensor norms, at::Tensor summary,
                           at::Tensor end_sums, at::Tensor end_counter, const c10::optional<at::Tensor>& ring,
                           const c10::optional<at::Tensor>& ring_pos, bool carry) {
  StepEndTensors end{state_x, state_v, dv_imposed, h, x_new, v_new, norms, summary, end_sums, end_counter, ring,
                     ring_pos, carry};
  return run_hooke_node_solve<L>(neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff, node_stiffness,
                                 rhs, tol_sq, chunk_start, chunk_object, object_chunk, chunk_nodes, chunk_slots,
                                 max_iter, x, r, p, threshold, rhs_sq, rr, status, alpha, beta, iterations, exchange,
                                 sums, counters, &end);
}

// hooke_node_steps: `steps` implicit Euler steps of the hooke tensor form (no imposed
// velocities) in one solve kernel on the GPU, each: the right-hand side as hooke_node_step_rhs
// computes it (into rhs, u = x - rest and, with planes, node_stiffness, at state_x, state_v), then
// hooke_node_solve_step's solve and end (with carry, the next step starts from the state it
// wrote). Bitwise `steps` times hooke_node_step_rhs then hooke_node_solve_step: the graph in
// shared memory, the launches and the gaps between them serve every step. Each step's summary
// goes to ring row ring_pos (advanced), the last also into summary; steps > 1 needs carry.
// Returns whether it ran: false, having changed nothing, where hooke_node_solve would.
template <class L>
bool hooke_node_steps(const at::Tensor& neighbor, const at::Tensor& node_k, const at::Tensor& incidences,
                      const c10::optional<at::Tensor>& row_node, const at::Tensor& mass,
                      const c10::optional<at::Tensor>& free, double c_mass, double c_stiff, const at::Tensor& rest,
                      const at::Tensor& external, double w_coef, double rayleigh_mass,
                      const c10::optional<at::Tensor>& plane_normals, const c10::optional<at::Tensor>& plane_offsets,
                      const c10::optional<at::Tensor>& plane_stiffness, at::Tensor u, at::Tensor rhs,
                      const c10::optional<at::Tensor>& node_stiffness, double tol_sq, const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                      const at::Tensor& object_chunk, int64_t chunk_nodes, int64_t chunk_slots, int64_t max_iter,
                      at::Tensor x, at::Tensor r, at::Tensor p, at::Tensor threshold, at::Tensor rhs_sq,
                      at::Tensor rr, at::Tensor status, at::Tensor alpha, at::Tensor beta, at::Tensor iterations,
                      at::Tensor exchange, at::Tensor sums, at::Tensor counters, at::Tensor state_x,
                      at::Tensor state_v, double h, at::Tensor x_new, at::Tensor v_new, at::Tensor norms,
                      at::Tensor summary, at::Tensor end_sums, at::Tensor end_counter,
                      const c10::optional<at::Tensor>& ring, const c10::optional<at::Tensor>& ring_pos, bool carry,
                      int64_t steps) {
  StepEndTensors end{state_x, state_v, c10::nullopt, h, x_new, v_new, norms, summary, end_sums, end_counter, ring,
                     ring_pos, carry};
  check_values(rhs, "rhs");
  const StepPlanes planes(rhs, plane_normals, plane_offsets, plane_stiffness, node_stiffness);
  TORCH_CHECK(planes.given || !(node_stiffness.has_value() && node_stiffness->defined()),
              "tensormass: node_stiffness is the contact planes' stiffness: it needs plane_normals");
  const StepRhsTensors step_rhs{rest, external, w_coef, rayleigh_mass, planes, u, steps};
  return run_hooke_node_solve<L>(neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff, node_stiffness,
                                 rhs, tol_sq, chunk_start, chunk_object, object_chunk, chunk_nodes, chunk_slots,
                                 max_iter, x, r, p, threshold, rhs_sq, rr, status, alpha, beta, iterations, exchange,
                                 sums, counters, &end, &step_rhs);
}

// ------------------------------------------------------------------ tensor form, stvk

struct StvkTensorArgs {
  at::Tensor u, du, elements, tb, tc, td;
  int64_t num_elements, nodes_per_element, dim;
  at::ScalarType index_type;
  StvkTensorArgs(const at::Tensor& u_, const c10::optional<at::Tensor>& du_, const at::Tensor& elements_,
                 const at::Tensor& b, const at::Tensor& c, const at::Tensor& d)
      : u(u_), elements(elements_), tb(b), tc(c), td(d) {
    check_values(u, "u");
    dim = u.size(1);
    index_type = index_type_of(elements, "elements");
    TORCH_CHECK(elements.dim() == 2, "tensormass: elements must be [N, n], got shape ", shape_str(elements.sizes()));
    num_elements = elements.size(0);
    const int64_t n = nodes_per_element = elements.size(1);
    check_index_tensor(elements, "elements", u, index_type, {num_elements, n});
    if (du_.has_value() && du_->defined()) {
      du = *du_;
      check_float_tensor(du, "du", u, u.sizes());
    }
    check_float_tensor(tb, "tensor_b", u, {num_elements, n, n, dim, dim});
    check_float_tensor(tc, "tensor_c", u, {num_elements, n, n, n, dim});
    check_float_tensor(td, "tensor_d", u, {num_elements, n, n, n, n});
    dispatch_kind(n, dim, [](auto, auto) {});
  }
};

template <class L, bool DFORCE>
void run_stvk_tensor_kernel1(const StvkTensorArgs& a, const at::Tensor& force_index, at::Tensor& out) {
  dispatch_scalar(a.u.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(a.index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_kind(a.nodes_per_element, a.dim, [&](auto nn_c, auto d_c) {
        constexpr int NN = decltype(nn_c)::value;
        constexpr int D = decltype(d_c)::value;
        dispatch_bool(force_index.defined(), [&](auto padded_c) {
          constexpr bool PADDED = decltype(padded_c)::value;
          TensorStvkKernel<DFORCE, NN, D, S, I, PADDED> k;
          k.u = a.u.data_ptr<S>();
          k.du = a.du.defined() ? a.du.data_ptr<S>() : nullptr;
          k.elements = a.elements.data_ptr<I>();
          k.tb = a.tb.data_ptr<S>();
          k.tc = a.tc.data_ptr<S>();
          k.td = a.td.data_ptr<S>();
          k.write.out = out.data_ptr<S>();
          set_padded(k.write, force_index, a.u.size(0));
          L::run(a.num_elements, k, L::kElementBlock);
        });
      });
    });
  });
}

template <class L>
at::Tensor tensor_stvk_element_forces(const at::Tensor& u, const at::Tensor& elements, const at::Tensor& b,
                                      const at::Tensor& c, const at::Tensor& d) {
  StvkTensorArgs a(u, c10::nullopt, elements, b, c, d);
  typename L::Guard guard(u.device());
  at::Tensor out = at::empty({a.num_elements, a.nodes_per_element, a.dim}, u.options());
  run_stvk_tensor_kernel1<L, false>(a, at::Tensor(), out);
  return out;
}

template <class L>
at::Tensor tensor_stvk_element_dforces(const at::Tensor& u, const at::Tensor& du, const at::Tensor& elements,
                                       const at::Tensor& b, const at::Tensor& c, const at::Tensor& d) {
  StvkTensorArgs a(u, du, elements, b, c, d);
  typename L::Guard guard(u.device());
  at::Tensor out = at::empty({a.num_elements, a.nodes_per_element, a.dim}, u.options());
  run_stvk_tensor_kernel1<L, true>(a, at::Tensor(), out);
  return out;
}

template <class L, bool DFORCE>
at::Tensor tensor_stvk_padded_impl(const StvkTensorArgs& a, const at::Tensor& force_index, int64_t num_slots,
                                   const at::Tensor* incidences) {
  check_plan(a.u, force_index, num_slots, a.index_type, {a.num_elements, a.nodes_per_element});
  if (incidences != nullptr) check_incidences(a.u, *incidences, a.index_type);
  typename L::Guard guard(a.u.device());
  at::Tensor partial = at::empty({num_slots, a.u.size(0), a.dim}, a.u.options());
  run_stvk_tensor_kernel1<L, DFORCE>(a, force_index, partial);
  if (incidences == nullptr) return partial;
  at::Tensor out = at::empty({a.u.size(0), a.dim}, a.u.options());
  run_gather<L>(partial, *incidences, at::Tensor(), out);
  return out;
}

template <class L>
at::Tensor tensor_stvk_partial_forces(const at::Tensor& u, const at::Tensor& elements, const at::Tensor& force_index,
                                      int64_t num_slots, const at::Tensor& b, const at::Tensor& c,
                                      const at::Tensor& d) {
  StvkTensorArgs a(u, c10::nullopt, elements, b, c, d);
  return tensor_stvk_padded_impl<L, false>(a, force_index, num_slots, nullptr);
}

template <class L>
at::Tensor tensor_stvk_partial_dforces(const at::Tensor& u, const at::Tensor& du, const at::Tensor& elements,
                                       const at::Tensor& force_index, int64_t num_slots, const at::Tensor& b,
                                       const at::Tensor& c, const at::Tensor& d) {
  StvkTensorArgs a(u, du, elements, b, c, d);
  return tensor_stvk_padded_impl<L, true>(a, force_index, num_slots, nullptr);
}

template <class L>
at::Tensor tensor_stvk_forces(const at::Tensor& u, const at::Tensor& elements, const at::Tensor& force_index,
                              int64_t num_slots, const at::Tensor& incidences, const at::Tensor& b,
                              const at::Tensor& c, const at::Tensor& d) {
  StvkTensorArgs a(u, c10::nullopt, elements, b, c, d);
  return tensor_stvk_padded_impl<L, false>(a, force_index, num_slots, &incidences);
}

template <class L>
at::Tensor tensor_stvk_dforces(const at::Tensor& u, const at::Tensor& du, const at::Tensor& elements,
                               const at::Tensor& force_index, int64_t num_slots, const at::Tensor& incidences,
                               const at::Tensor& b, const at::Tensor& c, const at::Tensor& d) {
  StvkTensorArgs a(u, du, elements, b, c, d);
  return tensor_stvk_padded_impl<L, true>(a, force_index, num_slots, &incidences);
}

}  // namespace tensormass
