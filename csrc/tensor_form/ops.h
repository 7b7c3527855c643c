// Host side of the tensor-form ops (schemas: schema.cpp), written once for the CPU and CUDA: input
// checks (HookeTensorArgs, StvkTensorArgs), allocation and compile-time dispatch (scalar type, index
// type, dimension, element kind, layout) onto the per-item functors of kernels.h, run by the
// launcher `L` (common/cpu_launcher.h, common/cuda_launcher.cuh); cpu.cpp and cuda.cu instantiate
// these functions and register them (register_tensor_form_ops).
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Optional.h>
#include <torch/library.h>

#include <cstdint>

#include "common/checks.h"
#include "common/dispatch.h"
#include "common/gather.h"
#include "common/kernel_io.h"
#include "tensor_form/kernels.h"

namespace tensormass {

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

// Registers the implementations of the tensor-form ops of one backend (launcher L) under its
// TORCH_LIBRARY_IMPL (cpu.cpp, cuda.cu); the schemas: schema.cpp.
template <class L>
void register_tensor_form_ops(torch::Library& m) {
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

}  // namespace tensormass
