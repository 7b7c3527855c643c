// Host side of the contact ops (schemas: schema.cpp; kernels: kernels.h), written once for the CPU
// and CUDA: argument checks, dispatch and one launch through `L` (common/cpu_launcher.h,
// common/cuda_launcher.cuh); cpu.cpp and cuda.cu register them (register_contact_ops). The counts
// allocate their outputs; no op reads anything back to the host.
#pragma once

#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <torch/library.h>

#include <cstdint>
#include <limits>
#include <string>

#include "common/checks.h"
#include "common/dispatch.h"
#include "contact/kernels.h"

namespace tensormass {

// The broad phase's inputs, checked against each other (names as in schema.cpp).
struct CandidateArgs {
  at::Tensor cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start, query_stop,
      query_order, entry_triangle, entry_cells, low, high, triangle_object;
  bool same_body;
  c10::optional<at::Tensor> triangle_first;

  bool skips_own() const { return !same_body && triangle_first.has_value() && triangle_first->defined(); }

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
    check_index_tensor(query_order, "query_order", point_low, at::kLong, {num_queries}, "point_low");
    check_index_tensor(entry_triangle, "entry_triangle", point_low, at::kLong, {num_entries}, "point_low");
    check_index_tensor(entry_cells, "entry_cells", point_low, at::kLong, {num_entries, 3}, "point_low");
    check_index_tensor(triangle_object, "triangle_object", point_low, at::kLong, {num_triangles}, "point_low");
    if (triangle_first.has_value() && triangle_first->defined()) {
      TORCH_CHECK(triangle_first->dim() == 1 && triangle_first->size(0) >= 1,
                  "tensormass: triangle_first must be [B + 1], got shape ", shape_str(triangle_first->sizes()));
      check_index_tensor(*triangle_first, "triangle_first", point_low, at::kLong, {triangle_first->size(0)},
                         "point_low");
    }
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
    k.query_order = query_order.data_ptr<int64_t>();
    k.entry_triangle = entry_triangle.data_ptr<int64_t>();
    k.entry_cells = entry_cells.data_ptr<int64_t>();
    k.low = low.data_ptr<S>();
    k.high = high.data_ptr<S>();
    k.triangle_object = triangle_object.data_ptr<int64_t>();
    k.triangle_first = skips_own() ? triangle_first->data_ptr<int64_t>() : nullptr;
    k.same_body = same_body;
    return k;
  }
};

// contact_count_candidates: see schema.cpp.
template <class L>
at::Tensor contact_count_candidates(const at::Tensor& cell, const at::Tensor& point_low, const at::Tensor& point_high,
                                    const at::Tensor& vertex_object, const at::Tensor& query_vertex,
                                    const at::Tensor& query_cells, const at::Tensor& query_start,
                                    const at::Tensor& query_stop, const at::Tensor& query_order,
                                    const at::Tensor& entry_triangle,
                                    const at::Tensor& entry_cells, const at::Tensor& low, const at::Tensor& high,
                                    const at::Tensor& triangle_object, bool same_body,
                                    const c10::optional<at::Tensor>& triangle_first) {
  const CandidateArgs args{cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start,
                           query_stop, query_order, entry_triangle, entry_cells, low, high, triangle_object,
                           same_body, triangle_first};
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
                             const at::Tensor& query_stop, const at::Tensor& query_order,
                             const at::Tensor& entry_triangle,
                             const at::Tensor& entry_cells, const at::Tensor& low, const at::Tensor& high,
                             const at::Tensor& triangle_object, bool same_body,
                             const c10::optional<at::Tensor>& triangle_first, const at::Tensor& offsets,
                             at::Tensor vertex, at::Tensor triangle) {
  const CandidateArgs args{cell, point_low, point_high, vertex_object, query_vertex, query_cells, query_start,
                           query_stop, query_order, entry_triangle, entry_cells, low, high, triangle_object,
                           same_body, triangle_first};
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

// The narrow phase's inputs, checked against each other (names as in schema.cpp).
struct NearestArgs {
  at::Tensor x, vertices, vertex_object, triangles, triangle_object, first, candidate_triangle;
  c10::optional<at::Tensor> spread, body_step;
  double reach;

  bool swept() const { return spread.has_value() && spread->defined(); }

  void check() const {
    check_values(x, "x");
    TORCH_CHECK(x.size(1) == 3, "tensormass: x must be [V, 3], got shape ", shape_str(x.sizes()));
    const int64_t num_vertices = vertices.numel(), num_triangles = triangles.dim() == 2 ? triangles.size(0) : -1;
    TORCH_CHECK(num_triangles >= 0, "tensormass: triangles must be [F, 3], got shape ", shape_str(triangles.sizes()));
    check_index_tensor(vertices, "vertices", x, at::kLong, {num_vertices}, "x");
    check_index_tensor(vertex_object, "vertex_object", x, at::kLong, {num_vertices}, "x");
    check_index_tensor(triangles, "triangles", x, at::kLong, {num_triangles, 3}, "x");
    check_index_tensor(triangle_object, "triangle_object", x, at::kLong, {num_triangles}, "x");
    check_index_tensor(first, "first", x, at::kLong, {num_vertices + 1}, "x");
    check_index_tensor(candidate_triangle, "candidate_triangle", x, at::kLong, {candidate_triangle.numel()}, "x");
    TORCH_CHECK(reach > 0, "tensormass: reach must be > 0, got ", std::to_string(reach));
    if (swept()) {
      check_node_tensor(*spread, "spread", x, {x.size(0)}, "x");
      TORCH_CHECK(body_step.has_value() && body_step->defined() && body_step->dim() == 2,
                  "tensormass: body_step must be [B, 3] when spread is given");
      check_node_tensor(*body_step, "body_step", x, {body_step->size(0), 3}, "x");
    }
  }

  template <typename S>
  NearestPairsKernel<S> kernel() const {
    NearestPairsKernel<S> k{};
    k.x = x.data_ptr<S>();
    k.vertices = vertices.data_ptr<int64_t>();
    k.vertex_object = vertex_object.data_ptr<int64_t>();
    k.triangles = triangles.data_ptr<int64_t>();
    k.triangle_object = triangle_object.data_ptr<int64_t>();
    k.first = first.data_ptr<int64_t>();
    k.candidate_triangle = candidate_triangle.data_ptr<int64_t>();
    k.spread = swept() ? spread->data_ptr<S>() : nullptr;
    k.body_step = swept() ? body_step->data_ptr<S>() : nullptr;
    k.reach = static_cast<S>(reach);
    k.eps = std::numeric_limits<S>::epsilon();
    k.tiny = std::numeric_limits<S>::min();
    return k;
  }
};

// contact_count_nearest: see schema.cpp.
template <class L>
std::tuple<at::Tensor, at::Tensor> contact_count_nearest(
    const at::Tensor& x, const at::Tensor& vertices, const at::Tensor& vertex_object, const at::Tensor& triangles,
    const at::Tensor& triangle_object, const at::Tensor& first, const at::Tensor& candidate_triangle,
    const c10::optional<at::Tensor>& spread, const c10::optional<at::Tensor>& body_step, double reach) {
  const NearestArgs args{x, vertices, vertex_object, triangles, triangle_object, first, candidate_triangle,
                         spread, body_step, reach};
  args.check();
  at::Tensor counts = at::empty({vertices.numel()}, vertices.options());
  at::Tensor chosen = at::empty({vertices.numel()}, vertices.options());
  typename L::Guard guard(x.device());
  dispatch_scalar(x.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    NearestPairsKernel<S> k = args.kernel<S>();
    k.counts = counts.data_ptr<int64_t>();
    k.chosen = chosen.data_ptr<int64_t>();
    L::run(vertices.numel(), k, L::kElementBlock);
  });
  return {counts, chosen};
}

// contact_fill_nearest: see schema.cpp.
template <class L>
void contact_fill_nearest(const at::Tensor& x, const at::Tensor& vertices, const at::Tensor& vertex_object,
                          const at::Tensor& triangles, const at::Tensor& triangle_object, const at::Tensor& first,
                          const at::Tensor& candidate_triangle, const c10::optional<at::Tensor>& spread,
                          const c10::optional<at::Tensor>& body_step, double reach, const at::Tensor& offsets,
                          const at::Tensor& chosen, at::Tensor pair_vertex, at::Tensor pair_triangle,
                          at::Tensor weights, at::Tensor diff, at::Tensor distance, at::Tensor normal,
                          at::Tensor side) {
  const NearestArgs args{x, vertices, vertex_object, triangles, triangle_object, first, candidate_triangle,
                         spread, body_step, reach};
  args.check();
  check_index_tensor(offsets, "offsets", x, at::kLong, {vertices.numel()}, "x");
  check_index_tensor(chosen, "chosen", x, at::kLong, {vertices.numel()}, "x");
  TORCH_CHECK(pair_vertex.defined() && pair_vertex.dim() == 1, "tensormass: pair_vertex must be [P]");
  const int64_t num_pairs = pair_vertex.size(0);
  check_index_tensor(pair_vertex, "pair_vertex", x, at::kLong, {num_pairs}, "x");
  check_index_tensor(pair_triangle, "pair_triangle", x, at::kLong, {num_pairs}, "x");
  check_node_tensor(weights, "weights", x, {num_pairs, 3}, "x");
  check_node_tensor(diff, "diff", x, {num_pairs, 3}, "x");
  check_node_tensor(distance, "distance", x, {num_pairs}, "x");
  check_node_tensor(normal, "normal", x, {num_pairs, 3}, "x");
  check_node_tensor(side, "side", x, {num_pairs}, "x");
  typename L::Guard guard(x.device());
  dispatch_scalar(x.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    NearestPairsKernel<S> k = args.kernel<S>();
    k.offsets = offsets.data_ptr<int64_t>();
    k.chosen = const_cast<int64_t*>(chosen.data_ptr<int64_t>());  // (read only in the fill pass)
    k.pair_vertex = pair_vertex.data_ptr<int64_t>();
    k.pair_triangle = pair_triangle.data_ptr<int64_t>();
    k.weights = weights.data_ptr<S>();
    k.diff = diff.data_ptr<S>();
    k.distance = distance.data_ptr<S>();
    k.normal = normal.data_ptr<S>();
    k.side = side.data_ptr<S>();
    L::run(vertices.numel(), k, L::kElementBlock);
  });
}

// contact_pair_product: see schema.cpp.
template <class L>
void contact_pair_product(const at::Tensor& dx, const at::Tensor& nodes, const at::Tensor& coef,
                          const at::Tensor& direction, const at::Tensor& normal, const at::Tensor& friction,
                          const at::Tensor& order, const at::Tensor& offsets, at::Tensor vector, at::Tensor out,
                          bool accumulate) {
  check_values(dx, "dx");
  TORCH_CHECK(dx.size(1) == 3, "tensormass: dx must be [V, 3], got shape ", shape_str(dx.sizes()));
  const int64_t num_nodes = dx.size(0);
  TORCH_CHECK(nodes.defined() && nodes.dim() == 2 && nodes.size(1) == 4, "tensormass: nodes must be [C, 4]");
  const int64_t capacity = nodes.size(0);
  check_index_tensor(nodes, "nodes", dx, at::kLong, {capacity, 4}, "dx");
  check_node_tensor(coef, "coef", dx, {capacity, 4}, "dx");
  check_node_tensor(direction, "direction", dx, {capacity, 3}, "dx");
  check_node_tensor(normal, "normal", dx, {capacity}, "dx");
  check_node_tensor(friction, "friction", dx, {capacity}, "dx");
  check_index_tensor(order, "order", dx, at::kLong, {4 * capacity}, "dx");
  check_index_tensor(offsets, "offsets", dx, at::kLong, {num_nodes + 1}, "dx");
  check_node_tensor(vector, "vector", dx, {capacity, 3}, "dx");
  check_node_tensor(out, "out", dx, {num_nodes, 3}, "dx");
  TORCH_CHECK(!out.is_same(dx), "tensormass: out must not be dx");
  typename L::Guard guard(dx.device());
  dispatch_scalar(dx.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    PairVectorKernel<S> pairs{dx.data_ptr<S>(), nodes.data_ptr<int64_t>(), coef.data_ptr<S>(),
                              direction.data_ptr<S>(), normal.data_ptr<S>(), friction.data_ptr<S>(),
                              vector.data_ptr<S>()};
    L::run(capacity, pairs, L::kNodeBlock);
    PairGatherKernel<S> gather{coef.data_ptr<S>(), vector.data_ptr<S>(), order.data_ptr<int64_t>(),
                               offsets.data_ptr<int64_t>(), out.data_ptr<S>(), accumulate};
    L::run(num_nodes, gather, L::kNodeBlock);
  });
}

// Registers the implementations of the contact ops of one backend (launcher L) under its
// TORCH_LIBRARY_IMPL (cpu.cpp, cuda.cu); the schemas: schema.cpp.
template <class L>
void register_contact_ops(torch::Library& m) {
  m.impl("contact_count_candidates", &contact_count_candidates<L>);
  m.impl("contact_fill_candidates", &contact_fill_candidates<L>);
  m.impl("contact_count_nearest", &contact_count_nearest<L>);
  m.impl("contact_fill_nearest", &contact_fill_nearest<L>);
  m.impl("contact_pair_product", &contact_pair_product<L>);
}

}  // namespace tensormass
