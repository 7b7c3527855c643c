// Host side of the node graph ops (schemas: schema.cpp), written once for the CPU and CUDA: the CG
// matvec over the node graph (hooke_node_system; hooke_node_system_alpha, ending in the step
// length; its kernel and host side: common/node_graph.h), implicit Euler's right-hand side over it
// (hooke_node_step_rhs) and a stress-form group's tangent written as the graph's slot tensors
// (stress_tangent_node_k). Input checks, allocation and compile-time dispatch onto the per-item
// functors of kernels.h and common/, run by the launcher `L` (common/cpu_launcher.h,
// common/cuda_launcher.cuh); cpu.cpp and cuda.cu instantiate these functions and register them
// (register_node_graph_ops).
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Optional.h>
#include <torch/library.h>

#include <cstdint>
#include <string>
#include <tuple>
#include <utility>

#include "common/alpha_launch.h"
#include "common/checks.h"
#include "common/dispatch.h"
#include "common/node_graph.h"
#include "common/step_rhs.h"
#include "common/stress_args.h"
#include "node_graph/kernels.h"

namespace tensormass {

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

template <class L>
void hooke_node_system_alpha(const at::Tensor& p, const at::Tensor& neighbor, const at::Tensor& node_k,
                             const at::Tensor& incidences, const c10::optional<at::Tensor>& row_node,
                             const at::Tensor& mass,
                             const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                             const c10::optional<at::Tensor>& node_stiffness, at::Tensor ap,
                             const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                             const at::Tensor& object_chunk, const at::Tensor& rr, at::Tensor status,
                             at::Tensor alpha, at::Tensor scratch, at::Tensor counter,
                             const c10::optional<at::Tensor>& add) {
  check_values(p, "p");
  TORCH_CHECK(ap.defined(), "tensormass: ap is undefined");
  at::Tensor no_dots;
  run_hooke_node_system<L, true>(p, neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff,
                                 node_stiffness, ap, no_dots,
                                 alpha_launch<L>(p, chunk_start, chunk_object, object_chunk, rr, status, alpha,
                                                 scratch, counter), add);
}

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

// node_graph_write_edges: see schema.cpp.
template <class L>
void node_graph_write_edges(const at::Tensor& edge_ids, const at::Tensor& edges, const at::Tensor& force_index,
                            const at::Tensor& edge_k, at::Tensor node_k, const c10::optional<at::Tensor>& row_of) {
  TORCH_CHECK(edge_k.defined() && edge_k.dim() == 3, "tensormass: edge_k must be [Ed, d, d]");
  TORCH_CHECK(edge_k.scalar_type() == at::kFloat || edge_k.scalar_type() == at::kDouble,
              "tensormass: edge_k must be float32 or float64, got ", dtype_str(edge_k.scalar_type()));
  TORCH_CHECK(edge_k.is_contiguous(), "tensormass: edge_k must be contiguous (call .contiguous())");
  const int64_t num_edges = edge_k.size(0), dim = edge_k.size(1);
  const at::ScalarType index_type = index_type_of(edges, "edges");
  check_index_tensor(edges, "edges", edge_k, index_type, {num_edges, 2}, "edge_k");
  check_index_tensor(force_index, "force_index", edge_k, index_type, {num_edges, 2}, "edge_k");
  TORCH_CHECK(node_k.defined() && node_k.dim() == 4, "tensormass: node_k must be [N_n, V, d, d]");
  check_node_tensor(node_k, "node_k", edge_k, {node_k.size(0), node_k.size(1), dim, dim}, "edge_k");
  const at::ScalarType id_type = index_type_of(edge_ids, "edge_ids");
  TORCH_CHECK(edge_ids.dim() == 1, "tensormass: edge_ids must be [M], got shape ", shape_str(edge_ids.sizes()));
  TORCH_CHECK(edge_ids.device() == edge_k.device(), "tensormass: edge_ids is on ", edge_ids.device().str(),
              " but edge_k is on ", edge_k.device().str());
  TORCH_CHECK(edge_ids.is_contiguous(), "tensormass: edge_ids must be contiguous (call .contiguous())");
  const bool by_rows = row_of.has_value() && row_of->defined();
  if (by_rows) check_index_tensor(*row_of, "row_of", edge_k, index_type, {node_k.size(1)}, "edge_k");
  typename L::Guard guard(edge_k.device());
  dispatch_scalar(edge_k.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_index(id_type, [&](auto j_tag) {
        using J = decltype(j_tag);
        dispatch_dim(dim, [&](auto d_c) {
          constexpr int D = decltype(d_c)::value;
          WriteEdgesKernel<D, S, I, J> k;
          k.edge_ids = edge_ids.data_ptr<J>();
          k.edges = edges.data_ptr<I>();
          k.force_index = force_index.data_ptr<I>();
          k.edge_k = edge_k.data_ptr<S>();
          k.row_of = by_rows ? row_of->data_ptr<I>() : nullptr;
          k.num_nodes = node_k.size(1);
          k.node_k = node_k.data_ptr<S>();
          L::run(edge_ids.numel(), k, L::kNodeBlock);
        });
      });
    });
  });
}

// node_graph_rebuild_hooke_rows: see schema.cpp. Three launches (kernels.h): each touched row's
// elements' first nodes, then its neighbours, a (slot, node) an item, then its blocks a (node,
// slot) an item.
template <class L>
void node_graph_rebuild_hooke_rows(const at::Tensor& pair_k, const at::Tensor& elements, const at::Tensor& node_slots,
                                   const at::Tensor& alive, const at::Tensor& touched,
                                   const c10::optional<at::Tensor>& row_of, int64_t max_slots, at::Tensor neighbor,
                                   at::Tensor node_k, at::Tensor incidences, at::Tensor status, at::Tensor firsts) {
  TORCH_CHECK(node_k.defined() && node_k.dim() == 4, "tensormass: node_k must be [N_n, V, d, d]");
  TORCH_CHECK(node_k.scalar_type() == at::kFloat || node_k.scalar_type() == at::kDouble,
              "tensormass: node_k must be float32 or float64, got ", dtype_str(node_k.scalar_type()));
  TORCH_CHECK(node_k.is_contiguous(), "tensormass: node_k must be contiguous (call .contiguous())");
  const int64_t num_graph_slots = node_k.size(0), num_nodes = node_k.size(1), dim = node_k.size(2);
  const at::ScalarType index_type = index_type_of(elements, "elements");
  TORCH_CHECK(elements.dim() == 2 && (elements.size(1) == 3 || elements.size(1) == 4),
              "tensormass: elements must be [N, 4] (tetrahedra) or [N, 3] (triangles), got ",
              shape_str(elements.sizes()));
  check_index_tensor(elements, "elements", node_k, index_type, elements.sizes(), "node_k");
  const int64_t num_elements = elements.size(0), nn = elements.size(1);
  check_float_tensor(pair_k, "pair_k", node_k, {num_elements, nn * (nn - 1) / 2, dim, dim});
  TORCH_CHECK(node_slots.dim() == 2 && node_slots.size(1) == num_nodes, "tensormass: node_slots must be [S, ",
              std::to_string(num_nodes), "] (node_k is [N_n, V, d, d]), got ", shape_str(node_slots.sizes()));
  check_index_tensor(node_slots, "node_slots", node_k, index_type, node_slots.sizes(), "node_k");
  check_flags(alive, "alive", node_k, num_elements, "node_k");
  check_index_tensor(touched, "touched", node_k, at::kByte, {num_nodes}, "node_k");
  check_index_tensor(neighbor, "neighbor", node_k, index_type, {num_graph_slots, num_nodes}, "node_k");
  check_index_tensor(incidences, "incidences", node_k, index_type, {num_nodes}, "node_k");
  check_index_tensor(status, "status", node_k, at::kInt, {1}, "node_k");
  check_index_tensor(firsts, "firsts", node_k, at::kInt, node_slots.sizes(), "node_k");
  const bool by_rows = row_of.has_value() && row_of->defined();
  if (by_rows) check_index_tensor(*row_of, "row_of", node_k, index_type, {num_nodes}, "node_k");
  TORCH_CHECK(max_slots >= 0 && max_slots <= num_graph_slots, "tensormass: max_slots is ", std::to_string(max_slots),
              "; it must be in [0, ", std::to_string(num_graph_slots), "] (neighbor's slots)");
  typename L::Guard guard(node_k.device());
  dispatch_scalar(node_k.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_kind(nn, dim, [&](auto nn_c, auto d_c) {
        constexpr int NN = decltype(nn_c)::value;
        constexpr int D = decltype(d_c)::value;
        RebuildRowFirstsKernel<NN, I> first;
        first.elements = elements.data_ptr<I>();
        first.node_slots = node_slots.data_ptr<I>();
        first.num_slots = node_slots.size(0);
        first.num_nodes = num_nodes;
        first.alive = alive.data_ptr<bool>();
        first.touched = touched.data_ptr<uint8_t>();
        first.firsts = firsts.data_ptr<int32_t>();
        L::run(node_slots.numel(), first, L::kNodeBlock);
        RebuildRowNeighborsKernel<NN, I> rows;
        rows.elements = elements.data_ptr<I>();
        rows.node_slots = node_slots.data_ptr<I>();
        rows.num_slots = node_slots.size(0);
        rows.num_nodes = num_nodes;
        rows.touched = touched.data_ptr<uint8_t>();
        rows.firsts = firsts.data_ptr<int32_t>();
        rows.row_of = by_rows ? row_of->data_ptr<I>() : nullptr;
        rows.max_slots = max_slots;
        rows.neighbor = neighbor.data_ptr<I>();
        rows.incidences = incidences.data_ptr<I>();
        rows.status = status.data_ptr<int32_t>();
        L::run(node_slots.numel(), rows, L::kNodeBlock);
        RebuildRowBlocksKernel<NN, D, S, I> k;
        k.pair_k = pair_k.data_ptr<S>();
        k.elements = elements.data_ptr<I>();
        k.node_slots = node_slots.data_ptr<I>();
        k.num_slots = node_slots.size(0);
        k.num_nodes = num_nodes;
        k.alive = alive.data_ptr<bool>();
        k.touched = touched.data_ptr<uint8_t>();
        k.row_of = by_rows ? row_of->data_ptr<I>() : nullptr;
        k.graph_slots = num_graph_slots;
        k.neighbor = neighbor.data_ptr<I>();
        k.incidences = incidences.data_ptr<I>();
        k.node_k = node_k.data_ptr<S>();
        L::run(num_nodes * num_graph_slots, k, L::kNodeBlock);
      });
    });
  });
}

// Registers the implementations of the node graph ops of one backend (launcher L) under its
// TORCH_LIBRARY_IMPL (cpu.cpp, cuda.cu); the schemas: schema.cpp.
template <class L>
void register_node_graph_ops(torch::Library& m) {
  m.impl("hooke_node_system", &hooke_node_system<L>);
  m.impl("hooke_node_system_alpha", &hooke_node_system_alpha<L>);
  m.impl("hooke_node_step_rhs", &hooke_node_step_rhs<L>);
  m.impl("stress_tangent_node_k", &stress_tangent_node_k<L>);
  m.impl("node_graph_write_edges", &node_graph_write_edges<L>);
  m.impl("node_graph_rebuild_hooke_rows", &node_graph_rebuild_hooke_rows<L>);
}

}  // namespace tensormass
