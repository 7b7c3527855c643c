// The batched conjugate gradient's per-object scalar logic, written once for the CPU and CUDA
// implementations of the CG ops (cpu/cg_cpu.cpp, cuda/cg_cuda.cu), and the host-side checks.
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
// Objects that are not active are skipped by every kernel: their iterates stay as they were.
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/Optional.h>

#include <cstdint>
#include <string>

#include "element_math.h"

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

// The start of a solve from x0 = 0 (CGSolver.start): r = p = b, rr = b.b; the object is
// non-finite, already converged (b.b <= tol^2 b.b, i.e. b = 0), capped (max_iter = 0) or active.
template <typename S>
TM_HD int32_t cg_start_status(S rr, S threshold, int64_t max_iter) {
  if (!finite_value(rr)) return kNonfinite;
  if (rr <= threshold) return kConverged;
  return max_iter == 0 ? kCapped : kActive;
}

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
// euler_update (cg_ops.cpp): per value v_new = (v + dv) + dv_imposed, x_new = x + h v_new (and,
// when `carry`, x = x_new, v = v_new: the next chained step starts there), the per-object
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

  // The update of value j; returns v_new[j].
  TM_HD S operator()(int64_t j) const { return apply(j, dv[j]); }

  // The same with value j of dv given (a solve that holds it: hooke_node_solve_step).
  TM_HD S apply(int64_t j, S dv_j) const {
    S vn = v[j] + dv_j;
    if (dv_imposed != nullptr) vn += dv_imposed[j];
    const S xn = x[j] + h * vn;
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

// The buffers of a whole solve by the pipelined CG (hooke_node_solve; GPU: cuda/cg_pipelined.cuh):
// the iterates and scalars, and its own work: each node's r, w = A r and s = A p in an exchange
// row of 4d values (two rows per node: one parity read, the other written), the per-chunk sums
// of r.r and w.r (two parities), and counters.
template <typename S>
struct PipelinedSolve : CGIterates<S> {
  S* exchange;          // [2, V, 4d]
  double* sums;         // [4K]: r.r then w.r per chunk, for each parity
  int32_t* counters;    // [3]: active objects in the last three iterations (rotating)
  int64_t chunk_nodes;  // nodes of the chunk with the most: picks the layout (cuda/cg_pipelined.cuh)
  int64_t chunk_slots;  // slots of the chunk with the most (sum of incidences over its nodes; shared layout)
  int64_t max_slots;    // slots of the node with the most (N_n)
  int64_t cached_neighbors = 0, cached_ks = 0;  // streamed layout: a node's first slots kept in shared memory
  bool pair_rows = true;  // streamed layout: mirror rows share their slots' work (cuda/cg_pipelined.cuh NodeSlots)
  StepEnd<S> end;       // the step's end, or none (end.update.x == nullptr)
  StepRhs<S> step_rhs;  // each step's right-hand side computed first, or none (step_rhs.rest == nullptr)
  int64_t steps = 1;    // with step_rhs: implicit Euler steps run back to back (end.update.carry)
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

// ------------------------------------------------------------------ host-side checks

struct CGPlan {
  const int64_t* chunk_start;   // [K + 1] node offsets
  const int64_t* chunk_object;  // [K]
  const int64_t* object_chunk;  // [B + 1] chunk offsets
  int64_t num_chunks, num_objects, num_nodes;
};

inline std::string cg_shape_str(at::IntArrayRef shape) {
  std::string out = "[";
  for (size_t i = 0; i < shape.size(); ++i) out += (i ? ", " : "") + std::to_string(shape[i]);
  return out + "]";
}

inline void cg_check(const at::Tensor& t, const char* name, const at::Tensor& like, at::ScalarType dtype,
                     at::IntArrayRef shape) {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.device() == like.device(), "tensormass: ", name, " is on ", t.device().str(), " but the CG state is on ",
              like.device().str());
  TORCH_CHECK(t.scalar_type() == dtype, "tensormass: ", name, " is ", c10::toString(t.scalar_type()), "; expected ",
              c10::toString(dtype));
  TORCH_CHECK(t.sizes() == shape, "tensormass: ", name, " has shape ", cg_shape_str(t.sizes()), "; expected ",
              cg_shape_str(shape));
  TORCH_CHECK(t.is_contiguous(), "tensormass: ", name, " must be contiguous");
}

// Checks the chunk plan against B objects and V nodes (sizes only: the offsets are trusted, as
// they come from solver.segments.ChunkPlan).
inline CGPlan cg_plan(const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                      const at::Tensor& like, int64_t num_nodes) {
  TORCH_CHECK(chunk_object.dim() == 1, "tensormass: chunk_object must be [K]");
  TORCH_CHECK(object_chunk.dim() == 1 && object_chunk.size(0) >= 2, "tensormass: object_chunk must be [B + 1], B >= 1");
  const int64_t k = chunk_object.size(0), b = object_chunk.size(0) - 1;
  cg_check(chunk_start, "chunk_start", like, at::kLong, {k + 1});
  cg_check(chunk_object, "chunk_object", like, at::kLong, {k});
  cg_check(object_chunk, "object_chunk", like, at::kLong, {b + 1});
  return CGPlan{chunk_start.data_ptr<int64_t>(), chunk_object.data_ptr<int64_t>(), object_chunk.data_ptr<int64_t>(),
                k, b, num_nodes};
}

inline void cg_check_scalars(const at::Tensor& t, const char* name, const at::Tensor& like, int64_t num_objects) {
  cg_check(t, name, like, like.scalar_type(), {num_objects});
}

inline void cg_check_state(const at::Tensor& t, const char* name, const at::Tensor& like, int64_t num_objects) {
  cg_check(t, name, like, at::kInt, {num_objects});
}

inline void cg_check_values(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.scalar_type() == at::kFloat || t.scalar_type() == at::kDouble, "tensormass: ", name,
              " must be float32 or float64, got ", c10::toString(t.scalar_type()));
  TORCH_CHECK(t.dim() >= 1 && t.is_contiguous(), "tensormass: ", name, " must be a contiguous [V] or [V, d] tensor");
}

// The checks of each op, written once for both backends; each returns the plan.
inline CGPlan check_cg_alpha(const at::Tensor& p_dot_ap, const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                             const at::Tensor& object_chunk, const at::Tensor& rr, const at::Tensor& status,
                             const at::Tensor& alpha, const at::Tensor& scratch, const at::Tensor& counter) {
  cg_check_values(p_dot_ap, "p_dot_ap");
  TORCH_CHECK(p_dot_ap.dim() == 1, "tensormass: p_dot_ap must be [V] (p . Ap per node)");
  CGPlan plan = cg_plan(chunk_start, chunk_object, object_chunk, p_dot_ap, p_dot_ap.size(0));
  cg_check_scalars(rr, "rr", p_dot_ap, plan.num_objects);
  cg_check_scalars(alpha, "alpha", p_dot_ap, plan.num_objects);
  cg_check_state(status, "status", p_dot_ap, plan.num_objects);
  cg_check(scratch, "scratch", p_dot_ap, at::kDouble, {plan.num_chunks});
  cg_check_state(counter, "counter", p_dot_ap, plan.num_objects);
  return plan;
}

inline CGPlan check_cg_update(const at::Tensor& x, const at::Tensor& r, const at::Tensor& p, const at::Tensor& ap,
                              const at::Tensor& alpha, const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                              const at::Tensor& object_chunk, const at::Tensor& threshold, int64_t max_iter,
                              const at::Tensor& rr, const at::Tensor& status, const at::Tensor& beta,
                              const at::Tensor& iterations, const at::Tensor& scratch, const at::Tensor& counter) {
  cg_check_values(x, "x");
  TORCH_CHECK(max_iter >= 0, "tensormass: max_iter must be >= 0, got ", std::to_string(max_iter));
  CGPlan plan = cg_plan(chunk_start, chunk_object, object_chunk, x, x.size(0));
  cg_check(r, "r", x, x.scalar_type(), x.sizes());
  cg_check(p, "p", x, x.scalar_type(), x.sizes());
  cg_check(ap, "ap", x, x.scalar_type(), x.sizes());
  cg_check_scalars(alpha, "alpha", x, plan.num_objects);
  cg_check_scalars(threshold, "threshold", x, plan.num_objects);
  cg_check_scalars(rr, "rr", x, plan.num_objects);
  cg_check_scalars(beta, "beta", x, plan.num_objects);
  cg_check_state(status, "status", x, plan.num_objects);
  cg_check_state(iterations, "iterations", x, plan.num_objects);
  cg_check(scratch, "scratch", x, at::kDouble, {plan.num_chunks});
  cg_check_state(counter, "counter", x, plan.num_objects);
  return plan;
}

inline CGPlan check_cg_direction(const at::Tensor& p, const at::Tensor& r, const at::Tensor& beta,
                                 const at::Tensor& status, const at::Tensor& chunk_start,
                                 const at::Tensor& chunk_object, const at::Tensor& object_chunk) {
  cg_check_values(p, "p");
  CGPlan plan = cg_plan(chunk_start, chunk_object, object_chunk, p, p.size(0));
  cg_check(r, "r", p, p.scalar_type(), p.sizes());
  cg_check_scalars(beta, "beta", p, plan.num_objects);
  cg_check_state(status, "status", p, plan.num_objects);
  return plan;
}

inline CGPlan check_cg_dot(const at::Tensor& a, const at::Tensor& b, const at::Tensor& chunk_start,
                           const at::Tensor& chunk_object, const at::Tensor& object_chunk, const at::Tensor& out,
                           const at::Tensor& scratch, const at::Tensor& counter) {
  cg_check_values(a, "a");
  CGPlan plan = cg_plan(chunk_start, chunk_object, object_chunk, a, a.size(0));
  cg_check(b, "b", a, a.scalar_type(), a.sizes());
  cg_check_scalars(out, "out", a, plan.num_objects);
  cg_check(scratch, "scratch", a, at::kDouble, {plan.num_chunks});
  cg_check_state(counter, "counter", a, plan.num_objects);
  return plan;
}

// ------------------------------------------------------------------ the end of an implicit Euler step: checks

inline CGPlan check_euler_update(const at::Tensor& x, const at::Tensor& v, const at::Tensor& dv,
                                 const c10::optional<at::Tensor>& dv_imposed, const at::Tensor& x_new,
                                 const at::Tensor& v_new, const at::Tensor& chunk_start,
                                 const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                                 const at::Tensor& status, const at::Tensor& iterations, const at::Tensor& rr,
                                 const at::Tensor& rhs_sq, const at::Tensor& norms, const at::Tensor& summary,
                                 const at::Tensor& scratch, const at::Tensor& counter,
                                 const c10::optional<at::Tensor>& ring, const c10::optional<at::Tensor>& ring_pos) {
  cg_check_values(x, "x");
  CGPlan plan = cg_plan(chunk_start, chunk_object, object_chunk, x, x.size(0));
  for (const auto& named : {std::make_pair(&v, "v"), std::make_pair(&dv, "dv"), std::make_pair(&x_new, "x_new"),
                            std::make_pair(&v_new, "v_new")}) {
    cg_check(*named.first, named.second, x, x.scalar_type(), x.sizes());
  }
  if (dv_imposed.has_value() && dv_imposed->defined()) cg_check(*dv_imposed, "dv_imposed", x, x.scalar_type(), x.sizes());
  const int64_t b = plan.num_objects;
  cg_check_state(status, "status", x, b);
  cg_check_state(iterations, "iterations", x, b);
  cg_check_scalars(rr, "rr", x, b);
  cg_check_scalars(rhs_sq, "rhs_sq", x, b);
  cg_check_scalars(norms, "norms", x, b);
  cg_check(summary, "summary", x, at::kDouble, {5, b});
  cg_check(scratch, "scratch", x, at::kDouble, {plan.num_chunks});
  cg_check(counter, "counter", x, at::kInt, {b + 1});
  const bool has_ring = ring.has_value() && ring->defined();
  TORCH_CHECK(has_ring == (ring_pos.has_value() && ring_pos->defined()), "tensormass: ring and ring_pos go together");
  if (has_ring) {
    TORCH_CHECK(ring->dim() == 3, "tensormass: ring must be [R, 5, B], got shape ", cg_shape_str(ring->sizes()));
    cg_check(*ring, "ring", x, at::kDouble, {ring->size(0), 5, b});
    cg_check(*ring_pos, "ring_pos", x, at::kLong, {1});
  }
  return plan;
}

// Values per node of a [V] or [V, d] tensor.
inline int64_t values_per_node(const at::Tensor& t) { return t.size(0) ? t.numel() / t.size(0) : 1; }

// The ops' structs over their tensors (checked by check_euler_update).
template <typename S>
inline EulerUpdate<S> euler_update_of(at::Tensor& x, at::Tensor& v, const at::Tensor& dv,
                                      const c10::optional<at::Tensor>& dv_imposed, double h, at::Tensor& x_new,
                               at::Tensor& v_new, bool carry) {
  const bool imposed = dv_imposed.has_value() && dv_imposed->defined();
  return EulerUpdate<S>{x.data_ptr<S>(), v.data_ptr<S>(), dv.data_ptr<S>(), imposed ? dv_imposed->data_ptr<S>() : nullptr,
                        static_cast<S>(h), x_new.data_ptr<S>(), v_new.data_ptr<S>(), carry, values_per_node(x)};
}

template <typename S>
inline StepSummary<S> step_summary_of(const at::Tensor& status, const at::Tensor& iterations, const at::Tensor& rr,
                               const at::Tensor& rhs_sq, at::Tensor& norms, at::Tensor& summary,
                               const c10::optional<at::Tensor>& ring, const c10::optional<at::Tensor>& ring_pos) {
  const bool has_ring = ring.has_value() && ring->defined();
  return StepSummary<S>{status.data_ptr<int32_t>(), iterations.data_ptr<int32_t>(), rr.data_ptr<S>(),
                        rhs_sq.data_ptr<S>(), norms.data_ptr<S>(), summary.data_ptr<double>(),
                        has_ring ? ring->data_ptr<double>() : nullptr, has_ring ? ring_pos->data_ptr<int64_t>() : nullptr,
                        has_ring ? ring->size(0) : 0};
}

}  // namespace tensormass
