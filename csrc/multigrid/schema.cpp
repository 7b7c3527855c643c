// Schemas of the multigrid ops: the products a V-cycle's coarse levels take (the host side:
// ops.h, its kernels: kernels.h; registered for the CPU and CUDA by cpu.cpp and cuda.cu). The
// conventions every op follows: library.cpp. Fake kernels: none (the ops write in place); the
// Python module named below holds their references (set_python_module).
//
// A BSR matrix is (values [nb, R, C], block_cols [nb] int32, row_ptr [Rb + 1] int32): block row I
// holds the blocks row_ptr[I] .. row_ptr[I + 1] - 1, block k at block column block_cols[k] (any
// order within a row; the caller guarantees the columns are in range). Block shapes: 6x6, 3x6,
// 6x3, 3x3, 2x3, 3x2, 2x2, 1x1. Vectors are flat [n] of the matrix's dtype. Each block row is
// summed in a fixed order (deterministic, no atomics).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tensormass, m) {
  m.set_python_module("tensormass_torch.ops.multigrid");
  // multigrid_bsr_gemv(values, block_cols, row_ptr, x [Cb C], y? [Rb R], alpha, beta, out! [Rb R]) -> ()
  //   out = alpha A x + beta y (alpha A x without y). out may be y, never x.
  m.def("multigrid_bsr_gemv(Tensor values, Tensor block_cols, Tensor row_ptr, Tensor x, Tensor? y, float alpha, "
        "float beta, Tensor(a!) out) -> ()");
  // multigrid_chebyshev(values?, block_cols?, row_ptr?, product? [n], b [n], inverse_diagonal [n], x? [n],
  //                     step! [n], x_out! [n], a, c) -> ()
  //   one step of Chebyshev iteration for A x = b scaled by D^-1 = inverse_diagonal:
  //   r = b - A x (the square matrix given), b - product (A x given), or b (no x: x = 0);
  //   step = a step + c D^-1 r (a = 0: step's old values unread); x_out = x + step (no x: step).
  //   x_out may be x only where the matrix is not given.
  m.def("multigrid_chebyshev(Tensor? values, Tensor? block_cols, Tensor? row_ptr, Tensor? product, Tensor b, "
        "Tensor inverse_diagonal, Tensor? x, Tensor(a!) step, Tensor(b!) x_out, float a, float c) -> ()");
  // multigrid_block_cholesky(blocks [n, d, d], scale! [n, d, d], scale_t! [n, d, d], inverse! [n, d, d]) -> ()
  //   block Jacobi's scaling (d 2 or 3): for each symmetric block A = L L^T (its lower triangle
  //   read), scale = L^-T, scale_t = L^-1 and inverse = L^T; the identity for the three where a
  //   pivot is not positive. Four different tensors.
  m.def("multigrid_block_cholesky(Tensor blocks, Tensor(a!) scale, Tensor(b!) scale_t, Tensor(c!) inverse) -> ()");
  // multigrid_rigid_restrict(node_inverse [V, 3, 3], arm [V, 3], range_ptr [R + 1] int32, r [3 V], out! [6 R]) -> ()
  //   the rigid correction's restriction with its basis formed on the fly: for each range b of
  //   nodes range_ptr[b] .. range_ptr[b + 1] - 1 (a body, or a run of one's nodes), out_b = the sum
  //   of (u_i, arm_i x u_i), u_i = node_inverse_i^T r_i (node_inverse [V]: u_i = node_inverse_i r_i,
  //   a value a node, N_i = n_i I).
  m.def("multigrid_rigid_restrict(Tensor node_inverse, Tensor arm, Tensor range_ptr, Tensor r, Tensor(a!) out) -> ()");
  // multigrid_rigid_prolong(node_inverse, arm, node_body [V] int32, coarse [6 B], r? [3 V], weight, out! [3 V]) -> ()
  //   its prolongation: out_i = r_i + weight node_inverse_i (t + w x arm_i), (t, w) = coarse's six
  //   values of the node's body (no r: 0 in its place). out may be r, never coarse.
  m.def("multigrid_rigid_prolong(Tensor node_inverse, Tensor arm, Tensor node_body, Tensor coarse, Tensor? r, "
        "float weight, Tensor(a!) out) -> ()");
  // multigrid_match_clusters(edge_keys [E] int64, edge_ends [E, 2] int64, incident_ptr [B + 1] int64,
  //                          incident_edges [2 E] int64, most, rounds, label! [B] int64, work! [6, B] int64) -> ()
  //   heavy-edge matching of a graph of B nodes into clusters of at most `most`: `rounds` times,
  //   each cluster offers its edge of largest key (keys distinct, >= 0) to a cluster it fits
  //   beside, and two clusters offering each other one edge merge. label = each node's cluster's
  //   smallest node. incident_edges lists each node's edges (incident_ptr: its range); an edge
  //   whose two ends are one node never offers. work: scratch.
  m.def("multigrid_match_clusters(Tensor edge_keys, Tensor edge_ends, Tensor incident_ptr, Tensor incident_edges, "
        "int most, int rounds, Tensor(a!) label, Tensor(b!) work) -> ()");
}
