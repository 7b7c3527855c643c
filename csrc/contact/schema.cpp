// Schemas of the contact ops: the broad phase's candidate pairs between surface vertices and
// surface triangles (the host side: ops.h, its kernel: kernels.h; registered for the CPU and
// CUDA by cpu.cpp and cuda.cu). The conventions every op follows: library.cpp. Fake kernels: the
// Python module named below (set_python_module).
//
// Both ops take the spatial hash as tensor ops build it (tensormass_torch/ops/contact.py): the
// triangles' grown boxes listed once per covered cell, sorted by key (entry_triangle [E],
// entry_cells [E, 3]), and the queries, a (surface vertex, cell of its box) each, with the run
// [query_start, query_stop) of the entries of their key. A candidate is kept where the entry's
// cell is the query's, the boxes meet, the low corner of their intersection is in the query's
// cell (once per pair) and the bodies differ (unless same_body). Index tensors are int64; the
// caller guarantees what would cost a pass to check (ids in range, runs within the entries).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tensormass, m) {
  m.set_python_module("tensormass_torch.ops.contact");
  // contact_count_candidates(cell [1], point_low [Sv, 3], point_high [Sv, 3], vertex_object [Sv],
  //     query_vertex [Q], query_cells [Q, 3], query_start [Q], query_stop [Q],
  //     entry_triangle [E], entry_cells [E, 3], low [F, 3], high [F, 3], triangle_object [F],
  //     same_body) -> counts [Q] int64
  //   how many candidates each query keeps.
  m.def("contact_count_candidates(Tensor cell, Tensor point_low, Tensor point_high, Tensor vertex_object, "
        "Tensor query_vertex, Tensor query_cells, Tensor query_start, Tensor query_stop, Tensor entry_triangle, "
        "Tensor entry_cells, Tensor low, Tensor high, Tensor triangle_object, bool same_body) -> Tensor");
  // contact_fill_candidates(the same, offsets [Q], vertex! [C], triangle! [C]) -> ()
  //   the candidates, query q's from offsets[q] (the exclusive prefix sum of the counts; C their
  //   total) in run order: vertex (into the surface vertices) and triangle ids.
  m.def("contact_fill_candidates(Tensor cell, Tensor point_low, Tensor point_high, Tensor vertex_object, "
        "Tensor query_vertex, Tensor query_cells, Tensor query_start, Tensor query_stop, Tensor entry_triangle, "
        "Tensor entry_cells, Tensor low, Tensor high, Tensor triangle_object, bool same_body, Tensor offsets, "
        "Tensor(a!) vertex, Tensor(b!) triangle) -> ()");
}
