// Host side of the gather ops (schemas: schema.cpp), written once for the CPU and CUDA: kernel 2 of
// the paper's Algorithm 1 alone (gather_partial, node_gather) and with the implicit-Euler system
// epilogue (gather_system: the CG matvec of the element path; gather_system_alpha: ending in the
// step length). Input checks, allocation and compile-time dispatch onto the per-item functors of
// kernels.h and common/, run by the launcher `L` (common/cpu_launcher.h, common/cuda_launcher.cuh);
// cpu.cpp and cuda.cu instantiate these functions and register them (register_gather_ops).
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Optional.h>
#include <torch/library.h>

#include <cstdint>
#include <string>
#include <tuple>
#include <type_traits>

#include "common/alpha_launch.h"
#include "common/checks.h"
#include "common/dispatch.h"
#include "common/gather.h"
#include "common/system_epilogue.h"
#include "gather/kernels.h"

namespace tensormass {

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
//
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
                                      p_dot_ap, false, [&](auto& k) {
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

// Registers the implementations of the gather ops of one backend (launcher L) under its
// TORCH_LIBRARY_IMPL (cpu.cpp, cuda.cu); the schemas: schema.cpp.
template <class L>
void register_gather_ops(torch::Library& m) {
  m.impl("gather_partial", &gather_partial<L>);
  m.impl("node_gather", &node_gather<L>);
  m.impl("gather_system", &gather_system<L>);
  m.impl("gather_system_alpha", &gather_system_alpha<L>);
}

}  // namespace tensormass
