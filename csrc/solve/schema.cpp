// Schemas of the solve ops: a whole CG solve over the node graph in one op (the host side: ops.h;
// the GPU kernels: cg_persistent.cuh, cg_pipelined.cuh; registered for the CPU and CUDA by cpu.cpp
// and cuda.cu). Every op writes in place and returns nothing, so that a CUDA graph replays it and
// torch's functionalization traces it. Fake kernels and the pure-torch references: the Python
// module named below (set_python_module), imported when torch needs them.
//
// The ops take their many tensors packed in lists, by what they are (unpacked once, ops.h):
//   system   Tensor?[] [neighbor, node_k, incidences, row_node?, mass, free?]: hooke_node_system's
//            graph and epilogue (node_graph/schema.cpp)
//   plan     Tensor[]  [chunk_start [K + 1], chunk_object [K], object_chunk [B + 1]] int64: the chunk
//            plan of the CG ops (cg/schema.cpp)
//   cg       Tensor(!)[] [x, r, p [V, d], threshold, rhs_sq, rr, alpha, beta [B], status, iterations
//            [B] int32]: the CG state (Python: ops.cg.CGState), written
//   buffers  Tensor(!)[] the op's work (contents unspecified between calls): per op below
//   step     Tensor(!)[] [state_x, state_v, x_new, v_new [V, d], norms [B], summary [5, B] float64,
//            end_sums [K] float64, end_counter [B + 1] int32 (zero between calls)]: euler_update's
//            tensors (cg/schema.cpp) for the step's end, with the solve's x as dv
//
// Kernel variants are arguments (ops/variants.py KernelVariants; no environment read here):
//   flags        bit 0: hooke_node_cg keeps each node's neighbours in shared memory across iterations;
//                bit 1: the streamed layout's mirror rows share their slots' work (two threads a node)
//   cache_slots  the streamed layout's cap on the slots of a node kept in shared memory (-1: as many
//                as fit; 0: every slot read from the graph each iteration)
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tensormass, m) {
  m.set_python_module("tensormass_torch.ops.solve");
  // hooke_node_cg(system, c_mass, c_stiff, node_stiffness?, rhs? [V, d], tol_sq, plan, max_iter, count, cg!,
  //               buffers! = [ap [V, d], rr_swap [B], work [3B + 2] int32, sums [2K] float64], flags)
  //   the start from x0 = 0 (when rhs is given: r = p = free rhs, threshold = tol_sq rhs . rhs) and up
  //   to `count` iterations of the CG with hooke_node_system's matvec (its input: cg's p), stopping
  //   once no object is active: one persistent kernel on the GPU; bitwise the op-by-op solve.
  m.def("hooke_node_cg(Tensor?[] system, float c_mass, float c_stiff, Tensor? node_stiffness, Tensor? rhs, "
        "float tol_sq, Tensor[] plan, int max_iter, int count, Tensor(a!)[] cg, Tensor(b!)[] buffers, "
        "int flags=3) -> ()");
  // hooke_node_solve(system, c_mass, c_stiff, node_stiffness?, rhs [V, d], tol_sq, plan, chunk_nodes,
  //                  chunk_slots, max_iter, cg!, buffers! = [exchange [2, V, 4d], sums [4K] float64,
  //                  counters [3] int32], flags, cache_slots, from_iterate)
  //   a whole solve from x0 = 0 by Chronopoulos-Gear's CG (one reduction and one grid barrier an
  //   iteration), or (from_iterate) from the iterate a start left in cg (x0 = cg's x, rhs = its
  //   residual b - A x0, its threshold kept): GPU only. chunk_nodes and chunk_slots: the nodes and
  //   slots of the plan's largest chunk (<= 128 nodes, the slots may sit in shared memory; <= 256,
  //   streamed). Raises NotImplementedError, having changed nothing, where the solve does not fit one
  //   wave of the device, or on the CPU.
  m.def("hooke_node_solve(Tensor?[] system, float c_mass, float c_stiff, Tensor? node_stiffness, Tensor rhs, "
        "float tol_sq, Tensor[] plan, int chunk_nodes, int chunk_slots, int max_iter, Tensor(a!)[] cg, "
        "Tensor(b!)[] buffers, int flags=3, int cache_slots=-1, bool from_iterate=False) -> ()");
  // hooke_node_solve_step(<hooke_node_solve's but the last three>, step!, dv_imposed? [V, d], h,
  //                       ring! [R, 5, B]?, ring_pos! [1] int64?, carry, flags, cache_slots)
  //   the same solve, then euler_update (cg/schema.cpp) with its solution as dv, in the same kernel
  //   (the graphed step's last launch gone); raises where hooke_node_solve does, having done neither.
  m.def("hooke_node_solve_step(Tensor?[] system, float c_mass, float c_stiff, Tensor? node_stiffness, Tensor rhs, "
        "float tol_sq, Tensor[] plan, int chunk_nodes, int chunk_slots, int max_iter, Tensor(a!)[] cg, "
        "Tensor(b!)[] buffers, Tensor(c!)[] step, Tensor? dv_imposed, float h, Tensor(d!)? ring, "
        "Tensor(e!)? ring_pos, bool carry, int flags=3, int cache_slots=-1, float h_old=0.0) -> ()");
  // hooke_node_steps(system, c_mass, c_stiff, node_stiffness! [V, 3, 3]?, loads = [rest, external [V, d],
  //                  plane_normals? [P, 3], plane_offsets? [P], plane_stiffness? [P]], rhs_out! = [u, rhs
  //                  [V, d]], tol_sq, plan, chunk_nodes, chunk_slots, max_iter, cg!, buffers!, step!,
  //                  step_coefs = [h, w_coef, rayleigh_mass], ring!?, ring_pos!?, carry, steps, flags,
  //                  cache_slots)
  //   `steps` implicit Euler steps (no imposed velocity) in one kernel: each hooke_node_step_rhs's rhs
  //   (and contact stiffness; node_graph/schema.cpp) at the carried state, then hooke_node_solve_step.
  //   steps > 1 needs carry; raises where hooke_node_solve does, having done nothing.
  m.def("hooke_node_steps(Tensor?[] system, float c_mass, float c_stiff, Tensor(a!)? node_stiffness, "
        "Tensor?[] loads, Tensor(b!)[] rhs_out, float tol_sq, Tensor[] plan, int chunk_nodes, int chunk_slots, "
        "int max_iter, Tensor(c!)[] cg, Tensor(d!)[] buffers, Tensor(e!)[] step, float[] step_coefs, "
        "Tensor(f!)? ring, Tensor(g!)? ring_pos, bool carry, int steps, int flags=3, int cache_slots=-1) -> ()");
}
