// Schemas of the CG ops (implementations: cpu.cpp, cuda.cu; the scalar logic: common/cg.h, the
// checks: common/cg_checks.h). They update the CG state in place and return nothing, so that a
// fixed sequence of them (one CG iteration) can be captured once in a CUDA graph and replayed with
// no host round trip. The pure-torch reference and the fake kernels: the Python module named below
// (set_python_module), imported when torch needs them.
//
// The chunk plan = (chunk_start [K + 1], chunk_object [K], object_chunk [B + 1]) int64 (Python:
// solver.segments.ChunkPlan); scratch [K] float64; status, iterations, counter [B] int32 (counter
// all zero between calls). Objects that are not active are skipped.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tensormass, m) {
  m.set_python_module("tensormass_torch.ops.cg");
  // cg_alpha(p_dot_ap [V], <chunk plan>, rr [B], status!, alpha!, scratch!, counter!)
  //   alpha = rr / the object's sum of p . Ap (or the object stops: breakdown, non-finite).
  m.def("cg_alpha(Tensor p_dot_ap, Tensor chunk_start, Tensor chunk_object, Tensor object_chunk, Tensor rr, "
        "Tensor(a!) status, Tensor(b!) alpha, Tensor(c!) scratch, Tensor(d!) counter) -> ()");
  // cg_alpha_dot(p, ap! [V] or [V, d], free? [V, 1], <chunk plan>, rr [B], status!, alpha!, scratch!, counter!)
  //   cg_alpha from the vectors, for a product that is not fused with its dots: on the nodes of
  //   active objects Ap is projected in place (Ap *= free) and p . Ap per node summed per object
  //   as cg_alpha sums its per-node dots; one pass where the projection, the dots and cg_alpha
  //   took four.
  m.def("cg_alpha_dot(Tensor p, Tensor(a!) ap, Tensor? free, Tensor chunk_start, Tensor chunk_object, "
        "Tensor object_chunk, Tensor rr, Tensor(b!) status, Tensor(c!) alpha, Tensor(d!) scratch, "
        "Tensor(e!) counter) -> ()");
  // cg_update(x!, r!, p, ap [V, d], alpha [B], <chunk plan>, threshold [B], max_iter, rr!, status!,
  //           beta!, iterations!, scratch!, counter!)
  //   x += alpha p, r -= alpha Ap, rr_new = r . r per object; the object stops (converged: rr_new <=
  //   threshold, non-finite, the iteration cap) or beta = rr_new / rr.
  //   With inverse_blocks [V, d, d] (B^-1, one block a node, d <= 3) and z! [V, d]: the update
  //   preconditioned by the block diagonal B, in the same pass: z = B^-1 r and rr_new = r . z
  //   (common/cg.h: BlockUpdate); the CG's direction is then p = z + beta p.
  m.def("cg_update(Tensor(a!) x, Tensor(b!) r, Tensor p, Tensor ap, Tensor alpha, Tensor chunk_start, "
        "Tensor chunk_object, Tensor object_chunk, Tensor threshold, int max_iter, Tensor(c!) rr, "
        "Tensor(d!) status, Tensor(e!) beta, Tensor(f!) iterations, Tensor(g!) scratch, Tensor(h!) counter, "
        "Tensor? inverse_blocks=None, Tensor(i!)? z=None) -> ()");
  // cg_direction(p!, r, beta [B], status, <chunk plan>, node_inverse?, arm?, node_body?, coarse?, weight)
  //   p = r + beta p. With a coarse term (node_inverse [V] or [V, 3, 3], arm [V, 3], node_body [V]
  //   int32, coarse [6 B]: the rigid correction's basis and coarse solution, common/rigid_modes.h)
  //   p = r + weight Z' coarse + beta p (r: block Jacobi's z = B^-1 r; p [V, 3]).
  m.def("cg_direction(Tensor(a!) p, Tensor r, Tensor beta, Tensor status, Tensor chunk_start, "
        "Tensor chunk_object, Tensor object_chunk, Tensor? node_inverse=None, Tensor? arm=None, "
        "Tensor? node_body=None, Tensor? coarse=None, float weight=1.0) -> ()");
  // cg_dot(a, b [V] or [V, d], <chunk plan>, out! [B], scratch!, counter!)
  //   per-object a . b (every object, active or not).
  m.def("cg_dot(Tensor a, Tensor b, Tensor chunk_start, Tensor chunk_object, Tensor object_chunk, "
        "Tensor(a!) out, Tensor(b!) scratch, Tensor(c!) counter) -> ()");
  // cg_dot_beta(r, z [V, d], <chunk plan>, status, rz! [B], beta! [B], scratch!, counter!)
  //   preconditioned CG's direction coefficient: per active object rz_new = r . z (cg_dot's sums),
  //   beta = rz_new / rz, rz = rz_new; objects that are not active are skipped.
  m.def("cg_dot_beta(Tensor r, Tensor z, Tensor chunk_start, Tensor chunk_object, Tensor object_chunk, "
        "Tensor status, Tensor(a!) rz, Tensor(b!) beta, Tensor(c!) scratch, Tensor(d!) counter) -> ()");
  // cg_start_status(rr [B], rhs_sq [B], tol_sq, max_iter, threshold!, status!, iterations!, alpha!, beta!,
  //                 floor? [B], gate? [B] int32)
  //   the per-object start of a solve once its residual's r.r (rr) and b.b (rhs_sq) are known
  //   (common/cg.h: start_object): threshold = tol_sq rhs_sq, raised to floor where given, infinite
  //   where the gate (another solve's statuses) is not active; status non-finite, converged, capped
  //   (max_iter 0) or active against it; iterations, alpha, beta zero. Every object.
  m.def("cg_start_status(Tensor rr, Tensor rhs_sq, float tol_sq, int max_iter, Tensor(a!) threshold, "
        "Tensor(b!) status, Tensor(c!) iterations, Tensor(d!) alpha, Tensor(e!) beta, Tensor? floor=None, "
        "Tensor? gate=None) -> ()");
  // cg_round_end(rr [B], threshold [B], round_status, round_iterations [B] int32, status!, iterations!)
  //   the end of an iterative refinement's round (common/cg.h: round_end_object): an active object
  //   takes the round's iterations and its failure (breakdown, non-finite), else the status of
  //   its new r.r (non-finite, converged or still active); the others are left as they are.
  m.def("cg_round_end(Tensor rr, Tensor threshold, Tensor round_status, Tensor round_iterations, "
        "Tensor(a!) status, Tensor(b!) iterations) -> ()");
  // cg_coarse_beta(rr [B], u, v [N, k], item_ptr [B + 1] int64, weight, status, rz! [B], beta! [B])
  //   preconditioned CG's r.z and beta for z = B^-1 r + weight Z' y with a coarse correction's
  //   vectors u = Z'^T r and v = y = E^-1 u (common/cg.h: coarse_rz): per active object
  //   rz_new = rr + weight * the sum of u . v over its items item_ptr[b] .. item_ptr[b + 1] - 1
  //   (float64, a fixed order), beta = rz_new / rz, rz = rz_new (rr: cg_update's r.B^-1 r).
  m.def("cg_coarse_beta(Tensor rr, Tensor u, Tensor v, Tensor item_ptr, float weight, Tensor status, "
        "Tensor(a!) rz, Tensor(b!) beta) -> ()");
  // cg_pair_term(r [V, 3], z! [V, 3], nodes [K, 2] int64, blocks [K, 3, 3], item_ptr [B + 1] int64,
  //              rr [B], status, rz! [B], beta! [B], dots! [K] float64, step)
  //   paired blocks beside block Jacobi (common/cg.h: pair_term_item): for the pairs
  //   item_ptr[b] .. item_ptr[b + 1] - 1 of each active object b, z_i += O r_j and z_j += O^T r_i
  //   (O = blocks[k], (i, j) = nodes[k]; no node in two pairs) and dots[k] = r_i . O r_j + r_j . O^T
  //   r_i; then rz_new = rr + the object's sum of dots (float64, a fixed order); with step beta =
  //   rz_new / rz and rz = rz_new, else rz = rz_new (beta untouched). Pairs past item_ptr[B] are
  //   not read; the dots of skipped objects' pairs are left as they were.
  m.def("cg_pair_term(Tensor r, Tensor(a!) z, Tensor nodes, Tensor blocks, Tensor item_ptr, Tensor rr, "
        "Tensor status, Tensor(b!) rz, Tensor(c!) beta, Tensor(d!) dots, bool step) -> ()");
  // euler_update(x!, v!, dv, dv_imposed?, h, x_new!, v_new!, <chunk plan>, status, iterations, rr, rhs_sq,
  //              norms!, summary!, scratch!, counter! [B + 1], ring!?, ring_pos!?, carry, h_old=0)
  //   the end of an implicit step after its CG (common/cg.h: EulerUpdate, StepSummary):
  //   v_new = (v + dv) + dv_imposed, x_new = x + h v_new, or x + h_old v + (h - h_old) v_new where
  //   h_old != 0 (the trapezoidal rule's h / 2) (with carry also into x and v: the next
  //   chained step starts there), the per-object |v_new|^2 into norms and the step's summary [5, B]
  //   float64 (status, iterations, rr, rhs_sq, norms), also into row ring_pos of ring [R, 5, B] when
  //   given, ring_pos [1] int64 then advanced by one.
  m.def("euler_update(Tensor(a!) x, Tensor(b!) v, Tensor dv, Tensor? dv_imposed, float h, Tensor(c!) x_new, "
        "Tensor(d!) v_new, Tensor chunk_start, Tensor chunk_object, Tensor object_chunk, Tensor status, "
        "Tensor iterations, Tensor rr, Tensor rhs_sq, Tensor(e!) norms, Tensor(f!) summary, Tensor(g!) scratch, "
        "Tensor(h!) counter, Tensor(i!)? ring, Tensor(j!)? ring_pos, bool carry, float h_old=0.0) -> ()");
}
