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
  AT_DISPATCH_FLOATING_TYPES(x.scalar_type(), "cg_update", [&] {
    update_cpu<scalar_t>(plan, values_per_node(x), x.data_ptr<scalar_t>(), r.data_ptr<scalar_t>(),
                         p.data_ptr<scalar_t>(), ap.data_ptr<scalar_t>(), alpha.data_ptr<scalar_t>(),
                         threshold.data_ptr<scalar_t>(), max_iter, rr.data_ptr<scalar_t>(), status.data_ptr<int32_t>(),
                         beta.data_ptr<scalar_t>(), iterations.data_ptr<int32_t>(), scratch.data_ptr<double>());
  });
}

void cg_direction_cpu(at::Tensor p, const at::Tensor& r, const at::Tensor& beta, const at::Tensor& status,
                      const at::Tensor& chunk_start, const at::Tensor& chunk_object, const at::Tensor& object_chunk) {
  const CGPlan plan = check_cg_direction(p, r, beta, status, chunk_start, chunk_object, object_chunk);
  AT_DISPATCH_FLOATING_TYPES(p.scalar_type(), "cg_direction", [&] {
    direction_cpu<scalar_t>(plan, values_per_node(p), p.data_ptr<scalar_t>(), r.data_ptr<scalar_t>(),
                            beta.data_ptr<scalar_t>(), status.data_ptr<int32_t>());
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

}  // namespace
}  // namespace tensormass

TORCH_LIBRARY_IMPL(tensormass, CPU, m) {
  m.impl("cg_dot", &tensormass::cg_dot_cpu);
  m.impl("cg_alpha", &tensormass::cg_alpha_cpu);
  m.impl("cg_update", &tensormass::cg_update_cpu);
  m.impl("cg_direction", &tensormass::cg_direction_cpu);
}
