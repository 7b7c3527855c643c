// tensormass ops: the schemas (TORCH_LIBRARY) and the Python module tensormass_torch._C.
//
// Implementations: cpu/*.cpp (CPU) and cuda/*.cu (CUDA), both from ops_impl.h / kernels.h /
// element_math.h. Fake (meta) kernels and autograd are registered in Python, in
// tensormass_torch/ops/native.py (imported on demand through set_python_module).
//
// Conventions: u, du [V, d] (float32 or float64, one dtype for all floating inputs); index
// tensors (elements, edges, force_index, incidences) all int32 or all int64; every input
// contiguous and on one device. `model`: 0 = hooke, 1 = stvk, 2 = corotational (see below).
// A plan (force_index, num_slots, incidences) must come from topology.GatherPlan over the same
// items: force_index < num_slots and the slots of a node are 0 .. incidences[i]-1 (not
// re-checked here: it would cost a pass).
//
//   kernel 1 (element level)  *_element_forces / *_element_dforces -> [N, n, d]
//   kernel 1 (padded, paper)  *_partial_forces / *_partial_dforces -> PartialForce [N_n, V, d]
//                             (slots >= incidences[i] are left uninitialised)
//   kernel 2                  gather_partial(PartialForce, incidences) -> [V, d]
//                             node_gather(partial [N, n, d], index, force_index, ...) -> [V, d]
//                             gather_system(PartialForce, incidences, p, mass, free, c_M, c_K,
//                                           node_stiffness=None)
//                               -> (Ap = free (c_M mass p - c_K K p) [V, d], p . Ap per node [V])
//                               where (K p)_i = sum of node i's slots - node_stiffness_i p_i
//                               (node_stiffness [V, d, d]: the hooke tensor form's vertex term K_ii,
//                               contact penalties)
//   node-centric matvec       hooke_node_system(p, neighbor [N_n, V], node_k [N_n, V, d, d], incidences,
//                                               row_node?, mass, free, c_M, c_K, node_stiffness=None)
//                               -> (Ap, p . Ap) as gather_system, for the hooke tensor form in one
//                               kernel: (K p)_i = sum_{s < incidences[r]} -node_k[s][r]
//                               (p[neighbor[s][r]] - p_i) with i = row_node[r] (None: i = r; the
//                               graph's arrays are stored by row, native.node_graph_rows) (node_k:
//                               the edge tensor K_e where i is the edge's first node, K_e^T where it
//                               is its second; the plan's slots)
//   matvec + cg_alpha         gather_system_alpha / hooke_node_system_alpha(<the same inputs>, ap!,
//                               chunk plan, rr, status!, alpha!, scratch!, counter!) -> ()
//                               Ap into ap in place, then alpha per object as cg_alpha (cg_ops.cpp)
//                               does, in the same kernel (one block per chunk): one launch fewer
//                               per CG iteration; inactive objects are skipped
//   whole CG solve            hooke_node_cg(p!, <hooke_node_system's inputs>, ap!, x!, r!, rhs?, tol_sq,
//                               chunk plan, threshold!, rhs_sq!, max_iter, count, rr!, status!, alpha!,
//                               beta!, iterations!, rr_swap!, work!, sums!) -> ()
//                               the start (when rhs is given) and up to count iterations of the CG
//                               with hooke_node_system's matvec, stopping once no object is active:
//                               one persistent kernel on the GPU; bitwise the op-by-op solve
//   pipelined whole solve     hooke_node_solve(<hooke_node_system's graph and epilogue>, rhs, tol_sq, chunk
//                               plan, chunk_nodes (its largest chunk: <= 128 nodes, the slots may sit in
//                               shared memory; <= 256, streamed), chunk_slots, max_iter, x!, r!, p!, threshold!,
//                               rhs_sq!, rr!, status!, alpha!, beta!, iterations!, exchange!, sums!,
//                               counters!) -> bool
//                               a whole solve from x0 = 0 by Chronopoulos-Gear's CG (one reduction and
//                               one grid barrier an iteration): GPU only; false (nothing done) where it
//                               does not fit one wave, or on the CPU
//                             hooke_node_solve_step(<hooke_node_solve's arguments>, state_x!, state_v!,
//                               dv_imposed?, h, x_new!, v_new!, norms!, summary!, end_sums!, end_counter!,
//                               ring!?, ring_pos!?, carry) -> bool
//                               the same solve, then euler_update with its solution as dv, in the same
//                               kernel (the graphed step's last launch gone)
//                             hooke_node_steps(<hooke_node_solve's graph and epilogue without node_stiffness>,
//                               rest, external, w_coef, r_M, plane_normals?, plane_offsets?, plane_stiffness?,
//                               u!, rhs!, node_stiffness!?, <hooke_node_solve's tol_sq .. counters>, state_x!,
//                               state_v!, h, x_new!, v_new!, norms!, summary!, end_sums!, end_counter!, ring!?,
//                               ring_pos!?, carry, steps) -> bool
//                               `steps` implicit Euler steps (no imposed velocity) in one kernel: each
//                               hooke_node_step_rhs's rhs (and contact stiffness), then hooke_node_solve_step
//   step right-hand side      hooke_node_step_rhs(x, v, rest, neighbor, node_k, incidences, row_node?, mass, external,
//                               plane_normals?, plane_offsets?, plane_stiffness?, h, w_coef, r_M, u!, rhs!,
//                               node_stiffness!?) -> ()
//                               implicit Euler's rhs = h (f((x - rest) + w_coef v) + external + contact(x)
//                               - Kc(x) w_coef v - r_M mass v), u = x - rest and the contact stiffness
//                               Kc [V, 3, 3] in one pass over the nodes (hooke tensor form, node graph)
//   fused (kernel 1 + 2)      stress_forces, stress_dforces, tensor_hooke_forces,
//                             tensor_stvk_forces, tensor_stvk_dforces -> [V, d]
//
// Corotational (model 2): corotational_rotations(u, elements, shape_vectors, projector,
// rest_elements, method) -> R [N, d, d] computes the element rotations once per linearisation
// (method 0 = SOFA's QR frame, 3-D only; 1 = polar: the closest proper rotation to F, robust to
// inverted and nearly flat elements; membranes map their rest normal onto the current one). The
// stress ops end with `rest_elements` [N, n, 3] and `rotations` [N, d, d], both optional and for
// model 2 only: given `rotations`, the kernels read R (9 numbers per element, the CG path);
// otherwise they recompute SOFA's QR frame from u and `rest_elements` at every call. The
// differential holds R fixed, as SOFA does.
//
// The tangent on the node graph (stress form): stress_tangent_node_k(u, <stress inputs>, rotations?,
// element_edges, edge_slots, num_edge_slots, edge_counts, slot_edge, incidences, node_k!,
// edge_partial!) -> () writes the group's force differential at u as the edge blocks of
// the node graph (node_k [N_n, V, d, d]), so that hooke_node_system, hooke_node_cg and
// hooke_node_solve run its CG products (once per linearisation instead of an element pass per
// CG iteration).
#include <pybind11/pybind11.h>
#include <torch/library.h>

TORCH_LIBRARY(tensormass, m) {
  m.set_python_module("tensormass_torch.ops.native");
  // ---- stress form
  m.def("stress_element_forces(Tensor u, Tensor elements, Tensor shape_vectors, Tensor measure, Tensor lam, "
        "Tensor mu, Tensor? projector, int model, "
        "Tensor? rest_elements=None, Tensor? rotations=None) -> Tensor");
  m.def("stress_element_dforces(Tensor u, Tensor du, Tensor elements, Tensor shape_vectors, Tensor measure, "
        "Tensor lam, Tensor mu, Tensor? projector, int model, "
        "Tensor? rest_elements=None, Tensor? rotations=None) -> Tensor");
  m.def("stress_partial_forces(Tensor u, Tensor elements, Tensor force_index, int num_slots, "
        "Tensor shape_vectors, Tensor measure, Tensor lam, Tensor mu, Tensor? projector, int model, "
        "Tensor? rest_elements=None, Tensor? rotations=None) -> Tensor");
  m.def("stress_partial_dforces(Tensor u, Tensor du, Tensor elements, Tensor force_index, int num_slots, "
        "Tensor shape_vectors, Tensor measure, Tensor lam, Tensor mu, Tensor? projector, int model, "
        "Tensor? rest_elements=None, Tensor? rotations=None) -> Tensor");
  m.def("stress_forces(Tensor u, Tensor elements, Tensor force_index, int num_slots, Tensor incidences, "
        "Tensor shape_vectors, Tensor measure, Tensor lam, Tensor mu, Tensor? projector, int model, "
        "Tensor? rest_elements=None, Tensor? rotations=None) -> Tensor");
  m.def("stress_dforces(Tensor u, Tensor du, Tensor elements, Tensor force_index, int num_slots, "
        "Tensor incidences, Tensor shape_vectors, Tensor measure, Tensor lam, Tensor mu, Tensor? projector, "
        "int model, Tensor? rest_elements=None, Tensor? rotations=None) -> Tensor");
  // ---- corotational: the element rotations at u, once per linearisation (0 = qr, 1 = polar)
  m.def("corotational_rotations(Tensor u, Tensor elements, Tensor shape_vectors, Tensor? projector, "
        "Tensor? rest_elements, int method) -> Tensor");
  // ---- the differential at u as slot tensors of the node graph (in place; once per linearisation)
  m.def("stress_tangent_node_k(Tensor u, Tensor elements, Tensor shape_vectors, Tensor measure, Tensor lam, "
        "Tensor mu, Tensor? projector, int model, Tensor? rotations, Tensor element_edges, Tensor edge_slots, "
        "int num_edge_slots, Tensor edge_counts, Tensor slot_edge, Tensor incidences, "
        "Tensor(a!) node_k, Tensor(b!) edge_partial) -> ()");
  // ---- tensor form, hooke (items are edges; linear, so dforces(du) = forces(du))
  m.def("tensor_hooke_element_forces(Tensor u, Tensor edges, Tensor edge_k) -> Tensor");
  m.def("tensor_hooke_partial_forces(Tensor u, Tensor edges, Tensor force_index, int num_slots, "
        "Tensor edge_k) -> Tensor");
  m.def("tensor_hooke_forces(Tensor u, Tensor edges, Tensor force_index, int num_slots, Tensor incidences, "
        "Tensor edge_k) -> Tensor");
  // ---- tensor form, stvk
  m.def("tensor_stvk_element_forces(Tensor u, Tensor elements, Tensor tensor_b, Tensor tensor_c, "
        "Tensor tensor_d) -> Tensor");
  m.def("tensor_stvk_element_dforces(Tensor u, Tensor du, Tensor elements, Tensor tensor_b, Tensor tensor_c, "
        "Tensor tensor_d) -> Tensor");
  m.def("tensor_stvk_partial_forces(Tensor u, Tensor elements, Tensor force_index, int num_slots, "
        "Tensor tensor_b, Tensor tensor_c, Tensor tensor_d) -> Tensor");
  m.def("tensor_stvk_partial_dforces(Tensor u, Tensor du, Tensor elements, Tensor force_index, int num_slots, "
        "Tensor tensor_b, Tensor tensor_c, Tensor tensor_d) -> Tensor");
  m.def("tensor_stvk_forces(Tensor u, Tensor elements, Tensor force_index, int num_slots, Tensor incidences, "
        "Tensor tensor_b, Tensor tensor_c, Tensor tensor_d) -> Tensor");
  m.def("tensor_stvk_dforces(Tensor u, Tensor du, Tensor elements, Tensor force_index, int num_slots, "
        "Tensor incidences, Tensor tensor_b, Tensor tensor_c, Tensor tensor_d) -> Tensor");
  // ---- kernel 2
  m.def("gather_partial(Tensor partial, Tensor incidences, Tensor? node_term) -> Tensor");
  m.def("node_gather(Tensor partial, Tensor index, Tensor force_index, int num_slots, Tensor incidences, "
        "Tensor? node_term) -> Tensor");
  // ---- kernel 2 + implicit-Euler system epilogue (the CG matvec; not differentiable)
  m.def("gather_system(Tensor partial, Tensor incidences, Tensor p, Tensor mass, Tensor? free, float c_mass, "
        "float c_stiff, Tensor? node_stiffness=None) -> (Tensor, Tensor)");
  // ---- the hooke tensor form's CG matvec in one kernel over the node graph (not differentiable)
  m.def("hooke_node_system(Tensor p, Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, Tensor mass, Tensor? free, "
        "float c_mass, float c_stiff, Tensor? node_stiffness=None) -> (Tensor, Tensor)");
  // ---- the two CG matvecs ending in the step length (cg_alpha fused; in place, for CUDA graphs)
  m.def("gather_system_alpha(Tensor partial, Tensor incidences, Tensor p, Tensor mass, Tensor? free, "
        "float c_mass, float c_stiff, Tensor? node_stiffness, Tensor(a!) ap, Tensor chunk_start, "
        "Tensor chunk_object, Tensor object_chunk, Tensor rr, Tensor(b!) status, Tensor(c!) alpha, "
        "Tensor(d!) scratch, Tensor(e!) counter) -> ()");
  m.def("hooke_node_system_alpha(Tensor p, Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, Tensor mass, "
        "Tensor? free, float c_mass, float c_stiff, Tensor? node_stiffness, Tensor(a!) ap, Tensor chunk_start, "
        "Tensor chunk_object, Tensor object_chunk, Tensor rr, Tensor(b!) status, Tensor(c!) alpha, "
        "Tensor(d!) scratch, Tensor(e!) counter) -> ()");
  // ---- a whole CG solve over the hooke node graph: one persistent kernel on the GPU (in place)
  m.def("hooke_node_cg(Tensor(a!) p, Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, Tensor mass, "
        "Tensor? free, float c_mass, float c_stiff, Tensor? node_stiffness, Tensor(b!) ap, Tensor(c!) x, "
        "Tensor(d!) r, Tensor? rhs, float tol_sq, Tensor chunk_start, Tensor chunk_object, Tensor object_chunk, "
        "Tensor(e!) threshold, Tensor(f!) rhs_sq, int max_iter, int count, Tensor(g!) rr, Tensor(h!) status, "
        "Tensor(i!) alpha, Tensor(j!) beta, Tensor(k!) iterations, Tensor(l!) rr_swap, Tensor(m!) work, "
        "Tensor(n!) sums) -> ()");
  // ---- a whole CG solve from x0 = 0 by the pipelined CG (one grid barrier an iteration; GPU)
  m.def("hooke_node_solve(Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, Tensor mass, Tensor? free, "
        "float c_mass, float c_stiff, Tensor? node_stiffness, Tensor rhs, float tol_sq, Tensor chunk_start, "
        "Tensor chunk_object, Tensor object_chunk, int chunk_nodes, int chunk_slots, int max_iter, Tensor(a!) x, Tensor(b!) r, "
        "Tensor(c!) p, Tensor(d!) threshold, Tensor(e!) rhs_sq, Tensor(f!) rr, Tensor(g!) status, "
        "Tensor(h!) alpha, Tensor(i!) beta, Tensor(j!) iterations, Tensor(k!) exchange, Tensor(l!) sums, "
        "Tensor(m!) counters) -> bool");
  m.def("hooke_node_solve_step(Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, Tensor mass, "
        "Tensor? free, float c_mass, float c_stiff, Tensor? node_stiffness, Tensor rhs, float tol_sq, Tensor chunk_start, "
        "Tensor chunk_object, Tensor object_chunk, int chunk_nodes, int chunk_slots, int max_iter, Tensor(a!) x, "
        "Tensor(b!) r, Tensor(c!) p, Tensor(d!) threshold, Tensor(e!) rhs_sq, Tensor(f!) rr, Tensor(g!) status, "
        "Tensor(h!) alpha, Tensor(i!) beta, Tensor(j!) iterations, Tensor(k!) exchange, Tensor(l!) sums, "
        "Tensor(m!) counters, Tensor(n!) state_x, Tensor(o!) state_v, Tensor? dv_imposed, float h, Tensor(p!) x_new, "
        "Tensor(q!) v_new, Tensor(r!) norms, Tensor(s!) summary, Tensor(t!) end_sums, Tensor(u!) end_counter, "
        "Tensor(v!)? ring, Tensor(w!)? ring_pos, bool carry) -> bool");
  m.def("hooke_node_steps(Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, Tensor mass, "
        "Tensor? free, float c_mass, float c_stiff, Tensor rest, Tensor external, float w_coef, float rayleigh_mass, "
        "Tensor? plane_normals, Tensor? plane_offsets, Tensor? plane_stiffness, Tensor(a!) u, Tensor(b!) rhs, "
        "Tensor(z!)? node_stiffness, float tol_sq, Tensor chunk_start, Tensor chunk_object, Tensor object_chunk, "
        "int chunk_nodes, int chunk_slots, int max_iter, Tensor(c!) x, Tensor(d!) r, Tensor(e!) p, "
        "Tensor(f!) threshold, Tensor(g!) rhs_sq, Tensor(h!) rr, Tensor(i!) status, Tensor(j!) alpha, "
        "Tensor(k!) beta, Tensor(l!) iterations, Tensor(m!) exchange, Tensor(n!) sums, Tensor(o!) counters, "
        "Tensor(p!) state_x, Tensor(q!) state_v, float h, Tensor(r!) x_new, Tensor(s!) v_new, Tensor(t!) norms, "
        "Tensor(u!) summary, Tensor(v!) end_sums, Tensor(w!) end_counter, Tensor(x!)? ring, "
        "Tensor(y!)? ring_pos, bool carry, int steps) -> bool");
  // ---- implicit Euler's right-hand side for the hooke tensor form, in one pass (in place)
  m.def("hooke_node_step_rhs(Tensor x, Tensor v, Tensor rest, Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, "
        "Tensor mass, Tensor external, Tensor? plane_normals, Tensor? plane_offsets, Tensor? plane_stiffness, "
        "float h, float w_coef, float rayleigh_mass, Tensor(a!) u, Tensor(b!) rhs, Tensor(c!)? node_stiffness) -> ()");
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "tensormass_torch._C: Tensor-Mass element kernels (the ops live in torch.ops.tensormass)";
  m.def("has_cuda", []() {
#ifdef TENSORMASS_WITH_CUDA
    return true;
#else
    return false;
#endif
  }, "Whether the extension was built with its CUDA kernels.");
}
