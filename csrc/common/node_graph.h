// The node graph of the hooke tensor form (and of a stress-form group's tangent on its edges): its
// CG matvec in one kernel (HookeNodeGraph, NodeHookeSystemKernel) and the host side of that kernel
// (check_hooke_node_graph, set_hooke_node_graph, run_hooke_node_system). Shared by the node_graph
// family (hooke_node_system, hooke_node_system_alpha, hooke_node_step_rhs) and the solve family
// (the whole solves, whose matvec it is; solve/cg_persistent.cuh, solve/cg_pipelined.cuh).
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <c10/util/Optional.h>

#include <cstdint>
#include <tuple>
#include <type_traits>

#include "common/checks.h"
#include "common/dispatch.h"
#include "common/element_math.h"
#include "common/kernel_io.h"
#include "common/system_epilogue.h"

namespace tensormass {

// The CG matvec of the hooke tensor form in one kernel, one item per node: the product with the
// stiffness is a sparse block product over the node graph,
//   (K p)_i = sum_{s < incidences[i]} -Kdir[s][i] (p[neighbor[s][i]] - p_i),
// with Kdir = K_e where i is the first node of edge e and K_e^T where it is the second, in the
// slots of the padded plan (slot-major "ELL" arrays neighbor [N_n, V], node_k [N_n, V, D, D]: the
// threads of a warp read consecutive nodes of one slot). Each term is tensor_hooke_edge's force
// on its first node with (Kdir, p_i, p_j): for the second node of an edge, w' = p_i - p_j = -w
// and -(K^T w') = K^T w exactly, so every term, and the sum in slot order, is bitwise the one
// kernel 1 writes and kernel 2 adds; no PartialForce buffer is written or read back.
//
// HookeNodeGraph holds the graph and sums that product for any field w read through load_p
// (f_i = sum_s -Kdir[s][i] (w_j - w_i), the elastic force of the displacements w): the matvec
// reads p, the step's right-hand side (NodeHookeStepRhsKernel) reads (x - rest) + c v.
//
// The graph's arrays are stored by ROW: row r holds the slots of node row_node[r] (a permutation
// of the nodes; nullptr: row r is node r). Rows are the nodes sorted by slot count within windows
// of each object (ops.node_graph.node_graph_rows), so that the threads of a warp, which take consecutive
// rows, walk as many slots each and read the slot arrays side by side: on the paper beam, whose
// nodes alternate 10 and 26 slots, a node-ordered matvec idles half its lanes (docs/node-graph.md;
// benchmarks/probes/node_k_layout_probe.py). Every result is per node and its slots are summed in
// slot order, so the row order changes no value.
template <int D, typename S, typename I>
struct HookeNodeGraph {
  const I* neighbor;    // [N_n, V] by row: the other NODE of the edge in each slot
  const S* node_k;      // [N_n, V, D, D] by row: Kdir of each slot
  const I* incidences;  // [V] by row: the row's slot count
  const I* row_node;    // [V] the node of each row, or nullptr (the identity)
  int64_t num_nodes;

  TM_HD int64_t node_of(int64_t row) const { return row_node != nullptr ? static_cast<int64_t>(ld(row_node + row)) : row; }

  // Slots are loaded kBatch at a time before any is used: a thread has only a few nodes' worth
  // of parallelism (one node), so its loads must be in flight together, not one dependent chain
  // (neighbor -> w_j) per slot; the terms are still added in slot order.
  static constexpr int kBatch = 4;

  // The neighbour in slot s of node i, read from the graph's arrays.
  struct GlobalNeighbors {
    const I* neighbor;
    int64_t num_nodes;
    TM_HD int64_t operator()(int64_t s, int64_t i) const { return static_cast<int64_t>(ld(neighbor + s * num_nodes + i)); }
  };

  // The forces of row `row` (node i, wi = w_i already loaded); load_p(field + j * D + a) reads w_j[a].
  template <class LoadP>
  TM_HD void add_forces(int64_t row, int64_t i, const S* field, const S (&wi)[D], const LoadP& load_p,
                        S (&acc)[D]) const {
    add_forces(row, i, static_cast<int64_t>(ld(incidences + row)), GlobalNeighbors{neighbor, num_nodes}, field, wi,
               load_p, acc);
  }

  // The same with the row's slot count and neighbours given (neighbors(s, row): the persistent CG
  // keeps them in shared memory across its iterations). k[q] of a slot past the count is never
  // loaded and never read (the second loop breaks first); g++ cannot see that and warns at every
  // instantiation, so its uninitialized-use warnings are off here (zeroing the batch would cost the
  // GPU loop its registers' moves).
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic push
#pragma GCC diagnostic ignored "-Wuninitialized"
#pragma GCC diagnostic ignored "-Wmaybe-uninitialized"
#endif
  template <class Neighbors, class LoadP>
  TM_HD void add_forces(int64_t row, int64_t i, int64_t count, const Neighbors& neighbors, const S* field,
                        const S (&wi)[D], const LoadP& load_p, S (&acc)[D]) const {
    for (int64_t s0 = 0; s0 < count; s0 += kBatch) {
      int64_t j[kBatch];
      TM_UNROLL for (int q = 0; q < kBatch; ++q) j[q] = s0 + q < count ? neighbors(s0 + q, row) : i;
      S k[kBatch][D][D], wj[kBatch][D];
      TM_UNROLL for (int q = 0; q < kBatch; ++q) {
        if (s0 + q < count) load_matrix<D, D, S>(node_k + ((s0 + q) * num_nodes + row) * (D * D), k[q]);
        TM_UNROLL for (int a = 0; a < D; ++a) wj[q][a] = load_p(field + j[q] * D + a);
      }
      TM_UNROLL for (int q = 0; q < kBatch; ++q) {
        if (s0 + q >= count) break;
        S f[2][D];
        tensor_hooke_edge<D, S>(k[q], wi, wj[q], f);  // f[1] is unused (dead code for the compiler)
        TM_UNROLL for (int a = 0; a < D; ++a) acc[a] += f[0][a];
      }
    }
  }
#if defined(__GNUC__) && !defined(__clang__)
#pragma GCC diagnostic pop
#endif
};

template <int D, typename S, typename I, bool HAS_FREE, bool HAS_NODE_K, bool HAS_ADD = false>
struct NodeHookeSystemKernel {
  using Scalar = S;
  using Index = I;
  static constexpr int kDim = D;
  static constexpr bool kHasAdd = HAS_ADD;
  const S* p;  // [V, D]
  HookeNodeGraph<D, S, I> graph;
  SystemEpilogue<D, S, HAS_FREE, HAS_NODE_K, HAS_ADD> epilogue;

  // For the node i of row `row`: Ap_i, and p_i . Ap_i (returned): the CG step-length kernels call
  // this over rows (cg_reduce.cuh); load_p reads p (the persistent CG's DirectionLoader forms
  // r + beta p with plain loads: p changes during that kernel, and the read-only cache of ld()
  // may hold stale copies).
  template <class LoadP = Loader>
  TM_HD S apply(int64_t row, LoadP load_p = LoadP()) const {
    using Global = typename HookeNodeGraph<D, S, I>::GlobalNeighbors;
    return apply(row, static_cast<int64_t>(ld(graph.incidences + row)), Global{graph.neighbor, graph.num_nodes},
                 load_p);
  }

  // apply with the row's slot count and neighbours given (HookeNodeGraph::add_forces).
  template <class Neighbors, class LoadP>
  TM_HD S apply(int64_t row, int64_t count, const Neighbors& neighbors, LoadP load_p) const {
    const int64_t i = graph.node_of(row);
    S pv[D];
    TM_UNROLL for (int a = 0; a < D; ++a) pv[a] = load_p(p + i * D + a);
    S acc[D];
    TM_UNROLL for (int a = 0; a < D; ++a) acc[a] = S(0);
    graph.add_forces(row, i, count, neighbors, p, pv, load_p, acc);
    return epilogue(i, pv, acc);
  }
  TM_HD void operator()(int64_t row) const { apply(row); }
};

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
// equal to tensor_hooke_partial_forces + gather_system over the same plan. `add` [V, d] (or
// nullopt): another product's rows added to Ap before the dots (SystemEpilogue's HAS_ADD), taken
// only where MAY_ADD (the ops without it instantiate no kernel that reads it).
template <class L, bool MAY_ADD = false, class Launch>
void run_hooke_node_system(const at::Tensor& p, const at::Tensor& neighbor, const at::Tensor& node_k,
                           const at::Tensor& incidences, const c10::optional<at::Tensor>& row_node,
                           const at::Tensor& mass,
                           const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                           const c10::optional<at::Tensor>& node_stiffness, at::Tensor& ap, at::Tensor& p_dot_ap,
                           const Launch& launch, const c10::optional<at::Tensor>& add = c10::nullopt) {
  check_values(p, "p");
  const int64_t num_nodes = p.size(0), dim = p.size(1);
  dispatch_dim(dim, [](auto) {});
  const at::ScalarType index_type = check_hooke_node_graph(p, "p", neighbor, node_k, incidences, row_node);
  check_node_tensor(mass, "mass", p, {num_nodes}, "p");
  at::Tensor fr, nk;
  std::tie(fr, nk) = optional_epilogue_inputs(free, node_stiffness, p, num_nodes, dim, "p");
  const at::Tensor added = add.has_value() && add->defined() ? *add : at::Tensor();
  if (added.defined()) check_node_tensor(added, "add", p, {num_nodes, dim}, "p");
  typename L::Guard guard(p.device());
  if (!ap.defined()) ap = at::empty({num_nodes, dim}, p.options());
  check_node_tensor(ap, "ap", p, {num_nodes, dim}, "p");
  dispatch_system<NodeHookeSystemKernel, MAY_ADD>(p.scalar_type(), index_type, dim, mass, fr, nk, c_mass, c_stiff,
                                                  ap, p_dot_ap, added.defined(), [&](auto& k) {
    using Kernel = std::decay_t<decltype(k)>;
    using S = typename Kernel::Scalar;
    k.p = p.data_ptr<S>();
    if (Kernel::kHasAdd) k.epilogue.add = added.data_ptr<S>();
    set_hooke_node_graph(k.graph, neighbor, node_k, incidences, row_node);
    launch(k, num_nodes);
  });
}

}  // namespace tensormass
