// Host side of the multigrid ops (schemas: schema.cpp; kernels: kernels.h), written once for the
// CPU and CUDA: argument checks, dispatch on the dtype and the block shape, one launch through
// `L` (cpu.cpp, cuda.cu: `L::run_rows(rows, kernel, group)` runs kernel.partial on `group` lanes
// of each row and kernel.finish on their sum; `L::run(n, kernel, block)` an item a thread). No allocation, no host synchronisation: a V-cycle
// of these ops is captured in a CUDA graph.
#pragma once

#include <ATen/core/Tensor.h>
#include <c10/util/Optional.h>
#include <torch/library.h>

#include <cstdint>
#include <limits>
#include <string>

#include "common/checks.h"
#include "common/dispatch.h"
#include "multigrid/kernels.h"

namespace tensormass {

// The block shapes the hierarchies use: a level's operator (k x k blocks, k = 6 rigid-body modes
// in 3-D, 3 in 2-D), its prolongator (d x k: a node's unknowns from its aggregates' modes) and
// restriction (k x d); the finest level's (d x d) for tests and other callers.
template <class F>
void dispatch_block(int64_t r, int64_t c, F&& f) {
#define TM_BLOCK_CASE(RR, CC)      \
  if (r == RR && c == CC) {        \
    f(IC<RR>{}, IC<CC>{});         \
    return;                        \
  }
  TM_BLOCK_CASE(6, 6)
  TM_BLOCK_CASE(3, 6)
  TM_BLOCK_CASE(6, 3)
  TM_BLOCK_CASE(3, 3)
  TM_BLOCK_CASE(2, 3)
  TM_BLOCK_CASE(3, 2)
  TM_BLOCK_CASE(2, 2)
  TM_BLOCK_CASE(1, 1)
#undef TM_BLOCK_CASE
  TORCH_CHECK(false, "tensormass: unsupported block shape ", std::to_string(r), " x ", std::to_string(c),
              " (6x6, 3x6, 6x3, 3x3, 2x3, 3x2, 2x2, 1x1)");
}

// f(S{}, IC<R>{}, IC<C>{}) for the dtype and block shape of a call.
template <class F>
void dispatch_scalar_block(at::ScalarType t, int64_t r, int64_t c, F&& f) {
  dispatch_scalar(t, [&](auto s_tag) { dispatch_block(r, c, [&](auto r_c, auto c_c) { f(s_tag, r_c, c_c); }); });
}

// Lanes summing one block row: a warp where rows hold many blocks (a coarse level's ~50), fewer
// where they hold few (a prolongator's ~4), one where they hold one (block Jacobi's factors, a
// rigid-mode prolongation: more lanes would only add zeros), one on the CPU. A function of the
// matrix alone, so one matrix always sums in one order.
inline int row_group(int64_t blocks, int64_t rows) {
  const int64_t per_row = rows > 0 ? blocks / rows : 0;
  return per_row >= 16 ? 32 : per_row >= 4 ? 8 : per_row >= 2 ? 4 : 1;
}

// A BSR matrix's arrays: values [nb, R, C] floating, block_cols [nb] and row_ptr [Rb + 1] int32,
// on `like`'s device and dtype. Returns Rb.
inline int64_t check_bsr(const at::Tensor& values, const at::Tensor& block_cols, const at::Tensor& row_ptr,
                         const at::Tensor& like, const char* like_name) {
  TORCH_CHECK(values.defined() && values.dim() == 3, "tensormass: values must be [nb, R, C]");
  check_node_tensor(values, "values", like, values.sizes(), like_name);
  TORCH_CHECK(row_ptr.defined() && row_ptr.dim() == 1 && row_ptr.size(0) >= 1,
              "tensormass: row_ptr must be [Rb + 1]");
  check_index_tensor(block_cols, "block_cols", like, at::kInt, {values.size(0)}, like_name);
  check_index_tensor(row_ptr, "row_ptr", like, at::kInt, {row_ptr.size(0)}, like_name);
  return row_ptr.size(0) - 1;
}

inline void check_vector(const at::Tensor& t, const char* name, const at::Tensor& like, int64_t size,
                         const char* like_name) {
  TORCH_CHECK(t.defined() && t.dim() == 1, "tensormass: ", name, " must be 1-D, got ",
              t.defined() ? shape_str(t.sizes()) : std::string("undefined"));
  check_node_tensor(t, name, like, {size}, like_name);
}

inline void check_float(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.defined(), "tensormass: ", name, " is undefined");
  TORCH_CHECK(t.scalar_type() == at::kFloat || t.scalar_type() == at::kDouble, "tensormass: ", name,
              " must be float32 or float64, got ", dtype_str(t.scalar_type()));
}

// multigrid_bsr_gemv: see schema.cpp.
template <class L>
void multigrid_bsr_gemv(const at::Tensor& values, const at::Tensor& block_cols, const at::Tensor& row_ptr,
                        const at::Tensor& x, const c10::optional<at::Tensor>& y, double alpha, double beta,
                        at::Tensor out) {
  check_float(out, "out");
  const int64_t rows = check_bsr(values, block_cols, row_ptr, out, "out");
  const int64_t r = values.size(1), c = values.size(2);
  check_vector(out, "out", out, rows * r, "out");
  TORCH_CHECK(x.defined() && x.dim() == 1 && x.numel() % c == 0, "tensormass: x must be 1-D of a multiple of C = ",
              std::to_string(c), " values");
  check_node_tensor(x, "x", out, {x.numel()}, "out");
  TORCH_CHECK(!x.is_same(out) && x.data_ptr() != out.data_ptr(), "tensormass: out must not be x");
  const bool with_y = y.has_value() && y->defined();
  if (with_y) check_vector(*y, "y", out, rows * r, "out");
  typename L::Guard guard(out.device());
  dispatch_scalar_block(out.scalar_type(), r, c, [&](auto s_tag, auto r_c, auto c_c) {
    using S = decltype(s_tag);
    BsrGemvKernel<decltype(r_c)::value, decltype(c_c)::value, S> k;
    k.a = {values.data_ptr<S>(), block_cols.data_ptr<int32_t>(), row_ptr.data_ptr<int32_t>()};
    k.x = x.data_ptr<S>();
    k.y = with_y ? y->data_ptr<S>() : nullptr;
    k.alpha = static_cast<S>(alpha);
    k.beta = static_cast<S>(beta);
    k.out = out.data_ptr<S>();
    L::run_rows(rows, k, row_group(values.size(0), rows));
  });
}

// multigrid_chebyshev: see schema.cpp.
template <class L>
void multigrid_chebyshev(const c10::optional<at::Tensor>& values, const c10::optional<at::Tensor>& block_cols,
                         const c10::optional<at::Tensor>& row_ptr, const c10::optional<at::Tensor>& product,
                         const at::Tensor& b, const at::Tensor& inverse_diagonal, const c10::optional<at::Tensor>& x,
                         at::Tensor step, at::Tensor x_out, double coef_a, double coef_c) {
  check_float(b, "b");
  TORCH_CHECK(b.dim() == 1, "tensormass: b must be 1-D, got ", shape_str(b.sizes()));
  const int64_t n = b.numel();
  check_vector(b, "b", b, n, "b");
  check_vector(inverse_diagonal, "inverse_diagonal", b, n, "b");
  check_vector(step, "step", b, n, "b");
  check_vector(x_out, "x_out", b, n, "b");
  const bool with_matrix = values.has_value() && values->defined();
  const bool with_product = product.has_value() && product->defined();
  const bool with_x = x.has_value() && x->defined();
  TORCH_CHECK(!(with_matrix && with_product), "tensormass: give the matrix (values, block_cols, row_ptr) or its "
              "product, not both");
  TORCH_CHECK(with_x || !(with_matrix || with_product), "tensormass: without x (x = 0) there is no product to take: "
              "give neither the matrix nor product");
  TORCH_CHECK(!with_x || with_matrix || with_product, "tensormass: with x, give the matrix or its product A x");
  if (with_x) check_vector(*x, "x", b, n, "b");
  if (with_product) check_vector(*product, "product", b, n, "b");
  TORCH_CHECK(step.data_ptr() != x_out.data_ptr(), "tensormass: step and x_out must be different tensors");
  int64_t r = 1, c = 1, rows = n, blocks = 0;
  if (with_matrix) {
    TORCH_CHECK(block_cols.has_value() && block_cols->defined() && row_ptr.has_value() && row_ptr->defined(),
                "tensormass: the matrix needs values, block_cols and row_ptr");
    rows = check_bsr(*values, *block_cols, *row_ptr, b, "b");
    r = values->size(1);
    c = values->size(2);
    blocks = values->size(0);
    TORCH_CHECK(r == c && rows * r == n, "tensormass: the matrix must be square with b's ", std::to_string(n),
                " rows, got blocks of ", std::to_string(r), " x ", std::to_string(c), " in ", std::to_string(rows),
                " block rows");
    TORCH_CHECK(x->data_ptr() != x_out.data_ptr(), "tensormass: x_out must not be x when the matrix is given "
                "(other rows read x)");
  }
  typename L::Guard guard(b.device());
  dispatch_scalar_block(b.scalar_type(), r, c, [&](auto s_tag, auto r_c, auto c_c) {
    using S = decltype(s_tag);
    ChebyshevKernel<decltype(r_c)::value, decltype(c_c)::value, S> k;
    k.a = {with_matrix ? values->data_ptr<S>() : nullptr, with_matrix ? block_cols->data_ptr<int32_t>() : nullptr,
           with_matrix ? row_ptr->data_ptr<int32_t>() : nullptr};
    k.product = with_product ? product->data_ptr<S>() : nullptr;
    k.b = b.data_ptr<S>();
    k.inverse_diagonal = inverse_diagonal.data_ptr<S>();
    k.x = with_x ? x->data_ptr<S>() : nullptr;
    k.step = step.data_ptr<S>();
    k.x_out = x_out.data_ptr<S>();
    k.coef_a = static_cast<S>(coef_a);
    k.coef_c = static_cast<S>(coef_c);
    L::run_rows(rows, k, with_matrix ? row_group(blocks, rows) : 1);
  });
}

// multigrid_block_cholesky: see schema.cpp.
template <class L>
void multigrid_block_cholesky(const at::Tensor& blocks, at::Tensor scale, at::Tensor scale_t, at::Tensor inverse) {
  check_float(blocks, "blocks");
  TORCH_CHECK(blocks.dim() == 3 && blocks.size(1) == blocks.size(2) && (blocks.size(1) == 2 || blocks.size(1) == 3),
              "tensormass: blocks must be [n, d, d] with d 2 or 3, got ", shape_str(blocks.sizes()));
  check_node_tensor(blocks, "blocks", blocks, blocks.sizes(), "blocks");
  check_node_tensor(scale, "scale", blocks, blocks.sizes(), "blocks");
  check_node_tensor(scale_t, "scale_t", blocks, blocks.sizes(), "blocks");
  check_node_tensor(inverse, "inverse", blocks, blocks.sizes(), "blocks");
  TORCH_CHECK(scale.data_ptr() != scale_t.data_ptr() && scale.data_ptr() != inverse.data_ptr() &&
                  scale_t.data_ptr() != inverse.data_ptr() && blocks.data_ptr() != scale.data_ptr() &&
                  blocks.data_ptr() != scale_t.data_ptr() && blocks.data_ptr() != inverse.data_ptr(),
              "tensormass: blocks, scale, scale_t and inverse must be four different tensors");
  const int64_t d = blocks.size(1);
  typename L::Guard guard(blocks.device());
  dispatch_scalar(blocks.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    auto run = [&](auto d_c) {
      BlockCholeskyKernel<decltype(d_c)::value, S> k;
      k.blocks = blocks.data_ptr<S>();
      k.scale = scale.data_ptr<S>();
      k.scale_t = scale_t.data_ptr<S>();
      k.inverse = inverse.data_ptr<S>();
      k.tiny = std::numeric_limits<S>::min();
      L::run(blocks.size(0), k, L::kNodeBlock);
    };
    if (d == 3) {
      run(IC<3>{});
    } else {
      run(IC<2>{});
    }
  });
}

// The rigid transfers' shared arguments: node_inverse [V, 3, 3] or [V] (N_i = n_i I) floating and
// arm [V, 3] of its dtype and device, contiguous. Returns V.
inline int64_t check_rigid_nodes(const at::Tensor& node_inverse, const at::Tensor& arm) {
  check_float(node_inverse, "node_inverse");
  TORCH_CHECK(node_inverse.dim() == 1 || (node_inverse.dim() == 3 && node_inverse.size(1) == 3 &&
                                          node_inverse.size(2) == 3),
              "tensormass: node_inverse must be [V, 3, 3] or [V], got ", shape_str(node_inverse.sizes()));
  check_node_tensor(node_inverse, "node_inverse", node_inverse, node_inverse.sizes(), "node_inverse");
  const int64_t nodes = node_inverse.size(0);
  check_node_tensor(arm, "arm", node_inverse, {nodes, 3}, "node_inverse");
  return nodes;
}

// multigrid_rigid_restrict: see schema.cpp.
template <class L>
void multigrid_rigid_restrict(const at::Tensor& node_inverse, const at::Tensor& arm, const at::Tensor& range_ptr,
                              const at::Tensor& r, at::Tensor out) {
  const int64_t nodes = check_rigid_nodes(node_inverse, arm);
  TORCH_CHECK(range_ptr.defined() && range_ptr.dim() == 1 && range_ptr.size(0) >= 1,
              "tensormass: range_ptr must be [R + 1]");
  check_index_tensor(range_ptr, "range_ptr", node_inverse, at::kInt, {range_ptr.size(0)}, "node_inverse");
  const int64_t ranges = range_ptr.size(0) - 1;
  check_vector(r, "r", node_inverse, 3 * nodes, "node_inverse");
  check_vector(out, "out", node_inverse, 6 * ranges, "node_inverse");
  TORCH_CHECK(out.data_ptr() != r.data_ptr(), "tensormass: out must not be r");
  typename L::Guard guard(out.device());
  dispatch_scalar(out.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    RigidRestrictKernel<S> k;
    k.node_inverse = node_inverse.data_ptr<S>();
    k.scalar = node_inverse.dim() == 1;
    k.arm = arm.data_ptr<S>();
    k.range_ptr = range_ptr.data_ptr<int32_t>();
    k.r = r.data_ptr<S>();
    k.out = out.data_ptr<S>();
    L::run_rows(ranges, k, row_group(nodes, ranges));
  });
}

// multigrid_rigid_prolong: see schema.cpp.
template <class L>
void multigrid_rigid_prolong(const at::Tensor& node_inverse, const at::Tensor& arm, const at::Tensor& node_body,
                             const at::Tensor& coarse, const c10::optional<at::Tensor>& r, double weight,
                             at::Tensor out) {
  const int64_t nodes = check_rigid_nodes(node_inverse, arm);
  check_index_tensor(node_body, "node_body", node_inverse, at::kInt, {nodes}, "node_inverse");
  TORCH_CHECK(coarse.defined() && coarse.dim() == 1 && coarse.numel() % 6 == 0,
              "tensormass: coarse must be 1-D of six values a body");
  check_node_tensor(coarse, "coarse", node_inverse, {coarse.numel()}, "node_inverse");
  const bool with_r = r.has_value() && r->defined();
  if (with_r) check_vector(*r, "r", node_inverse, 3 * nodes, "node_inverse");
  check_vector(out, "out", node_inverse, 3 * nodes, "node_inverse");
  TORCH_CHECK(out.data_ptr() != coarse.data_ptr(), "tensormass: out must not be coarse");
  typename L::Guard guard(out.device());
  dispatch_scalar(out.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    RigidProlongKernel<S> k;
    k.motion = RigidMotion<S>{node_inverse.data_ptr<S>(), node_inverse.dim() == 1, arm.data_ptr<S>(),
                              node_body.data_ptr<int32_t>(), coarse.data_ptr<S>(), static_cast<S>(weight)};
    k.r = with_r ? r->data_ptr<S>() : nullptr;
    k.out = out.data_ptr<S>();
    L::run(nodes, k, L::kNodeBlock);
  });
}

// multigrid_match_clusters: see schema.cpp.
template <class L>
void multigrid_match_clusters(const at::Tensor& edge_keys, const at::Tensor& edge_ends, const at::Tensor& incident_ptr,
                              const at::Tensor& incident_edges, int64_t most, int64_t rounds, at::Tensor label,
                              at::Tensor work) {
  TORCH_CHECK(label.defined() && label.dim() == 1, "tensormass: label must be [B]");
  const int64_t nodes = label.size(0);
  check_index_tensor(label, "label", label, at::kLong, {nodes}, "label");
  TORCH_CHECK(edge_keys.defined() && edge_keys.dim() == 1, "tensormass: edge_keys must be [E]");
  const int64_t edges = edge_keys.size(0);
  check_index_tensor(edge_keys, "edge_keys", label, at::kLong, {edges}, "label");
  check_index_tensor(edge_ends, "edge_ends", label, at::kLong, {edges, 2}, "label");
  check_index_tensor(incident_ptr, "incident_ptr", label, at::kLong, {nodes + 1}, "label");
  check_index_tensor(incident_edges, "incident_edges", label, at::kLong, {2 * edges}, "label");
  check_index_tensor(work, "work", label, at::kLong, {6, nodes}, "label");
  TORCH_CHECK(most >= 1, "tensormass: most must be at least 1, got ", std::to_string(most));
  TORCH_CHECK(rounds >= 0, "tensormass: rounds must not be negative, got ", std::to_string(rounds));
  TORCH_CHECK(!label.is_same(work) && label.data_ptr() != work.data_ptr(), "tensormass: label must not be work");
  if (nodes == 0) return;
  typename L::Guard guard(label.device());
  MatchClusters m;
  m.keys = edge_keys.data_ptr<int64_t>();
  m.ends = edge_ends.data_ptr<int64_t>();
  m.incident_ptr = incident_ptr.data_ptr<int64_t>();
  m.incident_edges = incident_edges.data_ptr<int64_t>();
  m.most = most;
  m.label = label.data_ptr<int64_t>();
  int64_t* w = work.data_ptr<int64_t>();
  m.size = w;
  m.best = w + nodes;
  m.node_best = w + 2 * nodes;
  m.next = w + 3 * nodes;
  m.tail = w + 4 * nodes;
  m.merged = w + 5 * nodes;
  L::run(nodes, MatchInitKernel{m}, L::kNodeBlock);
  for (int64_t round = 0; round < rounds && edges > 0; ++round) {
    L::run(nodes, MatchNodeOfferKernel{m}, L::kNodeBlock);
    L::run(nodes, MatchClusterOfferKernel{m}, L::kNodeBlock);
    L::run(edges, MatchMergeKernel{m}, L::kNodeBlock);
    L::run(nodes, MatchRelabelKernel{m}, L::kNodeBlock);
  }
}

// Registers the implementations of the multigrid ops of one backend (launcher L) under its
// TORCH_LIBRARY_IMPL (cpu.cpp, cuda.cu); the schemas: schema.cpp.
template <class L>
void register_multigrid_ops(torch::Library& m) {
  m.impl("multigrid_bsr_gemv", &multigrid_bsr_gemv<L>);
  m.impl("multigrid_chebyshev", &multigrid_chebyshev<L>);
  m.impl("multigrid_block_cholesky", &multigrid_block_cholesky<L>);
  m.impl("multigrid_rigid_restrict", &multigrid_rigid_restrict<L>);
  m.impl("multigrid_rigid_prolong", &multigrid_rigid_prolong<L>);
  m.impl("multigrid_match_clusters", &multigrid_match_clusters<L>);
}

}  // namespace tensormass
