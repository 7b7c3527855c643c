// Host side of the element-removal ops (schemas: schema.cpp; kernels: kernels.h), written once for
// the CPU and CUDA: argument checks, dispatch and one launch through `L` (common/cpu_launcher.h,
// common/cuda_launcher.cuh); cpu.cpp and cuda.cu register them (register_topology_ops). No
// allocation, no host synchronisation: a removal between captured steps costs a launch or two.
#pragma once

#include <ATen/core/Tensor.h>
#include <torch/library.h>

#include <cstdint>
#include <string>

#include "common/checks.h"
#include "common/dispatch.h"
#include "topology/kernels.h"

namespace tensormass {

// An index tensor of `index_type` on `like`'s device with `dims` dimensions, named in messages.
inline void check_index_dims(const at::Tensor& t, const char* name, const at::Tensor& like, at::ScalarType index_type,
                             int64_t dims, const char* like_name) {
  TORCH_CHECK(t.defined() && t.dim() == dims, "tensormass: ", name, " must have ", std::to_string(dims),
              " dimension(s)");
  check_index_tensor(t, name, like, index_type, t.sizes(), like_name);
}

// topology_refresh_nodes: see schema.cpp.
template <class L>
void topology_refresh_nodes(const at::Tensor& elements, const at::Tensor& rows, const at::Tensor& node_slots,
                            const at::Tensor& element_share, const at::Tensor& removed, at::Tensor mass,
                            at::Tensor node_elements) {
  TORCH_CHECK(mass.defined() && mass.dim() == 1, "tensormass: mass must be [V]");
  TORCH_CHECK(mass.scalar_type() == at::kFloat || mass.scalar_type() == at::kDouble,
              "tensormass: mass must be float32 or float64, got ", dtype_str(mass.scalar_type()));
  TORCH_CHECK(mass.is_contiguous(), "tensormass: mass must be contiguous (call .contiguous())");
  const int64_t num_nodes = mass.size(0);
  const at::ScalarType index_type = index_type_of(elements, "elements");
  check_index_dims(elements, "elements", mass, index_type, 2, "mass");
  check_index_dims(rows, "rows", mass, index_type, 1, "mass");
  check_index_dims(node_slots, "node_slots", mass, index_type, 2, "mass");
  TORCH_CHECK(node_slots.size(1) == num_nodes, "tensormass: node_slots has shape ", shape_str(node_slots.sizes()),
              "; expected [S, ", std::to_string(num_nodes), "] (mass is [V])");
  TORCH_CHECK(element_share.dim() == 1, "tensormass: element_share must be [N_model]");
  check_node_tensor(element_share, "element_share", mass, {element_share.size(0)}, "mass");
  check_flags(removed, "removed", mass, element_share.size(0), "mass");
  TORCH_CHECK(node_elements.defined() && node_elements.scalar_type() == at::kInt,
              "tensormass: node_elements must be int32");
  TORCH_CHECK(node_elements.device() == mass.device() && node_elements.sizes() == mass.sizes() &&
                  node_elements.is_contiguous(),
              "tensormass: node_elements must be a contiguous [V] tensor on mass's device");
  typename L::Guard guard(mass.device());
  dispatch_scalar(mass.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      RefreshNodesKernel<S, I> k;
      k.elements = elements.data_ptr<I>();
      k.rows = rows.data_ptr<I>();
      k.nodes_per_element = static_cast<int>(elements.size(1));
      k.node_slots = node_slots.data_ptr<I>();
      k.num_slots = node_slots.size(0);
      k.num_nodes = num_nodes;
      k.element_share = element_share.data_ptr<S>();
      k.removed = removed.data_ptr<bool>();
      k.mass = mass.data_ptr<S>();
      k.node_elements = node_elements.data_ptr<int32_t>();
      L::run(rows.size(0) * elements.size(1), k, L::kNodeBlock);
    });
  });
}

// topology_refresh_hooke_edges: see schema.cpp.
template <class L>
void topology_refresh_hooke_edges(const at::Tensor& rest, const at::Tensor& elements, const at::Tensor& rows,
                                  const at::Tensor& element_edges, const at::Tensor& edge_slots,
                                  const at::Tensor& element_row, const at::Tensor& removed,
                                  const at::Tensor& measure, const at::Tensor& young, const at::Tensor& poisson,
                                  at::Tensor edge_k) {
  check_values(rest, "rest");
  const int64_t dim = rest.size(1);
  const at::ScalarType index_type = index_type_of(elements, "elements");
  check_index_dims(elements, "elements", rest, index_type, 2, "rest");
  const int64_t num_elements = elements.size(0), nn = elements.size(1);
  check_index_dims(rows, "rows", rest, index_type, 1, "rest");
  check_index_tensor(element_edges, "element_edges", rest, index_type, {num_elements, nn * (nn - 1) / 2}, "rest");
  TORCH_CHECK(edge_k.defined() && edge_k.dim() == 3, "tensormass: edge_k must be [Ed, d, d]");
  const int64_t num_edges = edge_k.size(0);
  check_float_tensor(edge_k, "edge_k", rest, {num_edges, dim, dim});
  check_index_dims(edge_slots, "edge_slots", rest, index_type, 2, "rest");
  TORCH_CHECK(edge_slots.size(1) == num_edges, "tensormass: edge_slots has shape ", shape_str(edge_slots.sizes()),
              "; expected [S, ", std::to_string(num_edges), "] (edge_k is [Ed, d, d])");
  check_index_dims(element_row, "element_row", rest, index_type, 1, "rest");
  check_flags(removed, "removed", rest, element_row.size(0), "rest");
  check_float_tensor(measure, "measure", rest, {num_elements});
  check_float_tensor(young, "young", rest, {num_elements});
  check_float_tensor(poisson, "poisson", rest, {num_elements});
  typename L::Guard guard(rest.device());
  dispatch_scalar(rest.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_kind(nn, dim, [&](auto nn_c, auto d_c) {
        constexpr int NN = decltype(nn_c)::value;
        constexpr int D = decltype(d_c)::value;
        RefreshHookeEdgesKernel<NN, D, S, I> k;
        k.rest = rest.data_ptr<S>();
        k.elements = elements.data_ptr<I>();
        k.rows = rows.data_ptr<I>();
        k.element_edges = element_edges.data_ptr<I>();
        k.edge_slots = edge_slots.data_ptr<I>();
        k.num_slots = edge_slots.size(0);
        k.num_edges = num_edges;
        k.element_row = element_row.data_ptr<I>();
        k.removed = removed.data_ptr<bool>();
        k.measure = measure.data_ptr<S>();
        k.young = young.data_ptr<S>();
        k.poisson = poisson.data_ptr<S>();
        k.edge_k = edge_k.data_ptr<S>();
        L::run(rows.size(0) * (NN * (NN - 1) / 2), k, L::kElementBlock);
      });
    });
  });
}

// Registers the implementations of the topology ops of one backend (launcher L) under its
// TORCH_LIBRARY_IMPL (cpu.cpp, cuda.cu); the schemas: schema.cpp.
template <class L>
void register_topology_ops(torch::Library& m) {
  m.impl("topology_refresh_nodes", &topology_refresh_nodes<L>);
  m.impl("topology_refresh_hooke_edges", &topology_refresh_hooke_edges<L>);
}

}  // namespace tensormass
