// CPU implementations of the CG ops (common/cg.h, common/cg_checks.h; the chunked reductions:
// common/cg_chunks.h).
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <torch/library.h>

#include "common/cg.h"
#include "common/cg_checks.h"
#include "common/cg_chunks.h"

namespace tensormass {
namespace {

void cg_alpha_cpu(const at::Tensor& p_dot_ap, const at::Tensor& chunk_start, const at::Tensor& chunk_object,
                  const at::Tensor& object_chunk, const at::Tensor& rr, at::Tensor status, at::Tensor alpha,
                  at::Tensor scratch, at::Tensor counter) {
  const CGPlan plan = check_cg_alpha(p_dot_ap, chunk_start, chunk_object, object_chunk, rr, status, alpha, scratch,
                                     counter);
  AT_DISPATCH_FLOATING_TYPES(p_dot_ap.scalar_type(), "cg_alpha", [&] {
    const scalar_t* values = p_dot_ap.data_ptr<scalar_t>();
    double* sums = scratch.data_ptr<double>();
    int32_t* st = status.data_ptr<int32_t>();
    for_each_chunk(plan, 1, st, [&](int64_t c, int64_t begin, int64_t end) {
      double acc = 0.0;
      for (int64_t i = begin; i < end; ++i) acc += static_cast<double>(values[i]);
      sums[c] = acc;
    });
    alpha_from_chunk_sums(plan, sums, rr.data_ptr<scalar_t>(), st, alpha.data_ptr<scalar_t>());
  });
}

void cg_alpha_dot_cpu(const at::Tensor& p, at::Tensor ap, const c10::optional<at::Tensor>& free,
                      const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                      const at::Tensor& rr, at::Tensor status, at::Tensor alpha, at::Tensor scratch,
                      at::Tensor counter) {
  const CGPlan plan = check_cg_alpha_dot(p, ap, free, chunk_start, chunk_object, object_chunk, rr, status, alpha,
                                         scratch, counter);
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "cg_alpha_dot", [&] {
    const ProjectedDots<scalar_t> dots = projected_dots<scalar_t>(p, ap, free);
    chunk_alpha_cpu(plan, dots, rr.data_ptr<scalar_t>(), status.data_ptr<int32_t>(), alpha.data_ptr<scalar_t>(),
                    scratch.data_ptr<double>());
  });
}

void cg_update_cpu(at::Tensor x, at::Tensor r, const at::Tensor& p, const at::Tensor& ap, const at::Tensor& alpha,
                   const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                   const at::Tensor& threshold, int64_t max_iter, at::Tensor rr, at::Tensor status, at::Tensor beta,
                   at::Tensor iterations, at::Tensor scratch, at::Tensor counter,
                   const c10::optional<at::Tensor>& inverse_blocks, const c10::optional<at::Tensor>& z) {
  const CGPlan plan = check_cg_update(x, r, p, ap, alpha, chunk_start, chunk_object, object_chunk, threshold, max_iter,
                                      rr, status, beta, iterations, scratch, counter, inverse_blocks, z);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "cg_update", [&] {
    const BlockUpdate<scalar_t> blocks = block_update_of<scalar_t>(x, r, p, ap, inverse_blocks, z);
    if (blocks.inverse != nullptr) {
      block_update_cpu<scalar_t>(plan, blocks, alpha.data_ptr<scalar_t>(), threshold.data_ptr<scalar_t>(), max_iter,
                                 rr.data_ptr<scalar_t>(), status.data_ptr<int32_t>(), beta.data_ptr<scalar_t>(),
                                 iterations.data_ptr<int32_t>(), scratch.data_ptr<double>());
      return;
    }
    update_cpu<scalar_t>(plan, values_per_node(x), x.data_ptr<scalar_t>(), r.data_ptr<scalar_t>(),
                         p.data_ptr<scalar_t>(), ap.data_ptr<scalar_t>(), alpha.data_ptr<scalar_t>(),
                         threshold.data_ptr<scalar_t>(), max_iter, rr.data_ptr<scalar_t>(), status.data_ptr<int32_t>(),
                         beta.data_ptr<scalar_t>(), iterations.data_ptr<int32_t>(), scratch.data_ptr<double>());
  });
}

void cg_direction_cpu(at::Tensor p, const at::Tensor& r, const at::Tensor& beta, const at::Tensor& status,
                      const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                      const c10::optional<at::Tensor>& node_inverse, const c10::optional<at::Tensor>& arm,
                      const c10::optional<at::Tensor>& node_body, const c10::optional<at::Tensor>& coarse,
                      double weight) {
  const CGPlan plan = check_cg_direction(p, r, beta, status, chunk_start, chunk_object, object_chunk);
  const bool with_coarse = check_coarse_term(p, node_inverse, arm, node_body, coarse);
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "cg_direction", [&] {
    const RigidMotion<scalar_t> motion =
        with_coarse ? rigid_motion_of<scalar_t>(node_inverse, arm, node_body, coarse, weight) : RigidMotion<scalar_t>{};
    direction_cpu<scalar_t>(plan, values_per_node(p), p.data_ptr<scalar_t>(), r.data_ptr<scalar_t>(),
                            beta.data_ptr<scalar_t>(), status.data_ptr<int32_t>(), with_coarse ? &motion : nullptr);
  });
}

void cg_start_status_cpu(const at::Tensor& rr, const at::Tensor& rhs_sq, double tol_sq, int64_t max_iter,
                         at::Tensor threshold, at::Tensor status, at::Tensor iterations, at::Tensor alpha,
                         at::Tensor beta, const c10::optional<at::Tensor>& floor,
                         const c10::optional<at::Tensor>& gate) {
  const int64_t objects =
      check_cg_start_status(rr, rhs_sq, max_iter, threshold, status, iterations, alpha, beta, floor, gate);
  AT_DISPATCH_FLOATING_TYPES(rr.scalar_type(), "cg_start_status", [&] {
    const scalar_t* floor_b = floor.has_value() && floor->defined() ? floor->data_ptr<scalar_t>() : nullptr;
    const int32_t* gate_b = gate.has_value() && gate->defined() ? gate->data_ptr<int32_t>() : nullptr;
    const scalar_t* rr_b = rr.data_ptr<scalar_t>();
    const scalar_t* rhs_sq_b = rhs_sq.data_ptr<scalar_t>();
    scalar_t* threshold_b = threshold.data_ptr<scalar_t>();
    scalar_t* alpha_b = alpha.data_ptr<scalar_t>();
    scalar_t* beta_b = beta.data_ptr<scalar_t>();
    int32_t* st = status.data_ptr<int32_t>();
    int32_t* it = iterations.data_ptr<int32_t>();
    for (int64_t o = 0; o < objects; ++o) {
      start_object<scalar_t>(rr_b[o], rhs_sq_b[o], static_cast<scalar_t>(tol_sq), max_iter, floor_b, gate_b, o,
                             threshold_b[o], st[o], it[o], alpha_b[o], beta_b[o]);
    }
  });
}

void cg_round_end_cpu(const at::Tensor& rr, const at::Tensor& threshold, const at::Tensor& round_status,
                      const at::Tensor& round_iterations, at::Tensor status, at::Tensor iterations) {
  const int64_t objects = check_cg_round_end(rr, threshold, round_status, round_iterations, status, iterations);
  AT_DISPATCH_FLOATING_TYPES(rr.scalar_type(), "cg_round_end", [&] {
    const scalar_t* rr_b = rr.data_ptr<scalar_t>();
    const scalar_t* threshold_b = threshold.data_ptr<scalar_t>();
    const int32_t* round_st = round_status.data_ptr<int32_t>();
    const int32_t* round_it = round_iterations.data_ptr<int32_t>();
    int32_t* st = status.data_ptr<int32_t>();
    int32_t* it = iterations.data_ptr<int32_t>();
    for (int64_t o = 0; o < objects; ++o) {
      round_end_object<scalar_t>(rr_b[o], threshold_b[o], round_st[o], round_it[o], st[o], it[o]);
    }
  });
}

void cg_coarse_beta_cpu(const at::Tensor& rr, const at::Tensor& u, const at::Tensor& v, const at::Tensor& item_ptr,
                        double weight, const at::Tensor& status, at::Tensor rz, at::Tensor beta) {
  const int64_t objects = check_cg_coarse_beta(rr, u, v, item_ptr, status, rz, beta);
  const int64_t k = u.size(1);
  AT_DISPATCH_FLOATING_TYPES(rr.scalar_type(), "cg_coarse_beta", [&] {
    const scalar_t* a = u.data_ptr<scalar_t>();
    const scalar_t* b = v.data_ptr<scalar_t>();
    const int64_t* ptr = item_ptr.data_ptr<int64_t>();
    const int32_t* st = status.data_ptr<int32_t>();
    const scalar_t* rr_b = rr.data_ptr<scalar_t>();
    scalar_t* rz_b = rz.data_ptr<scalar_t>();
    scalar_t* beta_b = beta.data_ptr<scalar_t>();
    for (int64_t o = 0; o < objects; ++o) {
      if (st[o] != kActive) continue;
      const double dot = chunk_dot(a, b, ptr[o] * k, ptr[o + 1] * k);
      beta_b[o] = pcg_beta_step<scalar_t>(coarse_rz<scalar_t>(rr_b[o], dot, weight), rz_b[o]);
    }
  });
}

void cg_pair_term_cpu(const at::Tensor& r, at::Tensor z, const at::Tensor& nodes, const at::Tensor& blocks,
                      const at::Tensor& item_ptr, const at::Tensor& rr, const at::Tensor& status, at::Tensor rz,
                      at::Tensor beta, at::Tensor dots, bool step) {
  const int64_t objects = check_cg_pair_term(r, z, nodes, blocks, item_ptr, rr, status, rz, beta, dots);
  AT_DISPATCH_FLOATING_TYPES(r.scalar_type(), "cg_pair_term", [&] {
    const int64_t* ptr = item_ptr.data_ptr<int64_t>();
    const int64_t* pair_nodes = nodes.data_ptr<int64_t>();
    const scalar_t* o = blocks.data_ptr<scalar_t>();
    const scalar_t* rv = r.data_ptr<scalar_t>();
    scalar_t* zv = z.data_ptr<scalar_t>();
    const int32_t* st = status.data_ptr<int32_t>();
    const scalar_t* rr_b = rr.data_ptr<scalar_t>();
    scalar_t* rz_b = rz.data_ptr<scalar_t>();
    scalar_t* beta_b = beta.data_ptr<scalar_t>();
    double* pair_dots = dots.data_ptr<double>();
    for (int64_t b = 0; b < objects; ++b) {
      if (st[b] != kActive) continue;
      double dot = 0.0;
      for (int64_t k = ptr[b]; k < ptr[b + 1]; ++k) {
        pair_dots[k] = pair_term_item<scalar_t>(k, pair_nodes, o, rv, zv);
        dot += pair_dots[k];
      }
      pair_rz_end<scalar_t>(rr_b[b], dot, step, rz_b[b], beta_b[b]);
    }
  });
}

void cg_dot_cpu(const at::Tensor& a, const at::Tensor& b, const at::Tensor& chunk_start,
                const at::Tensor& chunk_object, const at::Tensor& object_chunk, at::Tensor out, at::Tensor scratch,
                at::Tensor counter) {
  const CGPlan plan = check_cg_dot(a, b, chunk_start, chunk_object, object_chunk, out, scratch, counter);
  AT_DISPATCH_FLOATING_TYPES(a.scalar_type(), "cg_dot", [&] {
    object_dots_cpu<scalar_t>(plan, values_per_node(a), a.data_ptr<scalar_t>(), b.data_ptr<scalar_t>(),
                              out.data_ptr<scalar_t>(), scratch.data_ptr<double>());
  });
}

void cg_dot_beta_cpu(const at::Tensor& r, const at::Tensor& z, const at::Tensor& chunk_start,
                     const at::Tensor& chunk_object, const at::Tensor& object_chunk, const at::Tensor& status,
                     at::Tensor rz, at::Tensor beta, at::Tensor scratch, at::Tensor counter) {
  const CGPlan plan = check_cg_dot_beta(r, z, chunk_start, chunk_object, object_chunk, status, rz, beta, scratch,
                                        counter);
  AT_DISPATCH_FLOATING_TYPES(r.scalar_type(), "cg_dot_beta", [&] {
    const int64_t d = values_per_node(r);
    const scalar_t* a = r.data_ptr<scalar_t>();
    const scalar_t* b = z.data_ptr<scalar_t>();
    const int32_t* st = status.data_ptr<int32_t>();
    double* sums = scratch.data_ptr<double>();
    for_each_chunk(plan, d, st, [&](int64_t c, int64_t begin, int64_t end) { sums[c] = chunk_dot(a, b, begin * d, end * d); });
    scalar_t* rz_b = rz.data_ptr<scalar_t>();
    scalar_t* beta_b = beta.data_ptr<scalar_t>();
    for (int64_t o = 0; o < plan.num_objects; ++o) {
      if (st[o] != kActive) continue;
      const scalar_t total = static_cast<scalar_t>(object_sum(sums, plan.object_chunk, o));
      beta_b[o] = pcg_beta_step<scalar_t>(total, rz_b[o]);
    }
  });
}

void euler_update_cpu(at::Tensor x, at::Tensor v, const at::Tensor& dv, const c10::optional<at::Tensor>& dv_imposed,
                      double h, at::Tensor x_new, at::Tensor v_new, const at::Tensor& chunk_start,
                      const at::Tensor& chunk_object, const at::Tensor& object_chunk, const at::Tensor& status,
                      const at::Tensor& iterations, const at::Tensor& rr, const at::Tensor& rhs_sq, at::Tensor norms,
                      at::Tensor summary, at::Tensor scratch, at::Tensor counter, const c10::optional<at::Tensor>& ring,
                      const c10::optional<at::Tensor>& ring_pos, bool carry, double h_old) {
  const CGPlan plan = check_euler_update(x, v, dv, dv_imposed, x_new, v_new, chunk_start, chunk_object, object_chunk,
                                         status, iterations, rr, rhs_sq, norms, summary, scratch, counter, ring,
                                         ring_pos);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "euler_update", [&] {
    const EulerUpdate<scalar_t> update = euler_update_of<scalar_t>(x, v, dv, dv_imposed, h, x_new, v_new, carry,
                                                                   h_old);
    const StepSummary<scalar_t> out = step_summary_of<scalar_t>(status, iterations, rr, rhs_sq, norms, summary, ring,
                                                                ring_pos);
    double* sums = scratch.data_ptr<double>();
    const int64_t d = update.d;
    at::parallel_for(0, plan.num_chunks, chunk_grain(plan, d), [&](int64_t begin, int64_t end) {
      for (int64_t c = begin; c < end; ++c) {
        double acc = 0.0;  // in chunk_dot's order
        for (int64_t j = plan.chunk_start[c] * d; j < plan.chunk_start[c + 1] * d; ++j) {
          const scalar_t vn = update(j);
          acc += static_cast<double>(vn) * static_cast<double>(vn);
        }
        sums[c] = acc;
      }
    });
    const int64_t pos = out.ring_pos != nullptr ? *out.ring_pos : -1;
    for (int64_t b = 0; b < plan.num_objects; ++b) {
      out.write(b, plan.num_objects, object_sum(sums, plan.object_chunk, b), pos);
    }
    if (out.ring_pos != nullptr) *out.ring_pos = pos + 1;
  });
}

}  // namespace
}  // namespace tensormass

TORCH_LIBRARY_IMPL(tensormass, CPU, m) {
  m.impl("euler_update", &tensormass::euler_update_cpu);
  m.impl("cg_dot", &tensormass::cg_dot_cpu);
  m.impl("cg_dot_beta", &tensormass::cg_dot_beta_cpu);
  m.impl("cg_alpha", &tensormass::cg_alpha_cpu);
  m.impl("cg_alpha_dot", &tensormass::cg_alpha_dot_cpu);
  m.impl("cg_update", &tensormass::cg_update_cpu);
  m.impl("cg_direction", &tensormass::cg_direction_cpu);
  m.impl("cg_coarse_beta", &tensormass::cg_coarse_beta_cpu);
  m.impl("cg_start_status", &tensormass::cg_start_status_cpu);
  m.impl("cg_round_end", &tensormass::cg_round_end_cpu);
  m.impl("cg_pair_term", &tensormass::cg_pair_term_cpu);
}
