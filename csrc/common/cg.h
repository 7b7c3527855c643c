// The batched conjugate gradient's per-object scalar logic and the structs its kernels read,
// written once for the CPU and CUDA implementations of the CG ops (cg/cpu.cpp, cg/cuda.cu) and of
// the whole solves (solve/). The host-side checks: cg_checks.h.
//
// The CG runs on packed objects: object b owns the contiguous nodes of its chunks. A chunk is a
// contiguous node range inside one object (Python: solver.segments.ChunkPlan); every reduction
// sums each chunk in a fixed order (into a double), then each object's chunk sums in chunk order,
// so the results do not depend on thread counts or timing: deterministic, no atomics on values.
// (On the GPU one atomic counter per object only elects which block does the final sum.)
//
// One iteration = matvec (kernel 1 + gather_system: Ap and p.Ap per node), then
//   cg_alpha      p_ap_b = sum p.Ap;  alpha_b = rr_b / p_ap_b  (or the object stops: breakdown)
//   cg_update     x += alpha p;  r -= alpha Ap;  rr_new_b = sum r.r;  beta_b = rr_new_b / rr_b
//                 (or the object stops: converged, non-finite, iteration cap)
//   cg_direction  p = r + beta p
// (block-preconditioned: cg_update also z = B^-1 r, and the direction takes z for r; with a coarse
// correction, cg_coarse_beta takes beta and cg_direction adds the coarse part: coarse_rz below).
// Objects that are not active are skipped by every kernel: their iterates stay as they were.
#pragma once

#include <cstdint>
#include <limits>

#include "common/element_math.h"
#include "common/rigid_modes.h"

namespace tensormass {

// Per-object CG status (Python: solver.cg.STATUS).
enum CGStatus : int32_t { kActive = 0, kConverged = 1, kBreakdown = 2, kNonfinite = 3, kCapped = 4 };

template <typename S>
TM_HD bool finite_value(S v) {
  return v - v == S(0);  // false for inf and NaN (no fast-math in this build)
}

// After the matvec: the step length, or the object stops on a curvature that is not positive
// (an indefinite system) or not finite.
template <typename S>
TM_HD S cg_alpha_step(double p_ap_sum, S rr, int32_t& status) {
  const S p_ap = static_cast<S>(p_ap_sum);
  if (!(p_ap > S(0))) {  // also NaN
    status = finite_value(p_ap) ? kBreakdown : kNonfinite;
    return S(0);
  }
  return rr / p_ap;
}

// After the update of x and r: convergence (||r|| <= tol ||b||, i.e. r.r <= threshold), the
// iteration cap, and the next direction's beta.
template <typename S>
TM_HD S cg_beta_step(double rr_new_sum, S& rr, S threshold, int64_t max_iter, int32_t& status,
                     int32_t& iterations) {
  const S rr_new = static_cast<S>(rr_new_sum);
  iterations += 1;
  if (!finite_value(rr_new)) {
    status = kNonfinite;
    return S(0);
  }
  const S rr_old = rr;
  rr = rr_new;
  if (rr_new <= threshold) {
    status = kConverged;
    return S(0);
  }
  if (iterations >= max_iter) {
    status = kCapped;
    return S(0);
  }
  return rr_new / rr_old;
}

// Preconditioned CG's direction coefficient after z = M^-1 r: beta = r'.z' / r.z, and r.z kept
// for the next iteration.
template <typename S>
TM_HD S pcg_beta_step(S rz_new, S& rz) {
  const S beta = rz_new / rz;
  rz = rz_new;
  return beta;
}

// A coarse correction beside block Jacobi (the rigid modes', solver/rigid_modes.py): M^-1 r = z +
// weight Z' y, z = B^-1 r (cg_update's) and y = E^-1 g the coarse solution of g = Z'^T r. Its
// r . M^-1 r = r.z + weight (Z'^T r) . y = rr + weight g . y, a sum over the bodies' six values
// (cg_coarse_beta) where r . (M^-1 r) took a pass over the nodes; and the direction p = M^-1 r +
// beta p adds the coarse part at each node (cg_direction with the coarse term), so the corrected
// z is never stored.
template <typename S>
TM_HD S coarse_rz(S rr, double coarse_dot, double weight) {
  return static_cast<S>(static_cast<double>(rr) + weight * coarse_dot);
}

template <typename S>
TM_HD void coarse_direction_node(int64_t i, const S* z, S beta, S* p, const RigidMotion<S>& coarse) {
  S moved[3];
  coarse.at(i, moved);
  TM_UNROLL for (int k = 0; k < 3; ++k) p[i * 3 + k] = (z[i * 3 + k] + moved[k]) + beta * p[i * 3 + k];
}

// Paired blocks beside block Jacobi (solver/preconditioner.py: BlockJacobi with pairs): two nodes
// i, j that a contact pair couples are one 6 x 6 block of the preconditioner, whose inverse holds
// D_i, D_j on its diagonal (cg_update's B^-1 at i and j) and O, O^T off it (O the block (i, j)).
// cg_pair_term adds the off-diagonal part to z = B^-1 r: z_i += O r_j, z_j += O^T r_i, and
// returns its part of r . z, r_i . O r_j + r_j . O^T r_i. Every node is in at most one pair, so the
// writes of two pairs never meet. nodes [K, 2], blocks [K, 3, 3] row-major.
template <typename S>
TM_HD double pair_term_item(int64_t k, const int64_t* nodes, const S* blocks, const S* r, S* z) {
  const int64_t i = nodes[2 * k], j = nodes[2 * k + 1];
  const S* o = blocks + 9 * k;
  S ri[3], rj[3];
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    ri[a] = r[i * 3 + a];
    rj[a] = r[j * 3 + a];
  }
  double dot = 0.0;
  TM_UNROLL for (int a = 0; a < 3; ++a) {
    const S at_i = o[3 * a] * rj[0] + o[3 * a + 1] * rj[1] + o[3 * a + 2] * rj[2];  // (O r_j)_a
    const S at_j = o[a] * ri[0] + o[3 + a] * ri[1] + o[6 + a] * ri[2];              // (O^T r_i)_a
    z[i * 3 + a] += at_i;
    z[j * 3 + a] += at_j;
    dot += static_cast<double>(ri[a]) * static_cast<double>(at_i) + static_cast<double>(rj[a]) * static_cast<double>(at_j);
  }
  return dot;
}

// The end of cg_pair_term for one object: rz_new = rr + its pairs' sum; with step, preconditioned
// CG's beta = rz_new / rz and rz = rz_new (pcg_beta_step), else rz = rz_new only (a coarse
// correction then takes rz for its rr: cg_coarse_beta).
template <typename S>
TM_HD void pair_rz_end(S rr, double pair_dot, bool step, S& rz, S& beta) {
  const S rz_new = static_cast<S>(static_cast<double>(rr) + pair_dot);
  if (step) {
    beta = pcg_beta_step<S>(rz_new, rz);
  } else {
    rz = rz_new;
  }
}

// The start of a solve from x0 = 0 (CGSolver.start): r = p = b, rr = b.b; the object is
// non-finite, already converged (b.b <= tol^2 b.b, i.e. b = 0), capped (max_iter = 0) or active.
template <typename S>
TM_HD int32_t cg_start_status(S rr, S threshold, int64_t max_iter) {
  if (!finite_value(rr)) return kNonfinite;
  if (rr <= threshold) return kConverged;
  return max_iter == 0 ? kCapped : kActive;
}

// cg_start_status for one object: the start of a solve from its residual's r.r once known. The
// threshold is tol^2 b.b, raised to floor where one is given (a refinement's correction: no
// tighter than the solve it corrects needs), and infinite where the gate (another solve's
// statuses) holds the object stopped: it then starts converged (unless its r.r is not finite) and
// does not iterate, its correction staying zero, also where a later start reads the threshold
// again (the pipelined solve from an iterate). The status is cg_start_status's; the iteration
// count and the step scalars start at zero.
template <typename S>
TM_HD void start_object(S rr, S rhs_sq, S tol_sq, int64_t max_iter, const S* floor, const int32_t* gate,
                        int64_t b, S& threshold, int32_t& status, int32_t& iterations, S& alpha, S& beta) {
  S t = rhs_sq * tol_sq;
  if (floor != nullptr && t < floor[b]) t = floor[b];
  if (gate != nullptr && gate[b] != kActive) t = std::numeric_limits<S>::infinity();
  threshold = t;
  status = cg_start_status<S>(rr, t, max_iter);
  iterations = 0;
  alpha = S(0);
  beta = S(0);
}

// cg_round_end for one object: the end of a refinement round (solver/refine.py). An object still
// active takes the round's iterations and the round's failure (breakdown, non-finite), else the
// status of its new residual's r.r against its threshold (non-finite, converged or active: the
// cap is the rounds', kept by the caller).
template <typename S>
TM_HD void round_end_object(S rr, S threshold, int32_t round_status, int32_t round_iterations, int32_t& status,
                            int32_t& iterations) {
  if (status != kActive) return;
  iterations += round_iterations;
  if (round_status == kBreakdown || round_status == kNonfinite) {
    status = round_status;
    return;
  }
  status = cg_start_status<S>(rr, threshold, 1);
}

// cg_alpha_dot's node kernel (cg/schema.cpp), for chunk_alpha_cpu / chunk_alpha_kernel: node i's
// Ap_i projected in place (times free_i where a mask is given) and p_i . Ap_i, summed over its d
// values in order.
template <typename S>
struct ProjectedDots {
  using Scalar = S;
  const S* p;     // [V, d]
  S* ap;          // [V, d]
  const S* free;  // [V] or nullptr
  int64_t d;

  TM_HD S apply(int64_t i) const {
    const S mask = free != nullptr ? free[i] : S(1);
    S dot = S(0);
    for (int64_t k = 0; k < d; ++k) {
      const S value = free != nullptr ? ap[i * d + k] * mask : ap[i * d + k];
      if (free != nullptr) ap[i * d + k] = value;
      dot += p[i * d + k] * value;
    }
    return dot;
  }
};

// cg_update preconditioned by a block diagonal (its inverse_blocks and z, cg/schema.cpp): node i's
// x_i += a p_i, r_i -= a Ap_i, z_i = B_i^-1 r_i with B_i^-1 its inverse block [d, d] (row-major),
// and r_i . z_i summed over its d values in order. The CG that runs on it is preconditioned CG
// whose "rr" is r.z (the B^-1 norm of the residual): the step length rr / p.Ap and the stopping rule
// rr <= threshold read it as they read r.r, and the direction is p = z + beta p. d <= kMaxBlock.
constexpr int64_t kMaxBlock = 3;

template <typename S>
struct BlockUpdate {
  S* x;              // [V, d]
  S* r;              // [V, d]
  const S* p;        // [V, d]
  const S* ap;       // [V, d]
  const S* inverse;  // [V, d, d]
  S* z;              // [V, d]
  int64_t d;

  TM_HD double apply(int64_t i, S a) const {
    S ri[kMaxBlock];
    for (int64_t k = 0; k < d; ++k) {
      const int64_t j = i * d + k;
      x[j] += a * p[j];
      ri[k] = r[j] - a * ap[j];
      r[j] = ri[k];
    }
    const S* block = inverse + i * d * d;
    double dot = 0.0;
    for (int64_t k = 0; k < d; ++k) {
      S zk = S(0);
      for (int64_t m = 0; m < d; ++m) zk += block[k * d + m] * ri[m];
      z[i * d + k] = zk;
      dot += static_cast<double>(ri[k]) * static_cast<double>(zk);
    }
    return dot;
  }
};

// What every whole-solve op writes: the iterates [V, d] and the per-object scalars [B], with the
// start's inputs (the right-hand side and tolerance) and the cap.
template <typename S>
struct CGIterates {
  S* x;
  S* r;
  S* p;
  const S* rhs;         // [V, d], or nullptr: go on from the current state (no start; hooke_node_cg)
  S tol_sq;             // start: threshold = tol^2 b.b
  S* threshold;
  S* rhs_sq;
  S* rr;
  S* alpha;
  S* beta;
  int32_t* status;
  int32_t* iterations;
  int64_t max_iter;
};

// ------------------------------------------------------------------ the end of an implicit Euler step
//
// euler_update (cg/schema.cpp): per value v_new = (v + dv) + dv_imposed, x_new = x + h v_new, or
// with h_old != 0 x_new = x + h_old v + (h - h_old) v_new (the trapezoidal / Newmark average-
// acceleration position update, h_old = h / 2; h_old = 0 is backward Euler's, computed as it always
// was) (and, when `carry`, x = x_new, v = v_new: the next chained step starts there), the per-object
// |v_new|^2 (summed as cg_dot sums) into norms, and the step's summary [5, B] float64 (status,
// iterations, rr, rhs_sq, norms), also into row ring_pos of ring [R, 5, B] when given, ring_pos
// then advanced by one.
template <typename S>
struct EulerUpdate {
  S* x;
  S* v;
  const S* dv;
  const S* dv_imposed;  // or nullptr
  S h;
  S* x_new;
  S* v_new;
  bool carry;
  int64_t d;
  S h_old;  // the old velocity's share of the step's motion (0: backward Euler)

  // The update of value j; returns v_new[j].
  TM_HD S operator()(int64_t j) const { return apply(j, dv[j]); }

  // The same with value j of dv given (a solve that holds it: hooke_node_solve_step).
  TM_HD S apply(int64_t j, S dv_j) const {
    S vn = v[j] + dv_j;
    if (dv_imposed != nullptr) vn += dv_imposed[j];
    const S xn = h_old == S(0) ? x[j] + h * vn : x[j] + h_old * v[j] + (h - h_old) * vn;
    x_new[j] = xn;
    v_new[j] = vn;
    if (carry) {
      x[j] = xn;
      v[j] = vn;
    }
    return vn;
  }
};

// The summary of a step and where it goes.
template <typename S>
struct StepSummary {
  const int32_t* status;
  const int32_t* iterations;
  const S* rr;
  const S* rhs_sq;
  S* norms;
  double* summary;     // [5, B]
  double* ring;        // [R, 5, B] or nullptr
  int64_t* ring_pos;   // [1]
  int64_t ring_rows;

  // Object b's column, its norm given (ring row `pos`, read before any object advanced it).
  TM_HD void write(int64_t b, int64_t num_objects, double norm_sq, int64_t pos) const {
    write_values(b, num_objects, status[b], iterations[b], rr[b], rhs_sq[b], norm_sq, pos);
  }

  // The same with the solve's outcome given (a solve that holds it: hooke_node_solve_step).
  TM_HD void write_values(int64_t b, int64_t num_objects, int32_t status_b, int32_t iterations_b, S rr_b, S rhs_sq_b,
                          double norm_sq, int64_t pos) const {
    const S norm = static_cast<S>(norm_sq);
    norms[b] = norm;
    const double column[5] = {static_cast<double>(status_b), static_cast<double>(iterations_b),
                              static_cast<double>(rr_b), static_cast<double>(rhs_sq_b), static_cast<double>(norm)};
    for (int k = 0; k < 5; ++k) {
      summary[k * num_objects + b] = column[k];
      if (ring != nullptr && pos >= 0 && pos < ring_rows) ring[(pos * 5 + k) * num_objects + b] = column[k];
    }
  }
};

// The end of a step done by the solve that computed its dv (hooke_node_solve_step): the update,
// the summary, and the object sums of |v_new|^2 (sums [K] float64 over the solve's chunks,
// counter [B + 1] int32, zero between calls). update.x == nullptr: the solve ends there.
template <typename S>
struct StepEnd {
  EulerUpdate<S> update{};
  StepSummary<S> summary{};
  double* sums = nullptr;
  int32_t* counter = nullptr;
};

// The right-hand side a solve computes before itself (hooke_node_steps): at the state x, v of
// its step end (EulerUpdate's x, v: each step's carried state), rhs = h (f((x - rest) + c_w v)
// + external + contact(x) - Kc (c_w v) - r_M mass v) over the node graph, u = x - rest and the
// contact stiffness Kc (which the solve's products then read), each node's slots summed in slot
// order by one thread: hooke_node_step_rhs's values (NodeHookeStepRhsKernel), bitwise.
// rest == nullptr: the solve's rhs is given.
template <typename S>
struct StepRhs {
  const S* rest = nullptr;      // [V, d]
  const S* external = nullptr;  // [V, d]
  S h = S(0), c_w = S(0), rayleigh_mass = S(0);
  const S* plane_normals = nullptr;  // [P, 3], offsets [P], stiffness [P] (PenaltyPlanes); P = 0: none
  const S* plane_offsets = nullptr;
  const S* plane_stiffness = nullptr;
  int64_t planes = 0;
  S* u = nullptr;               // [V, d] out
  S* rhs = nullptr;             // [V, d] out: the solve's rhs
  S* node_stiffness = nullptr;  // [V, 3, 3] out with planes: the solve's epilogue's contact stiffness
};

// The buffers of a whole CG solve run by one op (hooke_node_cg): the iterates and scalars, and
// what only the GPU's persistent kernel uses: the scalars of the other parity (an iteration reads
// one parity and writes the other, so that no block overwrites a scalar another block may still
// read), the status after each step length, two counters of active objects, and two sets of
// chunk sums.
template <typename S>
struct CGRun : CGIterates<S> {
  S* ap;
  const S* free;        // [V] 0/1 projection of rhs, or nullptr
  S* rr_swap;           // [B]            rr of the other parity
  int32_t* work;        // [3B + 2]       status, iterations of the other parity; status after alpha; counters
  double* sums;         // [2K]           p.Ap and r.r chunk sums
  int64_t d;            // values per node
  int64_t count;        // iterations to run at most (fewer when every object stops)
  bool cache_neighbors = true;  // GPU: keep the node graph's neighbours in shared memory (a
                                // switch for benchmarks: TENSORMASS_NEIGHBOR_CACHE=0 turns it off)
};

// The buffers of a whole solve by the pipelined CG (hooke_node_solve; GPU: solve/cg_pipelined.cuh):
// the iterates and scalars, and its own work: each node's r, w = A r and s = A p in an exchange
// row of 4d values (two rows per node: one parity read, the other written), the per-chunk sums
// of r.r and w.r (two parities), and counters.
template <typename S>
struct PipelinedSolve : CGIterates<S> {
  S* exchange;          // [2, V, 4d]
  double* sums;         // [4K]: r.r then w.r per chunk, for each parity
  int32_t* counters;    // [3]: active objects in the last three iterations (rotating)
  int64_t chunk_nodes;  // nodes of the chunk with the most: picks the layout (solve/cg_pipelined.cuh)
  int64_t chunk_slots;  // slots of the chunk with the most (sum of incidences over its nodes; shared layout)
  int64_t max_slots;    // slots of the node with the most (N_n)
  int64_t cached_neighbors = 0, cached_ks = 0;  // streamed layout: a node's first slots kept in shared memory
  bool pair_rows = true;  // streamed layout: mirror rows share their slots' work (solve/cg_pipelined.cuh NodeSlots)
  int64_t cache_slots = -1;  // streamed layout: cap on a node's slots kept in shared memory (-1: none)
  StepEnd<S> end;       // the step's end, or none (end.update.x == nullptr)
  StepRhs<S> step_rhs;  // each step's right-hand side computed first, or none (step_rhs.rest == nullptr)
  int64_t steps = 1;    // with step_rhs: implicit Euler steps run back to back (end.update.carry)
  // From the iterate a start left (hooke_node_solve's from_iterate): x0 = x, rhs = r0 = b - A x0 as
  // CGSolver.start formed it (projected), threshold = tol^2 b.b as it set it (rhs_sq, threshold
  // kept); false: from x0 = 0, rhs = b.
  bool from_iterate = false;
};

// Chronopoulos-Gear's step length from the reduction that also gave r.r: with
// gamma = r.r, delta = w.r (w = A r) and the last step's beta and alpha, p.Ap = delta - beta
// gamma / alpha_last (= delta on the first step), in double; the object stops where it is not
// positive (breakdown) or not finite, as cg_alpha_step.
template <typename S>
TM_HD S cg_pipelined_alpha(double gamma, double delta, S beta, S alpha_last, bool first, S rr, int32_t& status) {
  const double p_ap = first ? delta : delta - static_cast<double>(beta) * gamma / static_cast<double>(alpha_last);
  return cg_alpha_step<S>(p_ap, rr, status);
}

// The chunk plan, as the kernels read it (checked by cg_plan, cg_checks.h).
struct CGPlan {
  const int64_t* chunk_start;   // [K + 1] node offsets
  const int64_t* chunk_object;  // [K]
  const int64_t* object_chunk;  // [B + 1] chunk offsets
  int64_t num_chunks, num_objects, num_nodes;
};

}  // namespace tensormass
