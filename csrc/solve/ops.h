// Host side of the solve ops (schemas: schema.cpp): whole CG solves over the node graph in one op
// (hooke_node_cg; hooke_node_solve by the pipelined CG, hooke_node_solve_step ending the implicit
// Euler step, hooke_node_steps beginning each step too). Input checks and the solve's structs
// (common/cg.h) over the op's tensors; the matvec is the node graph's (common/node_graph.h). The
// launcher `L` (solve/cpu.cpp, solve/cuda.cu: the common launchers with run_cg and run_solve, the
// whole solve on its backend) instantiates these functions through register_solve_ops.
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/MemoryOverlap.h>
#include <c10/util/Optional.h>
#include <torch/library.h>

#include <cstdint>
#include <string>
#include <type_traits>
#include <utility>

#include "common/cg.h"
#include "common/cg_checks.h"
#include "common/checks.h"
#include "common/node_graph.h"
#include "common/step_rhs.h"

namespace tensormass {

// The checks every whole-solve op makes of its iterates [V, d] (like `like`), per-object scalars
// [B] and cap; returns the chunk plan.
inline CGPlan check_cg_iterates(const at::Tensor& like, const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                                const at::Tensor& object_chunk, const at::Tensor& x, const at::Tensor& r,
                                const at::Tensor& threshold, const at::Tensor& rhs_sq, const at::Tensor& rr,
                                const at::Tensor& alpha, const at::Tensor& beta, const at::Tensor& status,
                                const at::Tensor& iterations, int64_t max_iter) {
  TORCH_CHECK(max_iter >= 0, "tensormass: max_iter must be >= 0, got ", std::to_string(max_iter));
  const CGPlan plan = cg_plan(chunk_start, chunk_object, object_chunk, like, like.size(0));
  TORCH_CHECK(plan.num_chunks == 0 || like.size(0) > 0, "tensormass: a chunk plan over no nodes");
  cg_check(x, "x", like, like.scalar_type(), like.sizes());
  cg_check(r, "r", like, like.scalar_type(), like.sizes());
  for (const auto& named : {std::make_pair(&threshold, "threshold"), std::make_pair(&rhs_sq, "rhs_sq"),
                            std::make_pair(&rr, "rr"), std::make_pair(&alpha, "alpha"), std::make_pair(&beta, "beta")}) {
    cg_check_scalars(*named.first, named.second, like, plan.num_objects);
  }
  cg_check_state(status, "status", like, plan.num_objects);
  cg_check_state(iterations, "iterations", like, plan.num_objects);
  return plan;
}

// The iterates and per-object scalars of a whole-solve op, from its tensors (checked by the op).
template <typename S>
void set_cg_iterates(CGIterates<S>& s, const at::Tensor& x, const at::Tensor& r, const at::Tensor& p,
                     const S* rhs, double tol_sq, const at::Tensor& threshold, const at::Tensor& rhs_sq,
                     const at::Tensor& rr, const at::Tensor& alpha, const at::Tensor& beta, const at::Tensor& status,
                     const at::Tensor& iterations, int64_t max_iter) {
  s.x = x.data_ptr<S>();
  s.r = r.data_ptr<S>();
  s.p = p.data_ptr<S>();
  s.rhs = rhs;
  s.tol_sq = static_cast<S>(tol_sq);
  s.threshold = threshold.data_ptr<S>();
  s.rhs_sq = rhs_sq.data_ptr<S>();
  s.rr = rr.data_ptr<S>();
  s.alpha = alpha.data_ptr<S>();
  s.beta = beta.data_ptr<S>();
  s.status = status.data_ptr<int32_t>();
  s.iterations = iterations.data_ptr<int32_t>();
  s.max_iter = max_iter;
}

// hooke_node_cg: up to `count` CG iterations whose matvec is hooke_node_system's (A = c_M M -
// c_K K over the node graph, projected on `free`), preceded, when `rhs` is given, by the start
// from x0 = 0 (x = 0, r = p = free * rhs, rhs_sq = b.b, threshold = tol_sq b.b, statuses); it
// stops early once no object is active. On the GPU one persistent kernel (no launch and no host
// round trip per iteration); on the CPU the CG ops' functions in a loop. Either way the result is
// bitwise the op-by-op solve (hooke_node_system_alpha, cg_update, cg_direction) over the same
// chunk plan. Buffers: the CG state (x, r, p [V, d]; threshold, rhs_sq, rr, alpha, beta [B];
// status, iterations [B] int32), ap [V, d], and the persistent kernel's work: rr_swap [B],
// work [3B + 2] int32, sums [2K] float64.
template <class L>
void hooke_node_cg(at::Tensor p, const at::Tensor& neighbor, const at::Tensor& node_k, const at::Tensor& incidences,
                   const c10::optional<at::Tensor>& row_node, const at::Tensor& mass, const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                   const c10::optional<at::Tensor>& node_stiffness, at::Tensor ap, at::Tensor x, at::Tensor r,
                   const c10::optional<at::Tensor>& rhs, double tol_sq, const at::Tensor& chunk_start,
                   const at::Tensor& chunk_object, const at::Tensor& object_chunk, at::Tensor threshold,
                   at::Tensor rhs_sq, int64_t max_iter, int64_t count, at::Tensor rr, at::Tensor status,
                   at::Tensor alpha, at::Tensor beta, at::Tensor iterations, at::Tensor rr_swap, at::Tensor work,
                   at::Tensor sums, int64_t flags) {
  check_values(p, "p");
  TORCH_CHECK(ap.defined(), "tensormass: ap is undefined");
  TORCH_CHECK(count >= 0, "tensormass: count must be >= 0, got ", std::to_string(count));
  const CGPlan plan = check_cg_iterates(p, chunk_start, chunk_object, object_chunk, x, r, threshold, rhs_sq, rr, alpha,
                                        beta, status, iterations, max_iter);
  const bool start = rhs.has_value() && rhs->defined();
  if (start) cg_check(*rhs, "rhs", p, p.scalar_type(), p.sizes());
  cg_check_scalars(rr_swap, "rr_swap", p, plan.num_objects);
  cg_check(work, "work", p, at::kInt, {3 * plan.num_objects + 2});
  cg_check(sums, "sums", p, at::kDouble, {2 * plan.num_chunks});
  at::Tensor no_dots;
  run_hooke_node_system<L>(p, neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff, node_stiffness, ap,
                           no_dots, [&](const auto& k, int64_t) {
    using S = typename std::decay_t<decltype(k)>::Scalar;
    CGRun<S> s;
    set_cg_iterates<S>(s, x, r, p, start ? rhs->data_ptr<S>() : nullptr, tol_sq, threshold, rhs_sq, rr, alpha, beta,
                       status, iterations, max_iter);
    s.ap = ap.data_ptr<S>();
    s.free = k.epilogue.free;
    s.rr_swap = rr_swap.data_ptr<S>();
    s.work = work.data_ptr<int32_t>();
    s.sums = sums.data_ptr<double>();
    s.d = p.size(1);
    s.count = count;
    s.cache_neighbors = (flags & 1) != 0;
    L::run_cg(plan, k, s);
  });
}

// The step's end handed to hooke_node_solve_step (euler_update's tensors; dv is the solve's x).
struct StepEndTensors {
  at::Tensor x, v;
  c10::optional<at::Tensor> dv_imposed;
  double h;
  at::Tensor x_new, v_new, norms, summary, sums, counter;
  c10::optional<at::Tensor> ring, ring_pos;
  bool carry;
};

// The right-hand side that hooke_node_steps computes before each solve (StepRhs).
struct StepRhsTensors {
  at::Tensor rest, external;
  double w_coef, rayleigh_mass;
  const StepPlanes& planes;  // its node_stiffness is the solve's
  at::Tensor u;
  int64_t steps;
};

inline void check_no_overlap(const at::Tensor& written, const char* written_name, const at::Tensor& other,
                             const char* other_name) {
  TORCH_CHECK(at::get_overlap_status(written, other) == at::MemOverlapStatus::No, "tensormass: ", written_name,
              " shares memory with ", other_name, "; they must be separate tensors");
}

template <class L>
bool run_hooke_node_solve(const at::Tensor& neighbor, const at::Tensor& node_k, const at::Tensor& incidences,
                          const c10::optional<at::Tensor>& row_node, const at::Tensor& mass,
                          const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                          const c10::optional<at::Tensor>& node_stiffness, const at::Tensor& rhs, double tol_sq,
                          const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                          int64_t chunk_nodes, int64_t chunk_slots, int64_t max_iter, at::Tensor x, at::Tensor r,
                          at::Tensor p, at::Tensor threshold, at::Tensor rhs_sq, at::Tensor rr, at::Tensor status,
                          at::Tensor alpha, at::Tensor beta, at::Tensor iterations, at::Tensor exchange,
                          at::Tensor sums, at::Tensor counters, int64_t flags, int64_t cache_slots,
                          StepEndTensors* end, const StepRhsTensors* step_rhs = nullptr) {
  TORCH_CHECK(cache_slots >= -1, "tensormass: cache_slots must be >= -1, got ", std::to_string(cache_slots));
  check_values(rhs, "rhs");
  TORCH_CHECK(chunk_nodes >= 1, "tensormass: chunk_nodes must be >= 1, got ", std::to_string(chunk_nodes));
  TORCH_CHECK(chunk_slots >= 0, "tensormass: chunk_slots must be >= 0, got ", std::to_string(chunk_slots));
  const CGPlan plan = check_cg_iterates(rhs, chunk_start, chunk_object, object_chunk, x, r, threshold, rhs_sq, rr, alpha,
                                        beta, status, iterations, max_iter);
  cg_check(p, "p", rhs, rhs.scalar_type(), rhs.sizes());
  const int64_t dim = rhs.size(1);
  cg_check(exchange, "exchange", rhs, rhs.scalar_type(), {2, rhs.size(0), 4 * dim});
  cg_check(sums, "sums", rhs, at::kDouble, {4 * plan.num_chunks});
  cg_check(counters, "counters", rhs, at::kInt, {3});
  if (end != nullptr) {  // euler_update's checks, with the solve's x as dv and its plan
    cg_check(end->x, "state_x", rhs, rhs.scalar_type(), rhs.sizes());
    cg_check(end->v, "state_v", rhs, rhs.scalar_type(), rhs.sizes());
    cg_check(end->sums, "end_sums", rhs, at::kDouble, {plan.num_chunks});
    cg_check(end->counter, "end_counter", rhs, at::kInt, {plan.num_objects + 1});
    check_euler_update(end->x, end->v, x, end->dv_imposed, end->x_new, end->v_new, chunk_start, chunk_object,
                       object_chunk, status, iterations, rr, rhs_sq, end->norms, end->summary, end->sums, end->counter,
                       end->ring, end->ring_pos);
  }
  if (step_rhs != nullptr) {  // hooke_node_step_rhs's checks, at the state the step end carries
    TORCH_CHECK(end != nullptr, "tensormass: a solve that computes its right-hand side must end the step");
    TORCH_CHECK(step_rhs->steps >= 1, "tensormass: steps must be >= 1, got ", std::to_string(step_rhs->steps));
    TORCH_CHECK(step_rhs->steps == 1 || end->carry,
                "tensormass: steps > 1 needs carry (each step starts from the state the last one carried)");
    cg_check(step_rhs->rest, "rest", rhs, rhs.scalar_type(), rhs.sizes());
    cg_check(step_rhs->external, "external", rhs, rhs.scalar_type(), rhs.sizes());
    cg_check(step_rhs->u, "u", rhs, rhs.scalar_type(), rhs.sizes());
    const std::pair<const at::Tensor*, const char*> read[] = {{&end->x, "state_x"}, {&end->v, "state_v"},
                                                              {&step_rhs->rest, "rest"},
                                                              {&step_rhs->external, "external"}};
    for (const auto& named : read) {
      check_no_overlap(step_rhs->u, "u", *named.first, named.second);
      check_no_overlap(rhs, "rhs", *named.first, named.second);
    }
    check_no_overlap(rhs, "rhs", step_rhs->u, "u");
    if (step_rhs->planes.given) {
      for (const auto& named : read) {
        check_no_overlap(step_rhs->planes.node_stiffness, "node_stiffness", *named.first, named.second);
      }
    }
  }
  at::Tensor no_dots;
  bool ran = false;
  run_hooke_node_system<L>(rhs, neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff, node_stiffness,
                           r, no_dots, [&](const auto& k, int64_t) {
    using S = typename std::decay_t<decltype(k)>::Scalar;
    PipelinedSolve<S> s;
    set_cg_iterates<S>(s, x, r, p, rhs.data_ptr<S>(), tol_sq, threshold, rhs_sq, rr, alpha, beta, status, iterations,
                       max_iter);
    s.exchange = exchange.data_ptr<S>();
    s.sums = sums.data_ptr<double>();
    s.counters = counters.data_ptr<int32_t>();
    s.chunk_nodes = chunk_nodes;
    s.chunk_slots = chunk_slots;
    s.max_slots = neighbor.size(0);
    s.pair_rows = (flags & 2) != 0;
    s.cache_slots = cache_slots;
    if (end != nullptr) {
      s.end.update = euler_update_of<S>(end->x, end->v, x, end->dv_imposed, end->h, end->x_new, end->v_new, end->carry);
      s.end.summary = step_summary_of<S>(status, iterations, rr, rhs_sq, end->norms, end->summary, end->ring,
                                         end->ring_pos);
      s.end.sums = end->sums.data_ptr<double>();
      s.end.counter = end->counter.data_ptr<int32_t>();
    }
    if (step_rhs != nullptr) {
      s.step_rhs.rest = step_rhs->rest.data_ptr<S>();
      s.step_rhs.external = step_rhs->external.data_ptr<S>();
      s.step_rhs.h = static_cast<S>(end->h);
      s.step_rhs.c_w = static_cast<S>(step_rhs->w_coef);
      s.step_rhs.rayleigh_mass = static_cast<S>(step_rhs->rayleigh_mass);
      if (step_rhs->planes.given) {
        s.step_rhs.plane_normals = step_rhs->planes.normals.data_ptr<S>();
        s.step_rhs.plane_offsets = step_rhs->planes.offsets.data_ptr<S>();
        s.step_rhs.plane_stiffness = step_rhs->planes.stiffness.data_ptr<S>();
        s.step_rhs.planes = step_rhs->planes.normals.size(0);
        s.step_rhs.node_stiffness = step_rhs->planes.node_stiffness.data_ptr<S>();
      }
      s.step_rhs.u = step_rhs->u.data_ptr<S>();
      s.step_rhs.rhs = rhs.data_ptr<S>();
      s.steps = step_rhs->steps;
    }
    ran = L::run_solve(plan, k, s);
  });
  return ran;
}

// hooke_node_solve: a whole CG solve from x0 = 0 of hooke_node_system's system (A = c_M M - c_K K
// over the node graph, projected on `free`) by the pipelined CG (Chronopoulos-Gear: one
// reduction an iteration; on the GPU one persistent kernel with one grid barrier an iteration,
// cg_pipelined.cuh): the same iterates as CG in exact arithmetic, the same stopping rule
// and statuses (relative tolerance tol_sq = tol^2 on r.r, max_iter, breakdown, non-finite), not
// bitwise the two-reduction CG of hooke_node_cg. The plan's chunks must hold at most chunk_nodes
// nodes and chunk_slots slots (the sum of incidences over a chunk's nodes): a chunk beyond that
// ends its object as non-finite. chunk_nodes picks the layout: <= SOLVE_CHUNK_NODES (128) the
// chunks' slots may sit in shared memory, <= STREAM_CHUNK_NODES (256) they are read from the
// graph each iteration (chunk_slots unused). Returns whether it ran: false, having changed
// nothing, where the solve does not fit the device in one wave in either layout, or chunk_nodes
// exceeds both (or on the CPU, which has no such kernel); then the caller solves with
// hooke_node_cg. Buffers: the CG state
// (x, r, p [V, d]; threshold, rhs_sq, rr, alpha, beta [B]; status, iterations [B] int32) and
// the work: exchange [2, V, 4d], sums [4K] float64, counters [3] int32.
template <class L>
bool hooke_node_solve(const at::Tensor& neighbor, const at::Tensor& node_k, const at::Tensor& incidences,
                      const c10::optional<at::Tensor>& row_node, const at::Tensor& mass, const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                      const c10::optional<at::Tensor>& node_stiffness, const at::Tensor& rhs, double tol_sq,
                      const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                      int64_t chunk_nodes, int64_t chunk_slots, int64_t max_iter, at::Tensor x, at::Tensor r, at::Tensor p,
                      at::Tensor threshold, at::Tensor rhs_sq, at::Tensor rr, at::Tensor status, at::Tensor alpha,
                      at::Tensor beta, at::Tensor iterations, at::Tensor exchange, at::Tensor sums,
                      at::Tensor counters, int64_t flags, int64_t cache_slots) {
  return run_hooke_node_solve<L>(neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff, node_stiffness,
                                 rhs, tol_sq, chunk_start, chunk_object, object_chunk, chunk_nodes, chunk_slots,
                                 max_iter, x, r, p, threshold, rhs_sq, rr, status, alpha, beta, iterations, exchange,
                                 sums, counters, flags, cache_slots, nullptr);
}

// hooke_node_solve_step: hooke_node_solve, then the step's end as euler_update does it with the
// solution as dv (v_new = v + dv (+ dv_imposed), x_new = x + h v_new; with `carry` also into x,
// v; the object's |v_new|^2 into norms, the summary [5, B], ring row ring_pos, ring_pos
// advanced), in the same kernel: one launch a step fewer. end_sums [K] float64 over the plan's
// chunks and end_counter [B + 1] int32 (zero between calls) are its work. Returns whether it ran:
// false, having changed nothing, where hooke_node_solve would (then neither is done).
template <class L>
bool hooke_node_solve_step(const at::Tensor& neighbor, const at::Tensor& node_k, const at::Tensor& incidences,
                           const c10::optional<at::Tensor>& row_node, const at::Tensor& mass,
                           const c10::optional<at::Tensor>& free, double c_mass, double c_stiff,
                           const c10::optional<at::Tensor>& node_stiffness, const at::Tensor& rhs, double tol_sq,
                           const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                           const at::Tensor& object_chunk, int64_t chunk_nodes, int64_t chunk_slots, int64_t max_iter,
                           at::Tensor x, at::Tensor r, at::Tensor p, at::Tensor threshold, at::Tensor rhs_sq,
                           at::Tensor rr, at::Tensor status, at::Tensor alpha, at::Tensor beta, at::Tensor iterations,
                           at::Tensor exchange, at::Tensor sums, at::Tensor counters, at::Tensor state_x,
                           at::Tensor state_v, const c10::optional<at::Tensor>& dv_imposed, double h,
                           at::Tensor x_new, at::Tensor v_new, at::Tensor norms, at::Tensor summary,
                           at::Tensor end_sums, at::Tensor end_counter, const c10::optional<at::Tensor>& ring,
                           const c10::optional<at::Tensor>& ring_pos, bool carry, int64_t flags,
                           int64_t cache_slots) {
  StepEndTensors end{state_x, state_v, dv_imposed, h, x_new, v_new, norms, summary, end_sums, end_counter, ring,
                     ring_pos, carry};
  return run_hooke_node_solve<L>(neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff, node_stiffness,
                                 rhs, tol_sq, chunk_start, chunk_object, object_chunk, chunk_nodes, chunk_slots,
                                 max_iter, x, r, p, threshold, rhs_sq, rr, status, alpha, beta, iterations, exchange,
                                 sums, counters, flags, cache_slots, &end);
}

// hooke_node_steps: `steps` implicit Euler steps of the hooke tensor form (no imposed
// velocities) in one solve kernel on the GPU, each: the right-hand side as hooke_node_step_rhs
// computes it (into rhs, u = x - rest and, with planes, node_stiffness, at state_x, state_v), then
// hooke_node_solve_step's solve and end (with carry, the next step starts from the state it
// wrote). Bitwise `steps` times hooke_node_step_rhs then hooke_node_solve_step: the graph in
// shared memory, the launches and the gaps between them serve every step. Each step's summary
// goes to ring row ring_pos (advanced), the last also into summary; steps > 1 needs carry.
// Returns whether it ran: false, having changed nothing, where hooke_node_solve would.
template <class L>
bool hooke_node_steps(const at::Tensor& neighbor, const at::Tensor& node_k, const at::Tensor& incidences,
                      const c10::optional<at::Tensor>& row_node, const at::Tensor& mass,
                      const c10::optional<at::Tensor>& free, double c_mass, double c_stiff, const at::Tensor& rest,
                      const at::Tensor& external, double w_coef, double rayleigh_mass,
                      const c10::optional<at::Tensor>& plane_normals, const c10::optional<at::Tensor>& plane_offsets,
                      const c10::optional<at::Tensor>& plane_stiffness, at::Tensor u, at::Tensor rhs,
                      const c10::optional<at::Tensor>& node_stiffness, double tol_sq, const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                      const at::Tensor& object_chunk, int64_t chunk_nodes, int64_t chunk_slots, int64_t max_iter,
                      at::Tensor x, at::Tensor r, at::Tensor p, at::Tensor threshold, at::Tensor rhs_sq,
                      at::Tensor rr, at::Tensor status, at::Tensor alpha, at::Tensor beta, at::Tensor iterations,
                      at::Tensor exchange, at::Tensor sums, at::Tensor counters, at::Tensor state_x,
                      at::Tensor state_v, double h, at::Tensor x_new, at::Tensor v_new, at::Tensor norms,
                      at::Tensor summary, at::Tensor end_sums, at::Tensor end_counter,
                      const c10::optional<at::Tensor>& ring, const c10::optional<at::Tensor>& ring_pos, bool carry,
                      int64_t steps, int64_t flags, int64_t cache_slots) {
  StepEndTensors end{state_x, state_v, c10::nullopt, h, x_new, v_new, norms, summary, end_sums, end_counter, ring,
                     ring_pos, carry};
  check_values(rhs, "rhs");
  const StepPlanes planes(rhs, plane_normals, plane_offsets, plane_stiffness, node_stiffness);
  TORCH_CHECK(planes.given || !(node_stiffness.has_value() && node_stiffness->defined()),
              "tensormass: node_stiffness is the contact planes' stiffness: it needs plane_normals");
  const StepRhsTensors step_rhs{rest, external, w_coef, rayleigh_mass, planes, u, steps};
  return run_hooke_node_solve<L>(neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff, node_stiffness,
                                 rhs, tol_sq, chunk_start, chunk_object, object_chunk, chunk_nodes, chunk_slots,
                                 max_iter, x, r, p, threshold, rhs_sq, rr, status, alpha, beta, iterations, exchange,
                                 sums, counters, flags, cache_slots, &end, &step_rhs);
}

// Registers the implementations of the solve ops of one backend (launcher L) under its
// TORCH_LIBRARY_IMPL (cpu.cpp, cuda.cu); the schemas: schema.cpp.
template <class L>
void register_solve_ops(torch::Library& m) {
  m.impl("hooke_node_cg", &hooke_node_cg<L>);
  m.impl("hooke_node_solve", &hooke_node_solve<L>);
  m.impl("hooke_node_solve_step", &hooke_node_solve_step<L>);
  m.impl("hooke_node_steps", &hooke_node_steps<L>);
}

}  // namespace tensormass
