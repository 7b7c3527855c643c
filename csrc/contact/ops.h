// Host side of the contact ops (schemas: schema.cpp; kernel: kernels.h), written once for the CPU
// and CUDA: argument checks, dispatch and one launch through `L` (common/cpu_launcher.h,
// common/cuda_launcher.cuh); cpu.cpp and cuda.cu register them (register_contact_ops). The count
// allocates its output; neither op reads anything back to the host.
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <cstdint>
#include <string>

#include "common/checks.h"
#include "common/dispatch.h"
#include "contact/kernels.h"

namespace tensormass {

// The broad phase's inputs, checked against each other (names as in schema.cpp).
struct CandidateArgs {
  at::Tensor cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start, query_stop,
      entry_triangle, entry_cells, low, high, triangle_object;
  bool same_body;

  void check() const {
    TORCH_CHECK(point_low.defined() && point_low.dim() == 2 && point_low.size(1) == 3,
                "tensormass: point_low must be [Sv, 3], got shape ", shape_str(point_low.sizes()));
    TORCH_CHECK(point_low.scalar_type() == at::kFloat || point_low.scalar_type() == at::kDouble,
                "tensormass: point_low must be float32 or float64, got ", dtype_str(point_low.scalar_type()));
    const int64_t num_vertices = point_low.size(0), num_queries = query_vertex.numel();
    const int64_t num_entries = entry_triangle.numel(), num_triangles = low.size(0);
    check_node_tensor(point_low, "point_low", point_low, {num_vertices, 3}, "point_low");
    check_node_tensor(cell, "cell", point_low, {1}, "point_low");
    check_node_tensor(point_high, "point_high", point_low, {num_vertices, 3}, "point_low");
    check_node_tensor(low, "low", point_low, {num_triangles, 3}, "point_low");
    check_node_tensor(high, "high", point_low, {num_triangles, 3}, "point_low");
    check_index_tensor(vertex_object, "vertex_object", point_low, at::kLong, {num_vertices}, "point_low");
    check_index_tensor(query_vertex, "query_vertex", point_low, at::kLong, {num_queries}, "point_low");
    check_index_tensor(query_cells, "query_cells", point_low, at::kLong, {num_queries, 3}, "point_low");
    check_index_tensor(query_start, "query_start", point_low, at::kLong, {num_queries}, "point_low");
    check_index_tensor(query_stop, "query_stop", point_low, at::kLong, {num_queries}, "point_low");
    check_index_tensor(entry_triangle, "entry_triangle", point_low, at::kLong, {num_entries}, "point_low");
    check_index_tensor(entry_cells, "entry_cells", point_low, at::kLong, {num_entries, 3}, "point_low");
    check_index_tensor(triangle_object, "triangle_object", point_low, at::kLong, {num_triangles}, "point_low");
  }

  template <typename S>
  CandidatesKernel<S> kernel() const {
    CandidatesKernel<S> k{};
    k.cell = cell.data_ptr<S>();
    k.point_low = point_low.data_ptr<S>();
    k.point_high = point_high.data_ptr<S>();
    k.vertex_object = vertex_object.data_ptr<int64_t>();
    k.query_vertex = query_vertex.data_ptr<int64_t>();
    k.query_cells = query_cells.data_ptr<int64_t>();
    k.query_start = query_start.data_ptr<int64_t>();
    k.query_stop = query_stop.data_ptr<int64_t>();
    k.entry_triangle = entry_triangle.data_ptr<int64_t>();
    k.entry_cells = entry_cells.data_ptr<int64_t>();
    k.low = low.data_ptr<S>();
    k.high = high.data_ptr<S>();
    k.triangle_object = triangle_object.data_ptr<int64_t>();
    k.same_body = same_body;
    return k;
  }
};

// contact_count_candidates: see schema.cpp.
template <class L>
at::Tensor contact_count_candidates(const at::Tensor& cell, const at::Tensor& point_low, const at::Tensor& point_high,
                                    const at::Tensor& vertex_object, const at::Tensor& query_vertex,
                                    const at::Tensor& query_cells, const at::Tensor& query_start,
                                    const at::Tensor& query_stop, const at::Tensor& entry_triangle,
                                    const at::Tensor& entry_cells, const at::Tensor& low, const at::Tensor& high,
                                    const at::Tensor& triangle_object, bool same_body) {
  const CandidateArgs args{cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start,
                           query_stop, entry_triangle, entry_cells, low, high, triangle_object, same_body};
  args.check();
  at::Tensor counts = at::empty({query_vertex.numel()}, query_vertex.options());
  typename L::Guard guard(point_low.device());
  dispatch_scalar(point_low.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    CandidatesKernel<S> k = args.kernel<S>();
    k.counts = counts.data_ptr<int64_t>();
    L::run(query_vertex.numel(), k, L::kNodeBlock);
  });
  return counts;
}

// contact_fill_candidates: see schema.cpp.
template <class L>
void contact_fill_candidates(const at::Tensor& cell, const at::Tensor& point_low, const at::Tensor& point_high,
                             const at::Tensor& vertex_object, const at::Tensor& query_vertex,
                             const at::Tensor& query_cells, const at::Tensor& query_start,
                             const at::Tensor& query_stop, const at::Tensor& entry_triangle,
                             const at::Tensor& entry_cells, const at::Tensor& low, const at::Tensor& high,
                             const at::Tensor& triangle_object, bool same_body, const at::Tensor& offsets,
                             at::Tensor vertex, at::Tensor triangle) {
  const CandidateArgs args{cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start,
                           query_stop, entry_triangle, entry_cells, low, high, triangle_object, same_body};
  args.check();
  check_index_tensor(offsets, "offsets", point_low, at::kLong, {query_vertex.numel()}, "point_low");
  TORCH_CHECK(vertex.defined() && vertex.dim() == 1, "tensormass: vertex must be [C]");
  check_index_tensor(vertex, "vertex", point_low, at::kLong, {vertex.size(0)}, "point_low");
  check_index_tensor(triangle, "triangle", point_low, at::kLong, {vertex.size(0)}, "point_low");
  typename L::Guard guard(point_low.device());
  dispatch_scalar(point_low.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    CandidatesKernel<S> k = args.kernel<S>();
    k.offsets = offsets.data_ptr<int64_t>();
    k.vertex_out = vertex.data_ptr<int64_t>();
    k.triangle_out = triangle.data_ptr<int64_t>();
    L::run(query_vertex.numel(), k, L::kNodeBlock);
  });
}

// Registers the implementations of the contact ops of one backend (launcher L) under its
// TORCH_LIBRARY_IMPL (cpu.cpp, cuda.cu); the schemas: schema.cpp.
template <class L>
void register_contact_ops(torch::Library& m) {
  m.impl("contact_count_candidates", &contact_count_candidates<L>);
  m.impl("contact_fill_candidates", &contact_fill_candidates<L>);
}

}  // namespace tensormass
