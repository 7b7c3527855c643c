// Schemas of the node graph ops: the hooke tensor form's CG matvec in one kernel over the node
// graph, implicit Euler's right-hand side over it, and a stress-form group's tangent written as the
// graph's slot tensors (the host side: ops.h and common/node_graph.h, the kernels: kernels.h and
// common/; registered for the CPU and CUDA by cpu.cpp and cuda.cu). The conventions every op
// follows: library.cpp; the chunk plan of the CG: cg/schema.cpp. Fake kernels and autograd: the
// Python module named below (set_python_module), imported when torch needs them.
//
// The node graph (neighbor [N_n, V], node_k [N_n, V, d, d], incidences [V], row_node [V]?) holds the
// slots of the plan's edges by row: row r holds the slots of node i = row_node[r] (None: i = r;
// ops.node_graph.node_graph_rows), neighbor[s][r] the other node of slot s's edge and node_k[s][r] its
// tensor: the edge tensor K_e where i is the edge's first node, K_e^T where it is its second.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tensormass, m) {
  m.set_python_module("tensormass_torch.ops.node_graph");
  // hooke_node_system(p [V, d], neighbor, node_k, incidences, row_node?, mass [V], free [V]?, c_mass,
  //                   c_stiff, node_stiffness [V, d, d]?) -> (Ap [V, d], p . Ap per node [V])
  //   gather_system's matvec (gather/schema.cpp) for the hooke tensor form in one kernel, bitwise that
  //   of tensor_hooke_partial_forces + gather_system over the same plan:
  //   (K p)_i = sum_{s < incidences[r]} -node_k[s][r] (p[neighbor[s][r]] - p_i). Not differentiable.
  m.def("hooke_node_system(Tensor p, Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, Tensor mass, Tensor? free, "
        "float c_mass, float c_stiff, Tensor? node_stiffness=None) -> (Tensor, Tensor)");
  // hooke_node_system_alpha(<hooke_node_system's inputs>, ap!, chunk_start, chunk_object, object_chunk,
  //                         rr, status!, alpha!, scratch!, counter!, add [V, d]?) -> ()
  //   hooke_node_system's Ap into ap in place, then each object's step length as cg_alpha does, in the
  //   same kernel (as gather_system_alpha). Objects that are not active are skipped. add: another
  //   product's rows (the contact pairs') added to Ap, projected likewise, before the dots.
  m.def("hooke_node_system_alpha(Tensor p, Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, Tensor mass, "
        "Tensor? free, float c_mass, float c_stiff, Tensor? node_stiffness, Tensor(a!) ap, Tensor chunk_start, "
        "Tensor chunk_object, Tensor object_chunk, Tensor rr, Tensor(b!) status, Tensor(c!) alpha, "
        "Tensor(d!) scratch, Tensor(e!) counter, Tensor? add=None) -> ()");
  // stress_tangent_node_k(u [V, d], elements, shape_vectors, measure, lam, mu, projector?, model,
  //                       rotations [N, d, d]?, element_edges [N, P], edge_slots [N, P], num_edge_slots,
  //                       edge_counts [Ed], slot_edge [N_n, V], incidences [V], node_k!, edge_partial!) -> ()
  //   writes a stress-form group's force differential at u (the stress ops' inputs,
  //   stress/schema.cpp; the corotational model needs its rotations, held fixed) as the edge blocks of
  //   the node graph, node_k [N_n, V, d, d] in place (slots beyond a row's incidences are not written),
  //   so that hooke_node_system, hooke_node_cg and hooke_node_solve run its CG products (once per
  //   linearisation instead of an element pass per CG iteration). The edges (topology.EdgeGraph):
  //   element_edges / edge_slots, the edge of each local pair of an element and its slot among the
  //   edge's elements (edge_counts, num_edge_slots the most); slot_edge, the edge g of each slot of the
  //   node graph (~g where the row's node is the edge's second). edge_partial [num_edge_slots, Ed, 12]
  //   ([.., 4] in 2-D) is the work buffer.
  m.def("stress_tangent_node_k(Tensor u, Tensor elements, Tensor shape_vectors, Tensor measure, Tensor lam, "
        "Tensor mu, Tensor? projector, int model, Tensor? rotations, Tensor element_edges, Tensor edge_slots, "
        "int num_edge_slots, Tensor edge_counts, Tensor slot_edge, Tensor incidences, "
        "Tensor(a!) node_k, Tensor(b!) edge_partial) -> ()");
  // hooke_node_step_rhs(x, v, rest [V, d], neighbor, node_k, incidences, row_node?, mass [V],
  //                     external [V, d], plane_normals [P, 3]?, plane_offsets [P]?, plane_stiffness [P]?,
  //                     h, w_coef, rayleigh_mass, u!, rhs!, node_stiffness!?) -> ()
  //   implicit Euler's right-hand side for the hooke tensor form in one pass over the nodes:
  //   rhs = h (f((x - rest) + w_coef v) + external + contact(x) - Kc(x) w_coef v - rayleigh_mass mass v)
  //   (w_coef = h + r_K), u = x - rest and, with the planes (all of them and node_stiffness, or none;
  //   d = 3), the contact stiffness Kc [V, 3, 3] into node_stiffness. In place, so that a CUDA graph
  //   replays it.
  m.def("hooke_node_step_rhs(Tensor x, Tensor v, Tensor rest, Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, "
        "Tensor mass, Tensor external, Tensor? plane_normals, Tensor? plane_offsets, Tensor? plane_stiffness, "
        "float h, float w_coef, float rayleigh_mass, Tensor(a!) u, Tensor(b!) rhs, Tensor(c!)? node_stiffness) -> ()");
  // node_graph_write_edges(edge_ids [M], edges [Ed, 2], force_index [Ed, 2], edge_k [Ed, d, d], node_k!,
  //                        row_of [V]?) -> ()
  //   after edge_k changed in place at edge_ids (a topology change: topology/schema.cpp), the graph's
  //   blocks of those edges written again: node_k[force_index[e, 0]][r(i)] = K_e and
  //   node_k[force_index[e, 1]][r(j)] = K_e^T for e = (i, j), r the row of a node (row_of, the inverse of
  //   the graph's row_node; None: rows in node order). edge_ids may repeat an edge and have either index
  //   type. The graph's storage is kept, so captured CUDA graphs that read it stay valid.
  m.def("node_graph_write_edges(Tensor edge_ids, Tensor edges, Tensor force_index, Tensor edge_k, "
        "Tensor(a!) node_k, Tensor? row_of) -> ()");
  // node_graph_rebuild_hooke_rows(pair_k [N, P, d, d], elements [N, n], node_slots [S, V],
  //                               alive [N] bool, touched [V] uint8, row_of [V]?, max_slots,
  //                               neighbor! [N_n, V], node_k! [N_n, V, d, d], incidences! [V],
  //                               status! [1] int32, firsts! [S, V] int32) -> ()
  //   A hooke tensor-form group's node graph (by rows: row_of, the inverse of its row_node; None:
  //   node order) after its elements changed at the touched nodes (a cut on the device): each
  //   touched node's row summed again from its elements (node_slots: each node's element rows in
  //   id order, -1 past the last; the alive ones) and their pair tensors (pair_k: Cotin's K_ab of
  //   each local pair a < b in the order (0,1), (0,2), ..., formed from the rest shape), oriented as
  //   the edges store them; the neighbours in the order first met, incidences = their number. A
  //   row that needs more than max_slots slots (at most N_n) sets status[0] = 1 (else status is
  //   unchanged) and is not to be used: its neighbours stay, its blocks may change (the caller
  //   builds the graph again). The graph's storage is kept, so captured CUDA graphs that read it
  //   stay valid. firsts: scratch (the touched nodes' columns are overwritten).
  m.def("node_graph_rebuild_hooke_rows(Tensor pair_k, Tensor elements, Tensor node_slots, Tensor alive, "
        "Tensor touched, Tensor? row_of, int max_slots, "
        "Tensor(a!) neighbor, Tensor(b!) node_k, Tensor(c!) incidences, Tensor(d!) status, Tensor(e!) firsts) -> ()");
}
