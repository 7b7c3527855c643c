// Host side of the stress-form ops (schemas: schema.cpp), written once for the CPU and CUDA: input
// checks (common/stress_args.h: StressArgs), allocation and compile-time dispatch (element kind,
// model, scalar type, index type) onto the per-item functors of kernels.h. The backend is a template
// parameter `L` (a "launcher": common/cpu_launcher.h, at::parallel_for; common/cuda_launcher.cuh,
// one thread per item, on the current stream) that runs a functor over n items: cpu.cpp and cuda.cu
// instantiate these functions and register them (register_stress_ops).
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Optional.h>
#include <torch/library.h>

#include <cstdint>
#include <string>

#include "common/checks.h"
#include "common/dispatch.h"
#include "common/gather.h"
#include "common/kernel_io.h"
#include "common/stress_args.h"
#include "stress/kernels.h"

namespace tensormass {

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

// Registers the implementations of the stress-form ops of one backend (launcher L) under its
// TORCH_LIBRARY_IMPL (cpu.cpp, cuda.cu); the schemas: schema.cpp.
template <class L>
void register_stress_ops(torch::Library& m) {
  m.impl("stress_element_forces", &stress_element_forces<L>);
  m.impl("stress_element_dforces", &stress_element_dforces<L>);
  m.impl("stress_partial_forces", &stress_partial_forces<L>);
  m.impl("stress_partial_dforces", &stress_partial_dforces<L>);
  m.impl("stress_forces", &stress_forces<L>);
  m.impl("stress_dforces", &stress_dforces<L>);
  m.impl("corotational_rotations", &corotational_rotations<L>);
}

}  // namespace tensormass
