// Host side of the cut on the device (schemas: schema.cpp; kernels: kernels.h), written once for
// the CPU and CUDA: argument checks, dispatch and one launch through `L` (common/cpu_launcher.h,
// common/cuda_launcher.cuh). No allocation and no host synchronisation: a cut between captured
// steps, or inside one, is three launches and a prefix sum.
#pragma once

#include <ATen/core/Tensor.h>
#include <torch/library.h>

#include <algorithm>
#include <cstdint>
#include <limits>
#include <string>

#include "common/checks.h"
#include "common/dispatch.h"
#include "cutting/kernels.h"

namespace tensormass {
namespace cutting {

inline int64_t element_nodes(const at::Tensor& elements) {
  TORCH_CHECK(elements.defined() && elements.dim() == 2 && (elements.size(1) == 3 || elements.size(1) == 4),
              "tensormass: elements must be [N, 4] (tetrahedra) or [N, 3] (membrane triangles), got ",
              elements.defined() ? shape_str(elements.sizes()) : std::string("undefined"));
  return elements.size(1);
}

// The passes over a node's star hold it in one thread's memory: at most kMaxStar slots.
inline void check_star_slots(const at::Tensor& node_slots) {
  TORCH_CHECK(node_slots.size(0) <= kMaxStar, "tensormass: node_slots has ", std::to_string(node_slots.size(0)),
              " slots; a node may hold at most ", std::to_string(kMaxStar), " elements for the cut on the device");
}

template <class F>
void dispatch_element_nodes(int64_t nn, F&& f) {
  if (nn == 4) {
    f(IC<4>{});
  } else {
    f(IC<3>{});
  }
}

// cutting_cross_faces: see schema.cpp.
template <class L>
void cutting_cross_faces(const at::Tensor& x, const at::Tensor& elements, const at::Tensor& face_elements,
                         const at::Tensor& alive, const at::Tensor& blade_vertices,
                         const at::Tensor& blade_triangles, at::Tensor parted, at::Tensor crossed) {
  check_values(x, "x");
  TORCH_CHECK(x.size(1) == 3, "tensormass: x must be [V, 3], got ", shape_str(x.sizes()));
  const int64_t nn = element_nodes(elements);
  const at::ScalarType index_type = index_type_of(elements, "elements");
  check_index_tensor(elements, "elements", x, index_type, elements.sizes(), "x");
  TORCH_CHECK(face_elements.defined() && face_elements.dim() == 2 && face_elements.size(1) == 2,
              "tensormass: face_elements must be [F, 2]");
  check_index_tensor(face_elements, "face_elements", x, index_type, face_elements.sizes(), "x");
  const int64_t num_faces = face_elements.size(0);
  check_flags(alive, "alive", x, elements.size(0), "x");
  TORCH_CHECK(blade_vertices.defined() && blade_vertices.dim() == 2 && blade_vertices.size(1) == 3 &&
                  blade_vertices.size(0) >= 1,
              "tensormass: blade_vertices must be [B >= 1, 3]");
  check_float_tensor(blade_vertices, "blade_vertices", x, blade_vertices.sizes());
  TORCH_CHECK(blade_triangles.defined() && blade_triangles.dim() == 2 && blade_triangles.size(1) == 3,
              "tensormass: blade_triangles must be [T, 3]");
  check_index_tensor(blade_triangles, "blade_triangles", x, at::kLong, blade_triangles.sizes(), "x");
  check_flags(parted, "parted", x, num_faces, "x");
  check_flags(crossed, "crossed", x, num_faces, "x");
  typename L::Guard guard(x.device());
  dispatch_scalar(x.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_element_nodes(nn, [&](auto nn_c) {
        constexpr int NN = decltype(nn_c)::value;
        CrossFacesKernel<NN, S, I> k;
        k.x = x.data_ptr<S>();
        k.elements = elements.data_ptr<I>();
        k.face_elements = face_elements.data_ptr<I>();
        k.alive = alive.data_ptr<bool>();
        k.blade_vertices = blade_vertices.data_ptr<S>();
        k.num_blade_vertices = blade_vertices.size(0);
        k.blade_triangles = blade_triangles.data_ptr<int64_t>();
        k.num_triangles = blade_triangles.size(0);
        k.eps = std::numeric_limits<S>::epsilon();
        k.parted = parted.data_ptr<bool>();
        k.crossed = crossed.data_ptr<bool>();
        L::run(num_faces, k, L::kElementBlock);
      });
    });
  });
}

// cutting_split_stars: see schema.cpp. Three launches: the nodes of parted faces marked, the joins
// of their stars' elements found, then their stars split (every other node only writes -1s and
// new_count = 0).
template <class L>
void cutting_split_stars(const at::Tensor& elements, const at::Tensor& node_slots, const at::Tensor& alive,
                         const at::Tensor& element_faces, const at::Tensor& face_elements, const at::Tensor& parted,
                         const at::Tensor& crossed, at::Tensor recheck, at::Tensor group, at::Tensor new_count,
                         at::Tensor on_cut) {
  const int64_t nn = element_nodes(elements);
  const at::ScalarType index_type = index_type_of(elements, "elements");
  TORCH_CHECK(elements.is_contiguous(), "tensormass: elements must be contiguous (call .contiguous())");
  TORCH_CHECK(node_slots.defined() && node_slots.dim() == 2, "tensormass: node_slots must be [S, V]");
  check_index_tensor(node_slots, "node_slots", elements, index_type, node_slots.sizes(), "elements");
  check_star_slots(node_slots);
  const int64_t num_nodes = node_slots.size(1);
  check_flags(alive, "alive", elements, elements.size(0), "elements");
  check_index_tensor(element_faces, "element_faces", elements, index_type, elements.sizes(), "elements");
  TORCH_CHECK(face_elements.defined() && face_elements.dim() == 2 && face_elements.size(1) == 2,
              "tensormass: face_elements must be [F, 2]");
  check_index_tensor(face_elements, "face_elements", elements, index_type, face_elements.sizes(), "elements");
  check_flags(parted, "parted", elements, face_elements.size(0), "elements");
  check_flags(crossed, "crossed", elements, face_elements.size(0), "elements");
  check_flags(recheck, "recheck", elements, face_elements.size(0), "elements");
  check_index_tensor(group, "group", elements, at::kInt, node_slots.sizes(), "elements");
  check_index_tensor(new_count, "new_count", elements, at::kInt, {num_nodes}, "elements");
  check_index_tensor(on_cut, "on_cut", elements, at::kByte, {num_nodes}, "elements");
  typename L::Guard guard(elements.device());
  on_cut.zero_();
  dispatch_index(index_type, [&](auto i_tag) {
    using I = decltype(i_tag);
    dispatch_element_nodes(nn, [&](auto nn_c) {
      constexpr int NN = decltype(nn_c)::value;
      MarkCutNodesKernel<NN, I> mark;
      mark.elements = elements.data_ptr<I>();
      mark.face_elements = face_elements.data_ptr<I>();
      mark.alive = alive.data_ptr<bool>();
      mark.parted = parted.data_ptr<bool>();
      mark.crossed = crossed.data_ptr<bool>();
      mark.recheck = recheck.data_ptr<bool>();
      mark.on_cut = on_cut.data_ptr<uint8_t>();
      L::run(face_elements.size(0), mark, L::kNodeBlock);
      StarJoinsKernel<NN, I> joins;
      joins.elements = elements.data_ptr<I>();
      joins.node_slots = node_slots.data_ptr<I>();
      joins.num_slots = node_slots.size(0);
      joins.num_nodes = num_nodes;
      joins.alive = alive.data_ptr<bool>();
      joins.element_faces = element_faces.data_ptr<I>();
      joins.face_elements = face_elements.data_ptr<I>();
      joins.parted = parted.data_ptr<bool>();
      joins.on_cut = on_cut.data_ptr<uint8_t>();
      joins.group = group.data_ptr<int32_t>();
      L::run(node_slots.numel(), joins, L::kNodeBlock);
      SplitStarsKernel<NN, I> k;
      k.node_slots = node_slots.data_ptr<I>();
      k.num_slots = node_slots.size(0);
      k.num_nodes = num_nodes;
      k.on_cut = on_cut.data_ptr<uint8_t>();
      k.group = group.data_ptr<int32_t>();
      k.new_count = new_count.data_ptr<int32_t>();
      L::run(num_nodes, k, L::kNodeBlock);
    });
  });
}

// cutting_repoint_stars: see schema.cpp.
template <class L>
void cutting_repoint_stars(const at::Tensor& node_slots, const at::Tensor& group, const at::Tensor& new_count,
                           const at::Tensor& offset, const at::Tensor& limits, at::Tensor elements,
                           at::Tensor parents) {
  const int64_t nn = element_nodes(elements);
  const at::ScalarType index_type = index_type_of(elements, "elements");
  TORCH_CHECK(elements.is_contiguous(), "tensormass: elements must be contiguous (call .contiguous())");
  TORCH_CHECK(node_slots.defined() && node_slots.dim() == 2, "tensormass: node_slots must be [S, V]");
  check_index_tensor(node_slots, "node_slots", elements, index_type, node_slots.sizes(), "elements");
  check_star_slots(node_slots);
  const int64_t num_nodes = node_slots.size(1);
  TORCH_CHECK(num_nodes >= 1, "tensormass: node_slots must have at least one node");
  check_index_tensor(group, "group", elements, at::kInt, node_slots.sizes(), "elements");
  check_index_tensor(new_count, "new_count", elements, at::kInt, {num_nodes}, "elements");
  check_index_tensor(offset, "offset", elements, at::kLong, {num_nodes}, "elements");
  check_index_tensor(limits, "limits", elements, at::kLong, {2}, "elements");
  TORCH_CHECK(parents.defined() && parents.dim() == 1, "tensormass: parents must be [P]");
  check_index_tensor(parents, "parents", elements, at::kLong, parents.sizes(), "elements");
  typename L::Guard guard(elements.device());
  dispatch_index(index_type, [&](auto i_tag) {
    using I = decltype(i_tag);
    dispatch_element_nodes(nn, [&](auto nn_c) {
      constexpr int NN = decltype(nn_c)::value;
      RepointStarsKernel<NN, I> k;
      k.node_slots = node_slots.data_ptr<I>();
      k.num_slots = node_slots.size(0);
      k.num_nodes = num_nodes;
      k.group = group.data_ptr<int32_t>();
      k.new_count = new_count.data_ptr<int32_t>();
      k.offset = offset.data_ptr<int64_t>();
      k.limits = limits.data_ptr<int64_t>();
      k.elements = elements.data_ptr<I>();
      k.parents = parents.data_ptr<int64_t>();
      k.num_parents = parents.size(0);
      L::run(num_nodes, k, L::kNodeBlock);
    });
  });
}

// cutting_move_lists: see schema.cpp.
template <class L>
void cutting_move_lists(const at::Tensor& elements, const at::Tensor& group, const at::Tensor& new_count,
                        const at::Tensor& offset, const at::Tensor& limits, const at::Tensor& parents,
                        const at::Tensor& element_share, const at::Tensor& alive, at::Tensor node_slots,
                        at::Tensor mass, at::Tensor node_elements, at::Tensor touched) {
  const int64_t nn = element_nodes(elements);
  const at::ScalarType index_type = index_type_of(elements, "elements");
  TORCH_CHECK(elements.is_contiguous(), "tensormass: elements must be contiguous (call .contiguous())");
  TORCH_CHECK(node_slots.defined() && node_slots.dim() == 2, "tensormass: node_slots must be [S, V]");
  check_index_tensor(node_slots, "node_slots", elements, index_type, node_slots.sizes(), "elements");
  check_star_slots(node_slots);
  const int64_t num_nodes = node_slots.size(1);
  TORCH_CHECK(num_nodes >= 1, "tensormass: node_slots must have at least one node");
  check_index_tensor(group, "group", elements, at::kInt, node_slots.sizes(), "elements");
  check_index_tensor(new_count, "new_count", elements, at::kInt, {num_nodes}, "elements");
  check_index_tensor(offset, "offset", elements, at::kLong, {num_nodes}, "elements");
  check_index_tensor(limits, "limits", elements, at::kLong, {2}, "elements");
  TORCH_CHECK(parents.defined() && parents.dim() == 1, "tensormass: parents must be [P]");
  check_index_tensor(parents, "parents", elements, at::kLong, parents.sizes(), "elements");
  TORCH_CHECK(mass.defined() && mass.dim() == 1 && mass.size(0) == num_nodes, "tensormass: mass must be [V] (",
              std::to_string(num_nodes), " nodes: node_slots' columns)");
  TORCH_CHECK(mass.scalar_type() == at::kFloat || mass.scalar_type() == at::kDouble,
              "tensormass: mass must be float32 or float64, got ", dtype_str(mass.scalar_type()));
  TORCH_CHECK(mass.device() == elements.device() && mass.is_contiguous(),
              "tensormass: mass must be a contiguous tensor on elements' device");
  TORCH_CHECK(element_share.defined() && element_share.dim() == 1 && element_share.size(0) == elements.size(0),
              "tensormass: element_share must be [N] (", std::to_string(elements.size(0)), " elements)");
  check_float_tensor(element_share, "element_share", mass, element_share.sizes());
  check_flags(alive, "alive", elements, elements.size(0), "elements");
  check_index_tensor(node_elements, "node_elements", elements, at::kInt, {num_nodes}, "elements");
  check_index_tensor(touched, "touched", elements, at::kByte, {num_nodes}, "elements");
  typename L::Guard guard(elements.device());
  dispatch_scalar(mass.scalar_type(), [&](auto s_tag) {
    using S = decltype(s_tag);
    dispatch_index(index_type, [&](auto i_tag) {
      using I = decltype(i_tag);
      dispatch_element_nodes(nn, [&](auto nn_c) {
        constexpr int NN = decltype(nn_c)::value;
        MoveListsKernel<NN, S, I> k;
        k.elements = elements.data_ptr<I>();
        k.group = group.data_ptr<int32_t>();
        k.new_count = new_count.data_ptr<int32_t>();
        k.offset = offset.data_ptr<int64_t>();
        k.limits = limits.data_ptr<int64_t>();
        k.num_parents = parents.size(0);
        k.element_share = element_share.data_ptr<S>();
        k.alive = alive.data_ptr<bool>();
        k.node_slots = node_slots.data_ptr<I>();
        k.num_slots = node_slots.size(0);
        k.num_nodes = num_nodes;
        k.mass = mass.data_ptr<S>();
        k.node_elements = node_elements.data_ptr<int32_t>();
        k.touched = touched.data_ptr<uint8_t>();
        L::run(num_nodes, k, L::kNodeBlock);
      });
    });
  });
}

// cutting_copy_rows: see schema.cpp.
template <class L>
void cutting_copy_rows(const at::Tensor& rows, const at::Tensor& parents, int64_t max_rows, at::Tensor values) {
  TORCH_CHECK(values.defined() && values.dim() >= 1 && values.is_contiguous(),
              "tensormass: values must be a contiguous tensor of node rows [P', ...]");
  check_index_tensor(rows, "rows", values, at::kLong, {2}, "values");
  TORCH_CHECK(parents.defined() && parents.dim() == 1, "tensormass: parents must be [P]");
  check_index_tensor(parents, "parents", values, at::kLong, parents.sizes(), "values");
  TORCH_CHECK(values.size(0) >= parents.size(0), "tensormass: values has ", std::to_string(values.size(0)),
              " rows; it needs one per parents entry (", std::to_string(parents.size(0)), ")");
  TORCH_CHECK(max_rows >= 0 && max_rows <= parents.size(0), "tensormass: max_rows is ", std::to_string(max_rows),
              "; it must be in [0, ", std::to_string(parents.size(0)), "]");
  const int64_t row_bytes = values.numel() / std::max<int64_t>(values.size(0), 1) * values.element_size();
  if (row_bytes == 0) return;
  typename L::Guard guard(values.device());
  CopyRowsKernel k;
  k.rows = rows.data_ptr<int64_t>();
  k.parents = parents.data_ptr<int64_t>();
  k.row_bytes = row_bytes;
  k.values = static_cast<uint8_t*>(values.data_ptr());
  L::run(max_rows * row_bytes, k, L::kNodeBlock);
}

// cutting_count_new_nodes: see schema.cpp.
template <class L>
void cutting_count_new_nodes(const at::Tensor& ends, const at::Tensor& limits, at::Tensor rows, at::Tensor status) {
  TORCH_CHECK(ends.defined() && ends.dim() == 1 && ends.size(0) >= 1, "tensormass: ends must be [V + 1]");
  check_index_tensor(ends, "ends", ends, at::kLong, ends.sizes(), "ends");
  check_index_tensor(limits, "limits", ends, at::kLong, {2}, "ends");
  check_index_tensor(rows, "rows", ends, at::kLong, {2}, "ends");
  check_index_tensor(status, "status", ends, at::kInt, {1}, "ends");
  typename L::Guard guard(ends.device());
  CountNewNodesKernel k;
  k.ends = ends.data_ptr<int64_t>();
  k.num_nodes = ends.size(0) - 1;
  k.limits = limits.data_ptr<int64_t>();
  k.rows = rows.data_ptr<int64_t>();
  k.status = status.data_ptr<int32_t>();
  L::run(1, k, 1);
}

// cutting_close_cut: see schema.cpp. Two launches: the chunks checked, then the cut closed.
template <class L>
void cutting_close_cut(const at::Tensor& rows, const at::Tensor& incidences, const at::Tensor& chunk_start,
                       int64_t chunk_slots, at::Tensor limits, at::Tensor status, at::Tensor outcome) {
  TORCH_CHECK(incidences.defined() && incidences.dim() == 1, "tensormass: incidences must be [V]");
  check_index_tensor(incidences, "incidences", incidences, at::kInt, incidences.sizes(), "incidences");
  check_index_tensor(rows, "rows", incidences, at::kLong, {2}, "incidences");
  TORCH_CHECK(chunk_start.defined() && chunk_start.dim() == 1 && chunk_start.size(0) >= 1,
              "tensormass: chunk_start must be [C + 1]");
  check_index_tensor(chunk_start, "chunk_start", incidences, at::kLong, chunk_start.sizes(), "incidences");
  check_index_tensor(limits, "limits", incidences, at::kLong, {2}, "incidences");
  check_index_tensor(status, "status", incidences, at::kInt, {1}, "incidences");
  check_index_tensor(outcome, "outcome", incidences, at::kLong, {2}, "incidences");
  typename L::Guard guard(incidences.device());
  CheckChunksKernel check;
  check.incidences = incidences.data_ptr<int32_t>();
  check.chunk_start = chunk_start.data_ptr<int64_t>();
  check.chunk_slots = chunk_slots;
  check.status = status.data_ptr<int32_t>();
  L::run(chunk_start.size(0) - 1, check, L::kNodeBlock);
  CloseCutKernel close;
  close.rows = rows.data_ptr<int64_t>();
  close.limits = limits.data_ptr<int64_t>();
  close.status = status.data_ptr<int32_t>();
  close.outcome = outcome.data_ptr<int64_t>();
  L::run(1, close, 1);
}

// Registers the device cut's ops of one backend (launcher L): cpu.cpp and cuda.cu.
template <class L>
void register_device_cutting_ops(torch::Library& m) {
  m.impl("cutting_cross_faces", &cutting_cross_faces<L>);
  m.impl("cutting_split_stars", &cutting_split_stars<L>);
  m.impl("cutting_repoint_stars", &cutting_repoint_stars<L>);
  m.impl("cutting_move_lists", &cutting_move_lists<L>);
  m.impl("cutting_copy_rows", &cutting_copy_rows<L>);
  m.impl("cutting_count_new_nodes", &cutting_count_new_nodes<L>);
  m.impl("cutting_close_cut", &cutting_close_cut<L>);
}

}  // namespace cutting
}  // namespace tensormass
