// Host side of the solve ops (schemas: schema.cpp): whole CG solves over the node graph in one op
// (hooke_node_cg; hooke_node_solve by the pipelined CG, hooke_node_solve_step ending the implicit
// Euler step, hooke_node_steps beginning each step too). Input checks and the solve's structs
// (common/cg.h) over the op's tensors; the matvec is the node graph's (common/node_graph.h). The
// launcher `L` (solve/cpu.cpp, solve/cuda.cu: the common launchers with run_cg and run_solve, the
// whole solve on its backend) instantiates these functions through register_solve_ops.
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/MemoryOverlap.h>
#include <ATen/core/List.h>
#include <c10/util/Optional.h>
#include <torch/library.h>

#include <array>
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

// The packed arguments of the solve ops (schema.cpp names their members), unpacked once here:
// the kernels see the same structs as before the packing.
using OptionalTensorList = c10::List<c10::optional<at::Tensor>>;

// `list` [N] of the tensors `names` (every one defined), or a clear error naming the argument.
template <size_t N>
std::array<at::Tensor, N> unpack_tensors(at::TensorList list, const char* what, const char* const (&names)[N]) {
  std::string expected;
  for (size_t i = 0; i < N; ++i) expected += std::string(i ? ", " : "") + names[i];
  TORCH_CHECK(list.size() == N, "tensormass: ", what, " must be the ", std::to_string(N), " tensors [", expected,
              "], got ", std::to_string(list.size()));
  std::array<at::Tensor, N> out;
  for (size_t i = 0; i < N; ++i) {
    TORCH_CHECK(list[i].defined(), "tensormass: ", what, "[", std::to_string(i), "] (", names[i], ") is undefined");
    out[i] = list[i];
  }
  return out;
}

// `list` [N] of the optional tensors `names`; those marked `required` must be given.
template <size_t N>
std::array<c10::optional<at::Tensor>, N> unpack_optional_tensors(const OptionalTensorList& list, const char* what,
                                                                 const char* const (&names)[N],
                                                                 const bool (&required)[N]) {
  std::string expected;
  for (size_t i = 0; i < N; ++i) expected += std::string(i ? ", " : "") + names[i] + (required[i] ? "" : "?");
  TORCH_CHECK(list.size() == N, "tensormass: ", what, " must be the ", std::to_string(N), " tensors [", expected,
              "], got ", std::to_string(list.size()));
  std::array<c10::optional<at::Tensor>, N> out;
  for (size_t i = 0; i < N; ++i) {
    c10::optional<at::Tensor> value = list.get(i);
    if (value.has_value() && !value->defined()) value = c10::nullopt;
    TORCH_CHECK(!required[i] || value.has_value(), "tensormass: ", what, "[", std::to_string(i), "] (", names[i],
                ") is None");
    out[i] = value;
  }
  return out;
}

// system = [neighbor, node_k, incidences, row_node?, mass, free?]: hooke_node_system's graph and
// epilogue (node_graph/schema.cpp).
struct SystemTensors {
  at::Tensor neighbor, node_k, incidences;
  c10::optional<at::Tensor> row_node;
  at::Tensor mass;
  c10::optional<at::Tensor> free;

  explicit SystemTensors(const OptionalTensorList& system) {
    static const char* const names[] = {"neighbor", "node_k", "incidences", "row_node", "mass", "free"};
    static const bool required[] = {true, true, true, false, true, false};
    auto t = unpack_optional_tensors(system, "system", names, required);
    neighbor = *t[0], node_k = *t[1], incidences = *t[2], row_node = t[3], mass = *t[4], free = t[5];
  }
};

// plan = [chunk_start [K + 1], chunk_object [K], object_chunk [B + 1]]: the chunk plan.
struct PlanTensors {
  at::Tensor chunk_start, chunk_object, object_chunk;

  explicit PlanTensors(at::TensorList plan) {
    static const char* const names[] = {"chunk_start", "chunk_object", "object_chunk"};
    auto t = unpack_tensors(plan, "plan", names);
    chunk_start = t[0], chunk_object = t[1], object_chunk = t[2];
  }
};

// cg = [x, r, p [V, d], threshold, rhs_sq, rr, alpha, beta [B], status, iterations [B] int32]:
// the CG state (Python: ops.cg.CGState), written.
struct CGTensors {
  at::Tensor x, r, p, threshold, rhs_sq, rr, alpha, beta, status, iterations;

  explicit CGTensors(at::TensorList cg) {
    static const char* const names[] = {"x",  "r",     "p",    "threshold", "rhs_sq",
                                        "rr", "alpha", "beta", "status",    "iterations"};
    auto t = unpack_tensors(cg, "cg", names);
    x = t[0], r = t[1], p = t[2], threshold = t[3], rhs_sq = t[4], rr = t[5], alpha = t[6], beta = t[7];
    status = t[8], iterations = t[9];
  }
};

// The checks every whole-solve op makes of its iterates [V, d] (like `like`), per-object scalars
// [B] and cap; returns the chunk plan.
inline CGPlan check_cg_iterates(const at::Tensor& like, const PlanTensors& plan_tensors, const CGTensors& cg,
                                int64_t max_iter) {
  TORCH_CHECK(max_iter >= 0, "tensormass: max_iter must be >= 0, got ", std::to_string(max_iter));
  const CGPlan plan =
      cg_plan(plan_tensors.chunk_start, plan_tensors.chunk_object, plan_tensors.object_chunk, like, like.size(0));
  TORCH_CHECK(plan.num_chunks == 0 || like.size(0) > 0, "tensormass: a chunk plan over no nodes");
  cg_check(cg.x, "x", like, like.scalar_type(), like.sizes());
  cg_check(cg.r, "r", like, like.scalar_type(), like.sizes());
  cg_check(cg.p, "p", like, like.scalar_type(), like.sizes());
  for (const auto& named : {std::make_pair(&cg.threshold, "threshold"), std::make_pair(&cg.rhs_sq, "rhs_sq"),
                            std::make_pair(&cg.rr, "rr"), std::make_pair(&cg.alpha, "alpha"),
                            std::make_pair(&cg.beta, "beta")}) {
    cg_check_scalars(*named.first, named.second, like, plan.num_objects);
  }
  cg_check_state(cg.status, "status", like, plan.num_objects);
  cg_check_state(cg.iterations, "iterations", like, plan.num_objects);
  return plan;
}

// The iterates and per-object scalars of a whole-solve op, from its tensors (checked by the op).
template <typename S>
void set_cg_iterates(CGIterates<S>& s, const CGTensors& cg, const S* rhs, double tol_sq, int64_t max_iter) {
  s.x = cg.x.data_ptr<S>();
  s.r = cg.r.data_ptr<S>();
  s.p = cg.p.data_ptr<S>();
  s.rhs = rhs;
  s.tol_sq = static_cast<S>(tol_sq);
  s.threshold = cg.threshold.data_ptr<S>();
  s.rhs_sq = cg.rhs_sq.data_ptr<S>();
  s.rr = cg.rr.data_ptr<S>();
  s.alpha = cg.alpha.data_ptr<S>();
  s.beta = cg.beta.data_ptr<S>();
  s.status = cg.status.data_ptr<int32_t>();
  s.iterations = cg.iterations.data_ptr<int32_t>();
  s.max_iter = max_iter;
}

// hooke_node_cg: up to `count` CG iterations whose matvec is hooke_node_system's (A = c_M M -
// c_K K over the node graph, projected on `free`), preceded, when `rhs` is given, by the start
// from x0 = 0 (x = 0, r = p = free * rhs, rhs_sq = b.b, threshold = tol_sq b.b, statuses); it
// stops early once no object is active. On the GPU one persistent kernel (no launch and no host
// round trip per iteration); on the CPU the CG ops' functions in a loop. Either way the result is
// bitwise the op-by-op solve (hooke_node_system_alpha, cg_update, cg_direction) over the same
// chunk plan. cg's p is the product's input. buffers = [ap [V, d], rr_swap [B], work [3B + 2]
// int32, sums [2K] float64]: the product and the persistent kernel's work.
template <class L>
void hooke_node_cg(const OptionalTensorList& system_list, double c_mass, double c_stiff,
                   const c10::optional<at::Tensor>& node_stiffness, const c10::optional<at::Tensor>& rhs,
                   double tol_sq, at::TensorList plan_list, int64_t max_iter, int64_t count, at::TensorList cg_list,
                   at::TensorList buffers, int64_t flags) {
  const SystemTensors sys(system_list);
  const PlanTensors plan_tensors(plan_list);
  const CGTensors cg(cg_list);
  static const char* const buffer_names[] = {"ap", "rr_swap", "work", "sums"};
  const std::array<at::Tensor, 4> unpacked = unpack_tensors(buffers, "buffers", buffer_names);
  at::Tensor ap = unpacked[0];  // the product's output (run_hooke_node_system writes it)
  const at::Tensor &rr_swap = unpacked[1], &work = unpacked[2], &sums = unpacked[3];
  const at::Tensor& p = cg.p;
  check_values(p, "p");
  TORCH_CHECK(count >= 0, "tensormass: count must be >= 0, got ", std::to_string(count));
  const CGPlan plan = check_cg_iterates(p, plan_tensors, cg, max_iter);
  const bool start = rhs.has_value() && rhs->defined();
  if (start) cg_check(*rhs, "rhs", p, p.scalar_type(), p.sizes());
  cg_check(ap, "ap", p, p.scalar_type(), p.sizes());
  cg_check_scalars(rr_swap, "rr_swap", p, plan.num_objects);
  cg_check(work, "work", p, at::kInt, {3 * plan.num_objects + 2});
  cg_check(sums, "sums", p, at::kDouble, {2 * plan.num_chunks});
  at::Tensor no_dots;
  run_hooke_node_system<L>(p, sys.neighbor, sys.node_k, sys.incidences, sys.row_node, sys.mass, sys.free, c_mass,
                           c_stiff, node_stiffness, ap, no_dots, [&](const auto& k, int64_t) {
    using S = typename std::decay_t<decltype(k)>::Scalar;
    CGRun<S> s;
    set_cg_iterates<S>(s, cg, start ? rhs->data_ptr<S>() : nullptr, tol_sq, max_iter);
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

// The pipelined solve's buffers = [exchange [2, V, 4d], sums [4K] float64, counters [3] int32].
struct SolveBuffers {
  at::Tensor exchange, sums, counters;

  explicit SolveBuffers(at::TensorList buffers) {
    static const char* const names[] = {"exchange", "sums", "counters"};
    auto t = unpack_tensors(buffers, "buffers", names);
    exchange = t[0], sums = t[1], counters = t[2];
  }
};

// The step's end handed to hooke_node_solve_step (euler_update's tensors; dv is the solve's x):
// step = [state_x, state_v, x_new, v_new [V, d], norms [B], summary [5, B] float64, end_sums [K]
// float64, end_counter [B + 1] int32].
struct StepEndTensors {
  at::Tensor x, v;
  c10::optional<at::Tensor> dv_imposed;
  double h;
  at::Tensor x_new, v_new, norms, summary, sums, counter;
  c10::optional<at::Tensor> ring, ring_pos;
  bool carry;
  double h_old;  // EulerUpdate's: the old velocity's share of the step's motion (0: backward Euler)

  StepEndTensors(at::TensorList step, const c10::optional<at::Tensor>& dv_imposed_, double h_,
                 const c10::optional<at::Tensor>& ring_, const c10::optional<at::Tensor>& ring_pos_, bool carry_,
                 double h_old_)
      : dv_imposed(dv_imposed_), h(h_), ring(ring_), ring_pos(ring_pos_), carry(carry_), h_old(h_old_) {
    static const char* const names[] = {"state_x", "state_v", "x_new", "v_new",
                                        "norms",   "summary", "end_sums", "end_counter"};
    auto t = unpack_tensors(step, "step", names);
    x = t[0], v = t[1], x_new = t[2], v_new = t[3], norms = t[4], summary = t[5], sums = t[6], counter = t[7];
  }
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

// What every pipelined solve op takes: the system, its right-hand side and the chunk plan's promise.
struct SolveInputs {
  const SystemTensors& sys;
  double c_mass, c_stiff;
  const c10::optional<at::Tensor>& node_stiffness;
  const at::Tensor& rhs;
  double tol_sq;
  const PlanTensors& plan;
  int64_t chunk_nodes, chunk_slots, max_iter;
};

// The pipelined solve (ops below): checks every input, then launches the one kernel, which raises
// NotImplementedError, having changed nothing, where the solve does not fit the device in one
// wave in either layout (or on the CPU, which has no such kernel).
template <class L>
void run_hooke_node_solve(const SolveInputs& in, const CGTensors& cg, const SolveBuffers& buffers, int64_t flags,
                          int64_t cache_slots, const StepEndTensors* end, const StepRhsTensors* step_rhs = nullptr,
                          bool from_iterate = false) {
  const at::Tensor& rhs = in.rhs;
  TORCH_CHECK(!from_iterate || (end == nullptr && step_rhs == nullptr),
              "tensormass: a solve from the iterate (from_iterate) neither begins nor ends a step");
  TORCH_CHECK(cache_slots >= -1, "tensormass: cache_slots must be >= -1, got ", std::to_string(cache_slots));
  check_values(rhs, "rhs");
  TORCH_CHECK(in.chunk_nodes >= 1, "tensormass: chunk_nodes must be >= 1, got ", std::to_string(in.chunk_nodes));
  TORCH_CHECK(in.chunk_slots >= 0, "tensormass: chunk_slots must be >= 0, got ", std::to_string(in.chunk_slots));
  const CGPlan plan = check_cg_iterates(rhs, in.plan, cg, in.max_iter);
  const int64_t dim = rhs.size(1);
  cg_check(buffers.exchange, "exchange", rhs, rhs.scalar_type(), {2, rhs.size(0), 4 * dim});
  cg_check(buffers.sums, "sums", rhs, at::kDouble, {4 * plan.num_chunks});
  cg_check(buffers.counters, "counters", rhs, at::kInt, {3});
  if (end != nullptr) {  // euler_update's checks, with the solve's x as dv and its plan
    cg_check(end->x, "state_x", rhs, rhs.scalar_type(), rhs.sizes());
    cg_check(end->v, "state_v", rhs, rhs.scalar_type(), rhs.sizes());
    cg_check(end->sums, "end_sums", rhs, at::kDouble, {plan.num_chunks});
    cg_check(end->counter, "end_counter", rhs, at::kInt, {plan.num_objects + 1});
    check_euler_update(end->x, end->v, cg.x, end->dv_imposed, end->x_new, end->v_new, in.plan.chunk_start,
                       in.plan.chunk_object, in.plan.object_chunk, cg.status, cg.iterations, cg.rr, cg.rhs_sq,
                       end->norms, end->summary, end->sums, end->counter, end->ring, end->ring_pos);
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
  at::Tensor no_dots, product = cg.r;  // the product's buffer (checked; the solve's kernel writes r)
  bool ran = false;
  const SystemTensors& sys = in.sys;
  run_hooke_node_system<L>(rhs, sys.neighbor, sys.node_k, sys.incidences, sys.row_node, sys.mass, sys.free,
                           in.c_mass, in.c_stiff, in.node_stiffness, product, no_dots, [&](const auto& k, int64_t) {
    using S = typename std::decay_t<decltype(k)>::Scalar;
    PipelinedSolve<S> s;
    set_cg_iterates<S>(s, cg, rhs.data_ptr<S>(), in.tol_sq, in.max_iter);
    s.exchange = buffers.exchange.data_ptr<S>();
    s.sums = buffers.sums.data_ptr<double>();
    s.counters = buffers.counters.data_ptr<int32_t>();
    s.chunk_nodes = in.chunk_nodes;
    s.chunk_slots = in.chunk_slots;
    s.max_slots = sys.neighbor.size(0);
    s.pair_rows = (flags & 2) != 0;
    s.from_iterate = from_iterate;
    s.cache_slots = cache_slots;
    if (end != nullptr) {
      s.end.update = euler_update_of<S>(end->x, end->v, cg.x, end->dv_imposed, end->h, end->x_new, end->v_new,
                                        end->carry, end->h_old);
      s.end.summary = step_summary_of<S>(cg.status, cg.iterations, cg.rr, cg.rhs_sq, end->norms, end->summary,
                                         end->ring, end->ring_pos);
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
  TORCH_CHECK_NOT_IMPLEMENTED(ran, "tensormass: the pipelined solve does not fit one wave of this ",
                              rhs.is_cuda() ? "GPU" : "device (the CPU has no pipelined kernel)", " (",
                              std::to_string(plan.num_chunks), " chunks of at most ", std::to_string(in.chunk_nodes),
                              " nodes and ", std::to_string(in.chunk_slots),
                              " slots); nothing was changed: solve with hooke_node_cg");
}

// hooke_node_solve: a whole CG solve from x0 = 0 of hooke_node_system's system (A = c_M M - c_K K
// over the node graph, projected on `free`), or with from_iterate from the iterate a start left in
// cg (x = x0, r = rhs = b - A x0 projected, threshold = tol^2 b.b; rhs_sq and threshold kept,
// tol_sq unused: CG from x0 is CG on A d = r0 from 0, plus x0: a warm start), by the pipelined CG
// (Chronopoulos-Gear: one reduction an iteration; on the GPU one persistent kernel with one grid
// barrier an iteration, cg_pipelined.cuh): the same iterates as CG in exact arithmetic, the same
// stopping rule and statuses (relative tolerance tol_sq = tol^2 on r.r, max_iter, breakdown,
// non-finite), not bitwise the two-reduction CG of hooke_node_cg. The plan's chunks must hold at
// most chunk_nodes nodes and chunk_slots slots (the sum of incidences over a chunk's nodes): a
// chunk beyond that ends its object as non-finite. chunk_nodes picks the layout: <=
// SOLVE_CHUNK_NODES (128) the chunks' slots may sit in shared memory, <= STREAM_CHUNK_NODES (256)
// they are read from the graph each iteration (chunk_slots unused). Raises NotImplementedError,
// having changed nothing, where the solve does not fit the device in one wave in either layout, or
// chunk_nodes exceeds both, or on the CPU (no such kernel): the caller then solves with
// hooke_node_cg.
template <class L>
void hooke_node_solve(const OptionalTensorList& system, double c_mass, double c_stiff,
                      const c10::optional<at::Tensor>& node_stiffness, const at::Tensor& rhs, double tol_sq,
                      at::TensorList plan, int64_t chunk_nodes, int64_t chunk_slots, int64_t max_iter,
                      at::TensorList cg, at::TensorList buffers, int64_t flags, int64_t cache_slots,
                      bool from_iterate) {
  const SystemTensors sys(system);
  const PlanTensors plan_tensors(plan);
  const SolveInputs in{sys, c_mass, c_stiff, node_stiffness, rhs, tol_sq, plan_tensors, chunk_nodes, chunk_slots,
                       max_iter};
  run_hooke_node_solve<L>(in, CGTensors(cg), SolveBuffers(buffers), flags, cache_slots, nullptr, nullptr,
                          from_iterate);
}

// hooke_node_solve_step: hooke_node_solve, then the step's end as euler_update does it with the
// solution as dv (v_new = v + dv (+ dv_imposed), x_new = x + h v_new; with `carry` also into x,
// v; the object's |v_new|^2 into norms, the summary [5, B], ring row ring_pos, ring_pos
// advanced), in the same kernel: one launch a step fewer. step's end_sums [K] float64 over the
// plan's chunks and end_counter [B + 1] int32 (zero between calls) are its work. Raises where
// hooke_node_solve does (then neither is done).
template <class L>
void hooke_node_solve_step(const OptionalTensorList& system, double c_mass, double c_stiff,
                           const c10::optional<at::Tensor>& node_stiffness, const at::Tensor& rhs, double tol_sq,
                           at::TensorList plan, int64_t chunk_nodes, int64_t chunk_slots, int64_t max_iter,
                           at::TensorList cg, at::TensorList buffers, at::TensorList step,
                           const c10::optional<at::Tensor>& dv_imposed, double h, const c10::optional<at::Tensor>& ring,
                           const c10::optional<at::Tensor>& ring_pos, bool carry, int64_t flags, int64_t cache_slots,
                           double h_old) {
  const SystemTensors sys(system);
  const PlanTensors plan_tensors(plan);
  const SolveInputs in{sys, c_mass, c_stiff, node_stiffness, rhs, tol_sq, plan_tensors, chunk_nodes, chunk_slots,
                       max_iter};
  const StepEndTensors end(step, dv_imposed, h, ring, ring_pos, carry, h_old);
  run_hooke_node_solve<L>(in, CGTensors(cg), SolveBuffers(buffers), flags, cache_slots, &end);
}

// hooke_node_steps: `steps` implicit Euler steps of the hooke tensor form (no imposed
// velocities) in one solve kernel on the GPU, each: the right-hand side as hooke_node_step_rhs
// computes it (into rhs, u = x - rest and, with planes, node_stiffness, at state_x, state_v), then
// hooke_node_solve_step's solve and end (with carry, the next step starts from the state it
// wrote). Bitwise `steps` times hooke_node_step_rhs then hooke_node_solve_step: the graph in
// shared memory, the launches and the gaps between them serve every step. Each step's summary
// goes to ring row ring_pos (advanced), the last also into summary; steps > 1 needs carry.
// loads = [rest, external [V, d], plane_normals? [P, 3], plane_offsets? [P], plane_stiffness? [P]],
// rhs_out = [u, rhs [V, d]] (written), step_coefs = [h, w_coef, rayleigh_mass] or [h, w_coef,
// rayleigh_mass, h_old] (EulerUpdate's h_old; 0 where absent). Raises where hooke_node_solve does,
// having changed nothing.
template <class L>
void hooke_node_steps(const OptionalTensorList& system, double c_mass, double c_stiff,
                      const c10::optional<at::Tensor>& node_stiffness, const OptionalTensorList& loads,
                      at::TensorList rhs_out, double tol_sq, at::TensorList plan, int64_t chunk_nodes,
                      int64_t chunk_slots, int64_t max_iter, at::TensorList cg, at::TensorList buffers,
                      at::TensorList step, at::ArrayRef<double> step_coefs, const c10::optional<at::Tensor>& ring,
                      const c10::optional<at::Tensor>& ring_pos, bool carry, int64_t steps, int64_t flags,
                      int64_t cache_slots) {
  static const char* const load_names[] = {"rest", "external", "plane_normals", "plane_offsets", "plane_stiffness"};
  static const bool load_required[] = {true, true, false, false, false};
  const std::array<c10::optional<at::Tensor>, 5> load = unpack_optional_tensors(loads, "loads", load_names,
                                                                                load_required);
  const c10::optional<at::Tensor> &plane_normals = load[2], &plane_offsets = load[3], &plane_stiffness = load[4];
  static const char* const out_names[] = {"u", "rhs"};
  const std::array<at::Tensor, 2> outs = unpack_tensors(rhs_out, "rhs_out", out_names);
  const at::Tensor &u = outs[0], &rhs = outs[1];
  TORCH_CHECK(step_coefs.size() == 3 || step_coefs.size() == 4,
              "tensormass: step_coefs must be [h, w_coef, rayleigh_mass] or [h, w_coef, rayleigh_mass, h_old], got ",
              std::to_string(step_coefs.size()), " values");
  const double h = step_coefs[0], w_coef = step_coefs[1], rayleigh_mass = step_coefs[2];
  const double h_old = step_coefs.size() == 4 ? step_coefs[3] : 0.0;
  const SystemTensors sys(system);
  const PlanTensors plan_tensors(plan);
  const StepEndTensors end(step, c10::nullopt, h, ring, ring_pos, carry, h_old);
  check_values(rhs, "rhs");
  const StepPlanes planes(rhs, plane_normals, plane_offsets, plane_stiffness, node_stiffness);
  TORCH_CHECK(planes.given || !(node_stiffness.has_value() && node_stiffness->defined()),
              "tensormass: node_stiffness is the contact planes' stiffness: it needs plane_normals");
  const StepRhsTensors step_rhs{*load[0], *load[1], w_coef, rayleigh_mass, planes, u, steps};
  const SolveInputs in{sys, c_mass, c_stiff, node_stiffness, rhs, tol_sq, plan_tensors, chunk_nodes, chunk_slots,
                       max_iter};
  run_hooke_node_solve<L>(in, CGTensors(cg), SolveBuffers(buffers), flags, cache_slots, &end, &step_rhs);
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
