// The host-side checks of the CG ops (cg/) and of the whole solves (solve/), written once for both
// backends: the chunk plan, each op's tensors, and the structs of cg.h over those tensors.
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/Optional.h>

#include <cstdint>
#include <string>
#include <utility>

#include "common/cg.h"

namespace tensormass {

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
// The step length's per-object scalars and sums (cg_alpha, cg_alpha_dot), against ``like``'s
// device and dtype.
inline void check_alpha_scalars(const CGPlan& plan, const at::Tensor& like, const at::Tensor& rr,
                                const at::Tensor& status, const at::Tensor& alpha, const at::Tensor& scratch,
                                const at::Tensor& counter) {
  cg_check_scalars(rr, "rr", like, plan.num_objects);
  cg_check_scalars(alpha, "alpha", like, plan.num_objects);
  cg_check_state(status, "status", like, plan.num_objects);
  cg_check(scratch, "scratch", like, at::kDouble, {plan.num_chunks});
  cg_check_state(counter, "counter", like, plan.num_objects);
}

inline CGPlan check_cg_alpha(const at::Tensor& p_dot_ap, const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                             const at::Tensor& object_chunk, const at::Tensor& rr, const at::Tensor& status,
                             const at::Tensor& alpha, const at::Tensor& scratch, const at::Tensor& counter) {
  cg_check_values(p_dot_ap, "p_dot_ap");
  TORCH_CHECK(p_dot_ap.dim() == 1, "tensormass: p_dot_ap must be [V] (p . Ap per node)");
  CGPlan plan = cg_plan(chunk_start, chunk_object, object_chunk, p_dot_ap, p_dot_ap.size(0));
  check_alpha_scalars(plan, p_dot_ap, rr, status, alpha, scratch, counter);
  return plan;
}

// cg_alpha_dot: the direction p and the product ap [V] or [V, d], the free-node mask free [V, 1]
// (optional, p's dtype), then cg_alpha's scalars.
inline CGPlan check_cg_alpha_dot(const at::Tensor& p, const at::Tensor& ap, const c10::optional<at::Tensor>& free,
                                 const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                                 const at::Tensor& object_chunk, const at::Tensor& rr, const at::Tensor& status,
                                 const at::Tensor& alpha, const at::Tensor& scratch, const at::Tensor& counter) {
  cg_check_values(p, "p");
  CGPlan plan = cg_plan(chunk_start, chunk_object, object_chunk, p, p.size(0));
  cg_check(ap, "ap", p, p.scalar_type(), p.sizes());
  if (free.has_value() && free->defined()) cg_check(*free, "free", p, p.scalar_type(), {p.size(0), 1});
  check_alpha_scalars(plan, p, rr, status, alpha, scratch, counter);
  return plan;
}

inline CGPlan check_cg_update(const at::Tensor& x, const at::Tensor& r, const at::Tensor& p, const at::Tensor& ap,
                              const at::Tensor& alpha, const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                              const at::Tensor& object_chunk, const at::Tensor& threshold, int64_t max_iter,
                              const at::Tensor& rr, const at::Tensor& status, const at::Tensor& beta,
                              const at::Tensor& iterations, const at::Tensor& scratch, const at::Tensor& counter,
                              const c10::optional<at::Tensor>& inverse_blocks, const c10::optional<at::Tensor>& z) {
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
  const bool blocks = inverse_blocks.has_value() && inverse_blocks->defined();
  TORCH_CHECK(blocks == (z.has_value() && z->defined()),
              "tensormass: cg_update takes inverse_blocks and z together (the preconditioned update) or neither");
  if (blocks) {
    TORCH_CHECK(x.dim() == 2 && x.size(1) >= 1 && x.size(1) <= kMaxBlock, "tensormass: x must be [V, d] with d <= ",
                std::to_string(kMaxBlock), " for inverse_blocks, got ", cg_shape_str(x.sizes()));
    cg_check(*inverse_blocks, "inverse_blocks", x, x.scalar_type(), {x.size(0), x.size(1), x.size(1)});
    cg_check(*z, "z", x, x.scalar_type(), x.sizes());
    TORCH_CHECK(!z->is_same(r) && !z->is_same(x), "tensormass: z must be a buffer of its own, not r or x");
  }
  return plan;
}

// cg_direction's coarse term (all four tensors or none): node_inverse [V] or [V, 3, 3], arm [V, 3],
// node_body [V] int32 and coarse [6 B] (six values a body), p's dtype and device, p [V, 3].
inline bool check_coarse_term(const at::Tensor& p, const c10::optional<at::Tensor>& node_inverse,
                              const c10::optional<at::Tensor>& arm, const c10::optional<at::Tensor>& node_body,
                              const c10::optional<at::Tensor>& coarse) {
  auto given = [](const c10::optional<at::Tensor>& t) { return t.has_value() && t->defined(); };
  const int count = given(node_inverse) + given(arm) + given(node_body) + given(coarse);
  TORCH_CHECK(count == 0 || count == 4,
              "tensormass: cg_direction takes node_inverse, arm, node_body and coarse together (a coarse term) or "
              "none of them");
  if (count == 0) return false;
  const int64_t nodes = p.size(0);
  TORCH_CHECK(p.dim() == 2 && p.size(1) == 3, "tensormass: p must be [V, 3] for a coarse term, got ",
              cg_shape_str(p.sizes()));
  if (node_inverse->dim() == 1) {
    cg_check(*node_inverse, "node_inverse", p, p.scalar_type(), {nodes});
  } else {
    cg_check(*node_inverse, "node_inverse", p, p.scalar_type(), {nodes, 3, 3});
  }
  cg_check(*arm, "arm", p, p.scalar_type(), {nodes, 3});
  cg_check(*node_body, "node_body", p, at::kInt, {nodes});
  TORCH_CHECK(coarse->dim() == 1 && coarse->numel() % 6 == 0, "tensormass: coarse must be [6 B] (six values a body), "
              "got ", cg_shape_str(coarse->sizes()));
  cg_check(*coarse, "coarse", p, p.scalar_type(), coarse->sizes());
  return true;
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

// The per-object ops' first argument, rr [B] (float32 or float64): the object count B.
inline int64_t cg_objects_of(const at::Tensor& rr) {
  cg_check_values(rr, "rr");
  TORCH_CHECK(rr.dim() == 1, "tensormass: rr must be [B], got ", cg_shape_str(rr.sizes()));
  return rr.size(0);
}

// cg_start_status: rr [B] (float), rhs_sq, threshold, alpha, beta [B] of its dtype, status and
// iterations [B] int32; floor [B] (rr's dtype) and gate [B] int32 optional.
inline int64_t check_cg_start_status(const at::Tensor& rr, const at::Tensor& rhs_sq, int64_t max_iter,
                                     const at::Tensor& threshold, const at::Tensor& status,
                                     const at::Tensor& iterations, const at::Tensor& alpha, const at::Tensor& beta,
                                     const c10::optional<at::Tensor>& floor, const c10::optional<at::Tensor>& gate) {
  TORCH_CHECK(max_iter >= 0, "tensormass: max_iter must be >= 0, got ", std::to_string(max_iter));
  const int64_t objects = cg_objects_of(rr);
  cg_check_scalars(rhs_sq, "rhs_sq", rr, objects);
  cg_check_scalars(threshold, "threshold", rr, objects);
  cg_check_scalars(alpha, "alpha", rr, objects);
  cg_check_scalars(beta, "beta", rr, objects);
  cg_check_state(status, "status", rr, objects);
  cg_check_state(iterations, "iterations", rr, objects);
  if (floor.has_value() && floor->defined()) cg_check_scalars(*floor, "floor", rr, objects);
  if (gate.has_value() && gate->defined()) {
    cg_check_state(*gate, "gate", rr, objects);
    TORCH_CHECK(!gate->is_same(status), "tensormass: gate must be another solve's statuses, not status");
  }
  return objects;
}

// cg_round_end: rr, threshold [B] (float), round_status, round_iterations, status, iterations [B]
// int32.
inline int64_t check_cg_round_end(const at::Tensor& rr, const at::Tensor& threshold, const at::Tensor& round_status,
                                  const at::Tensor& round_iterations, const at::Tensor& status,
                                  const at::Tensor& iterations) {
  const int64_t objects = cg_objects_of(rr);
  cg_check_scalars(threshold, "threshold", rr, objects);
  cg_check_state(round_status, "round_status", rr, objects);
  cg_check_state(round_iterations, "round_iterations", rr, objects);
  cg_check_state(status, "status", rr, objects);
  cg_check_state(iterations, "iterations", rr, objects);
  TORCH_CHECK(!round_status.is_same(status) && !round_iterations.is_same(iterations),
              "tensormass: round_status and round_iterations must be the round's, not status and iterations");
  return objects;
}

// cg_coarse_beta: rr [B] (float), u and v [N, k] of its dtype, item_ptr [B + 1] int64, then the
// per-object status, rz and beta.
inline int64_t check_cg_coarse_beta(const at::Tensor& rr, const at::Tensor& u, const at::Tensor& v,
                                    const at::Tensor& item_ptr, const at::Tensor& status, const at::Tensor& rz,
                                    const at::Tensor& beta) {
  const int64_t objects = cg_objects_of(rr);
  TORCH_CHECK(u.defined() && u.dim() == 2, "tensormass: u must be [N, k]");
  cg_check(u, "u", rr, rr.scalar_type(), u.sizes());
  cg_check(v, "v", rr, rr.scalar_type(), u.sizes());
  cg_check(item_ptr, "item_ptr", rr, at::kLong, {objects + 1});
  cg_check_state(status, "status", rr, objects);
  cg_check_scalars(rz, "rz", rr, objects);
  cg_check_scalars(beta, "beta", rr, objects);
  TORCH_CHECK(!rz.is_same(beta) && !rz.is_same(rr), "tensormass: rz must be a buffer of its own, not rr or beta");
  return objects;
}

inline int64_t check_cg_pair_term(const at::Tensor& r, const at::Tensor& z, const at::Tensor& nodes,
                                  const at::Tensor& blocks, const at::Tensor& item_ptr, const at::Tensor& rr,
                                  const at::Tensor& status, const at::Tensor& rz, const at::Tensor& beta,
                                  const at::Tensor& dots) {
  cg_check_values(r, "r");
  TORCH_CHECK(r.dim() == 2 && r.size(1) == 3, "tensormass: r must be [V, 3], got ", cg_shape_str(r.sizes()));
  cg_check(z, "z", r, r.scalar_type(), r.sizes());
  TORCH_CHECK(nodes.defined() && nodes.dim() == 2 && nodes.size(1) == 2, "tensormass: nodes must be [K, 2]");
  const int64_t pairs = nodes.size(0);
  cg_check(nodes, "nodes", r, at::kLong, {pairs, 2});
  cg_check(blocks, "blocks", r, r.scalar_type(), {pairs, 3, 3});
  cg_check(dots, "dots", r, at::kDouble, {pairs});
  TORCH_CHECK(rr.defined() && rr.dim() == 1, "tensormass: rr must be [B]");
  const int64_t objects = rr.size(0);
  cg_check_scalars(rr, "rr", r, objects);
  cg_check(item_ptr, "item_ptr", r, at::kLong, {objects + 1});
  cg_check_state(status, "status", r, objects);
  cg_check_scalars(rz, "rz", r, objects);
  cg_check_scalars(beta, "beta", r, objects);
  TORCH_CHECK(!rz.is_same(beta) && !rz.is_same(rr), "tensormass: rz must be a buffer of its own, not rr or beta");
  TORCH_CHECK(!z.is_same(r), "tensormass: z must be a buffer of its own, not r");
  return objects;
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

// cg_dot_beta: cg_dot's operands, the statuses and the preconditioned scalars r.z and beta.
inline CGPlan check_cg_dot_beta(const at::Tensor& r, const at::Tensor& z, const at::Tensor& chunk_start,
                                const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                                const at::Tensor& status, const at::Tensor& rz, const at::Tensor& beta,
                                const at::Tensor& scratch, const at::Tensor& counter) {
  const CGPlan plan = check_cg_dot(r, z, chunk_start, chunk_object, object_chunk, rz, scratch, counter);
  cg_check_state(status, "status", r, plan.num_objects);
  cg_check_scalars(beta, "beta", r, plan.num_objects);
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

// cg_alpha_dot's node kernel over its (checked) tensors.
template <typename S>
ProjectedDots<S> projected_dots(const at::Tensor& p, at::Tensor& ap, const c10::optional<at::Tensor>& free) {
  const bool masked = free.has_value() && free->defined();
  return ProjectedDots<S>{p.data_ptr<S>(), ap.data_ptr<S>(), masked ? free->data_ptr<S>() : nullptr,
                          values_per_node(p)};
}

// cg_update's preconditioned node update over its (checked) tensors; inverse null where the
// update is the plain one.
template <typename S>
BlockUpdate<S> block_update_of(at::Tensor& x, at::Tensor& r, const at::Tensor& p, const at::Tensor& ap,
                               const c10::optional<at::Tensor>& inverse_blocks, const c10::optional<at::Tensor>& z) {
  const bool blocks = inverse_blocks.has_value() && inverse_blocks->defined();
  return BlockUpdate<S>{x.data_ptr<S>(), r.data_ptr<S>(), p.data_ptr<S>(), ap.data_ptr<S>(),
                        blocks ? inverse_blocks->data_ptr<S>() : nullptr, blocks ? z->data_ptr<S>() : nullptr,
                        values_per_node(x)};
}

// cg_direction's coarse term over its tensors (checked by check_coarse_term).
template <typename S>
RigidMotion<S> rigid_motion_of(const c10::optional<at::Tensor>& node_inverse, const c10::optional<at::Tensor>& arm,
                               const c10::optional<at::Tensor>& node_body, const c10::optional<at::Tensor>& coarse,
                               double weight) {
  return RigidMotion<S>{node_inverse->data_ptr<S>(), node_inverse->dim() == 1, arm->data_ptr<S>(),
                        node_body->data_ptr<int32_t>(), coarse->data_ptr<S>(), static_cast<S>(weight)};
}

// The ops' structs over their tensors (checked by check_euler_update).
template <typename S>
inline EulerUpdate<S> euler_update_of(const at::Tensor& x, const at::Tensor& v, const at::Tensor& dv,
                                      const c10::optional<at::Tensor>& dv_imposed, double h, const at::Tensor& x_new,
                                      const at::Tensor& v_new, bool carry, double h_old) {
  const bool imposed = dv_imposed.has_value() && dv_imposed->defined();
  return EulerUpdate<S>{x.data_ptr<S>(), v.data_ptr<S>(), dv.data_ptr<S>(), imposed ? dv_imposed->data_ptr<S>() : nullptr,
                        static_cast<S>(h), x_new.data_ptr<S>(), v_new.data_ptr<S>(), carry, values_per_node(x),
                        static_cast<S>(h_old)};
}

template <typename S>
inline StepSummary<S> step_summary_of(const at::Tensor& status, const at::Tensor& iterations, const at::Tensor& rr,
                                      const at::Tensor& rhs_sq, const at::Tensor& norms, const at::Tensor& summary,
                                      const c10::optional<at::Tensor>& ring,
                                      const c10::optional<at::Tensor>& ring_pos) {
  const bool has_ring = ring.has_value() && ring->defined();
  return StepSummary<S>{status.data_ptr<int32_t>(), iterations.data_ptr<int32_t>(), rr.data_ptr<S>(),
                        rhs_sq.data_ptr<S>(), norms.data_ptr<S>(), summary.data_ptr<double>(),
                        has_ring ? ring->data_ptr<double>() : nullptr, has_ring ? ring_pos->data_ptr<int64_t>() : nullptr,
                        has_ring ? ring->size(0) : 0};
}

}  // namespace tensormass
