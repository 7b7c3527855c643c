// CPU implementations of the CG ops (cg.h; the chunked reductions: cpu/cg_chunks.h).
#include <ATen/Dispatch.h>
#include <ATen/Parallel.h>

#include <algorithm>
#include <torch/library.h>

#include "cg.h"
#include "cpu/cg_chunks.h"

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

void cg_update_cpu(at::Tensor x, at::Tensor r, const at::Tensor& p, const at::Tensor& ap, const at::Tensor& alpha,
                   const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk,
                   const at::Tensor& threshold, int64_t max_iter, at::Tensor rr, at::Tensor status, at::Tensor beta,
                   at::Tensor iterations, at::Tensor scratch, at::Tensor counter) {
  const CGPlan plan = check_cg_update(x, r, p, ap, alpha, chunk_start, chunk_object, object_chunk, threshold, max_iter,
                                      rr, status, beta, iterations, scratch, counter);
  const int64_t d = values_per_node(x);
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "cg_update", [&] {
    scalar_t* x_p = x.data_ptr<scalar_t>();
    scalar_t* r_p = r.data_ptr<scalar_t>();
    const scalar_t* p_p = p.data_ptr<scalar_t>();
    const scalar_t* ap_p = ap.data_ptr<scalar_t>();
    const scalar_t* alpha_p = alpha.data_ptr<scalar_t>();
    double* sums = scratch.data_ptr<double>();
    int32_t* st = status.data_ptr<int32_t>();
    for_each_chunk(plan, d, st, [&](int64_t c, int64_t begin, int64_t end) {
      const scalar_t a = alpha_p[plan.chunk_object[c]];
      for (int64_t j = begin * d; j < end * d; ++j) {
        x_p[j] += a * p_p[j];
        r_p[j] -= a * ap_p[j];
      }
      sums[c] = chunk_dot(r_p, r_p, begin * d, end * d);
    });
    scalar_t* rr_p = rr.data_ptr<scalar_t>();
    scalar_t* beta_p = beta.data_ptr<scalar_t>();
    const scalar_t* threshold_p = threshold.data_ptr<scalar_t>();
    int32_t* it = iterations.data_ptr<int32_t>();
    for (int64_t b = 0; b < plan.num_objects; ++b) {
      if (st[b] != kActive) continue;
      beta_p[b] = cg_beta_step<scalar_t>(object_sum(sums, plan.object_chunk, b), rr_p[b], threshold_p[b], max_iter,
                                         st[b], it[b]);
    }
  });
}

void cg_direction_cpu(at::Tensor p, const at::Tensor& r, const at::Tensor& beta, const at::Tensor& status,
                      const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk) {
  const CGPlan plan = check_cg_direction(p, r, beta, status, chunk_start, chunk_object, object_chunk);
  const int64_t d = values_per_node(p);
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "cg_direction", [&] {
    scalar_t* p_p = p.data_ptr<scalar_t>();
    const scalar_t* r_p = r.data_ptr<scalar_t>();
    const scalar_t* beta_p = beta.data_ptr<scalar_t>();
    for_each_chunk(plan, d, status.data_ptr<int32_t>(), [&](int64_t c, int64_t begin, int64_t end) {
      const scalar_t bt = beta_p[plan.chunk_object[c]];
      for (int64_t j = begin * d; j < end * d; ++j) p_p[j] = r_p[j] + bt * p_p[j];
    });
  });
}

void cg_dot_cpu(const at::Tensor& a, const at::Tensor& b, const at::Tensor& chunk_start,
                const at::Tensor& chunk_object, const at::Tensor& object_chunk, at::Tensor out, at::Tensor scratch,
                at::Tensor counter) {
  const CGPlan plan = check_cg_dot(a, b, chunk_start, chunk_object, object_chunk, out, scratch, counter);
  const int64_t d = values_per_node(a);
  AT_DISPATCH_FLOATING_TYPES(a.scalar_type(), "cg_dot", [&] {
    const scalar_t* a_p = a.data_ptr<scalar_t>();
    const scalar_t* b_p = b.data_ptr<scalar_t>();
    double* sums = scratch.data_ptr<double>();
    at::parallel_for(0, plan.num_chunks, chunk_grain(plan, d), [&](int64_t begin, int64_t end) {
      for (int64_t c = begin; c < end; ++c) sums[c] = chunk_dot(a_p, b_p, plan.chunk_start[c] * d, plan.chunk_start[c + 1] * d);
    });
    scalar_t* out_p = out.data_ptr<scalar_t>();
    for (int64_t o = 0; o < plan.num_objects; ++o) out_p[o] = static_cast<scalar_t>(object_sum(sums, plan.object_chunk, o));
  });
}

}  // namespace
}  // namespace tensormass

TORCH_LIBRARY_IMPL(tensormass, CPU, m) {
  m.impl("cg_dot", &tensormass::cg_dot_cpu);
  m.impl("cg_alpha", &tensormass::cg_alpha_cpu);
  m.impl("cg_update", &tensormass::cg_update_cpu);
  m.impl("cg_direction", &tensormass::cg_direction_cpu);
}
