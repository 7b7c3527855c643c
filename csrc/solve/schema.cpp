// Schemas of the solve ops: a whole CG solve over the node graph in one op (the host side: ops.h;
// the GPU kernels: cg_persistent.cuh, cg_pipelined.cuh; registered for the CPU and CUDA by cpu.cpp
// and cuda.cu). The node graph's and the epilogue's inputs are hooke_node_system's
// (node_graph/schema.cpp); the chunk plan and the CG state are the CG ops' (cg/schema.cpp): x, r, p
// [V, d]; threshold, rhs_sq, rr, alpha, beta [B]; status, iterations [B] int32. Every op writes in
// place, so that a CUDA graph replays it. Fake kernels: the Python module named below
// (set_python_module), imported when torch needs them.
//
// Kernel variants are arguments (ops/variants.py KernelVariants; no environment read here):
//   flags        bit 0: hooke_node_cg keeps each node's neighbours in shared memory across iterations;
//                bit 1: the streamed layout's mirror rows share their slots' work (two threads a node)
//   cache_slots  the streamed layout's cap on the slots of a node kept in shared memory (-1: as many
//                as fit; 0: every slot read from the graph each iteration)
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tensormass, m) {
  m.set_python_module("tensormass_torch.ops.solve");
  // hooke_node_cg(p!, <hooke_node_system's inputs after p>, ap! [V, d], x!, r!, rhs [V, d]?, tol_sq,
  //               <chunk plan>, threshold!, rhs_sq!, max_iter, count, rr!, status!, alpha!, beta!,
  //               iterations!, rr_swap! [B], work! [3B + 2] int32, sums! [2K] float64, flags) -> ()
  //   the start from x0 = 0 (when rhs is given: r = p = free rhs, threshold = tol_sq rhs . rhs) and up
  //   to `count` iterations of the CG with hooke_node_system's matvec, stopping once no object is
  //   active: one persistent kernel on the GPU; bitwise the op-by-op solve.
  m.def("hooke_node_cg(Tensor(a!) p, Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, Tensor mass, "
        "Tensor? free, float c_mass, float c_stiff, Tensor? node_stiffness, Tensor(b!) ap, Tensor(c!) x, "
        "Tensor(d!) r, Tensor? rhs, float tol_sq, Tensor chunk_start, Tensor chunk_object, Tensor object_chunk, "
        "Tensor(e!) threshold, Tensor(f!) rhs_sq, int max_iter, int count, Tensor(g!) rr, Tensor(h!) status, "
        "Tensor(i!) alpha, Tensor(j!) beta, Tensor(k!) iterations, Tensor(l!) rr_swap, Tensor(m!) work, "
        "Tensor(n!) sums, int flags=3) -> ()");
  // hooke_node_solve(<hooke_node_system's graph and epilogue: neighbor .. node_stiffness>, rhs, tol_sq,
  //                  <chunk plan>, chunk_nodes, chunk_slots, max_iter, x!, r!, p!, threshold!, rhs_sq!,
  //                  rr!, status!, alpha!, beta!, iterations!, exchange! [2, V, 4d], sums! [4K] float64,
  //                  counters! [3] int32, flags, cache_slots) -> bool
  //   a whole solve from x0 = 0 by Chronopoulos-Gear's CG (one reduction and one grid barrier an
  //   iteration): GPU only. chunk_nodes and chunk_slots: the nodes and slots of the plan's largest
  //   chunk (<= 128 nodes, the slots may sit in shared memory; <= 256, streamed). Returns false,
  //   having done nothing, where the solve does not fit one wave of the device, or on the CPU.
  m.def("hooke_node_solve(Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, Tensor mass, Tensor? free, "
        "float c_mass, float c_stiff, Tensor? node_stiffness, Tensor rhs, float tol_sq, Tensor chunk_start, "
        "Tensor chunk_object, Tensor object_chunk, int chunk_nodes, int chunk_slots, int max_iter, Tensor(a!) x, Tensor(b!) r, "
        "Tensor(c!) p, Tensor(d!) threshold, Tensor(e!) rhs_sq, Tensor(f!) rr, Tensor(g!) status, "
        "Tensor(h!) alpha, Tensor(i!) beta, Tensor(j!) iterations, Tensor(k!) exchange, Tensor(l!) sums, "
        "Tensor(m!) counters, int flags=3, int cache_slots=-1) -> bool");
  // hooke_node_solve_step(<hooke_node_solve's arguments>, state_x!, state_v!, dv_imposed?, h, x_new!,
  //                       v_new!, norms!, summary!, end_sums! [K] float64, end_counter! [B + 1] int32,
  //                       ring!?, ring_pos!?, carry, flags, cache_slots) -> bool
  //   the same solve, then euler_update (cg/schema.cpp) with its solution as dv, in the same kernel
  //   (the graphed step's last launch gone); false, having done neither, where hooke_node_solve is.
  m.def("hooke_node_solve_step(Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, Tensor mass, "
        "Tensor? free, float c_mass, float c_stiff, Tensor? node_stiffness, Tensor rhs, float tol_sq, Tensor chunk_start, "
        "Tensor chunk_object, Tensor object_chunk, int chunk_nodes, int chunk_slots, int max_iter, Tensor(a!) x, "
        "Tensor(b!) r, Tensor(c!) p, Tensor(d!) threshold, Tensor(e!) rhs_sq, Tensor(f!) rr, Tensor(g!) status, "
        "Tensor(h!) alpha, Tensor(i!) beta, Tensor(j!) iterations, Tensor(k!) exchange, Tensor(l!) sums, "
        "Tensor(m!) counters, Tensor(n!) state_x, Tensor(o!) state_v, Tensor? dv_imposed, float h, Tensor(p!) x_new, "
        "Tensor(q!) v_new, Tensor(r!) norms, Tensor(s!) summary, Tensor(t!) end_sums, Tensor(u!) end_counter, "
        "Tensor(v!)? ring, Tensor(w!)? ring_pos, bool carry, int flags=3, int cache_slots=-1) -> bool");
  // hooke_node_steps(<hooke_node_solve's graph and epilogue without node_stiffness>, rest, external,
  //                  w_coef, rayleigh_mass, plane_normals?, plane_offsets?, plane_stiffness?, u!, rhs!,
  //                  node_stiffness!?, <hooke_node_solve's tol_sq .. counters>, state_x!, state_v!, h,
  //                  x_new!, v_new!, norms!, summary!, end_sums!, end_counter!, ring!?, ring_pos!?, carry,
  //                  steps, flags, cache_slots) -> bool
  //   `steps` implicit Euler steps (no imposed velocity) in one kernel: each hooke_node_step_rhs's rhs
  //   (and contact stiffness; node_graph/schema.cpp) at the carried state, then hooke_node_solve_step.
  //   steps > 1 needs carry; false, having done nothing, where hooke_node_solve is.
  m.def("hooke_node_steps(Tensor neighbor, Tensor node_k, Tensor incidences, Tensor? row_node, Tensor mass, "
        "Tensor? free, float c_mass, float c_stiff, Tensor rest, Tensor external, float w_coef, float rayleigh_mass, "
        "Tensor? plane_normals, Tensor? plane_offsets, Tensor? plane_stiffness, Tensor(a!) u, Tensor(b!) rhs, "
        "Tensor(z!)? node_stiffness, float tol_sq, Tensor chunk_start, Tensor chunk_object, Tensor object_chunk, "
        "int chunk_nodes, int chunk_slots, int max_iter, Tensor(c!) x, Tensor(d!) r, Tensor(e!) p, "
        "Tensor(f!) threshold, Tensor(g!) rhs_sq, Tensor(h!) rr, Tensor(i!) status, Tensor(j!) alpha, "
        "Tensor(k!) beta, Tensor(l!) iterations, Tensor(m!) exchange, Tensor(n!) sums, Tensor(o!) counters, "
        "Tensor(p!) state_x, Tensor(q!) state_v, float h, Tensor(r!) x_new, Tensor(s!) v_new, Tensor(t!) norms, "
        "Tensor(u!) summary, Tensor(v!) end_sums, Tensor(w!) end_counter, Tensor(x!)? ring, "
        "Tensor(y!)? ring_pos, bool carry, int steps, int flags=3, int cache_slots=-1) -> bool");
}
