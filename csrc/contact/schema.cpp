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
  //     query_vertex [Q], query_cells [Q, 3], query_start [Q], query_stop [Q], query_order [Q],
  //     entry_triangle [E], entry_cells [E, 3], low [F, 3], high [F, 3], triangle_object [F],
  //     same_body, triangle_first [B + 1]?) -> counts [Q] int64
  //   how many candidates each query keeps. query_order: a permutation of the queries, the order
  //   the kernel takes them in (by run: the lanes that walk one run share its loads); it changes
  //   no output. triangle_first (or None): the triangles are in body order, body b's from
  //   triangle_first[b] to triangle_first[b + 1] - 1, and each run lists its entries in triangle
  //   order; a query then skips its own body's entries (unless same_body): no output changes.
  m.def("contact_count_candidates(Tensor cell, Tensor point_low, Tensor point_high, Tensor vertex_object, "
        "Tensor query_vertex, Tensor query_cells, Tensor query_start, Tensor query_stop, Tensor query_order, "
        "Tensor entry_triangle, Tensor entry_cells, Tensor low, Tensor high, Tensor triangle_object, bool same_body, "
        "Tensor? triangle_first) -> Tensor");
  // contact_fill_candidates(the same, triangle_first?, offsets [Q], vertex! [C], triangle! [C]) -> ()
  //   the candidates, query q's from offsets[q] (the exclusive prefix sum of the counts; C their
  //   total) in run order: vertex (into the surface vertices) and triangle ids.
  m.def("contact_fill_candidates(Tensor cell, Tensor point_low, Tensor point_high, Tensor vertex_object, "
        "Tensor query_vertex, Tensor query_cells, Tensor query_start, Tensor query_stop, Tensor query_order, "
        "Tensor entry_triangle, Tensor entry_cells, Tensor low, Tensor high, Tensor triangle_object, bool same_body, "
        "Tensor? triangle_first, Tensor offsets, Tensor(a!) vertex, Tensor(b!) triangle) -> ()");
  // The narrow phase (body_contact.SurfaceContact.nearby). For each surface vertex s (node
  // vertices[s], body vertex_object[s]) over its run of candidate triangles
  // candidate_triangle[first[s]:first[s + 1]] (the broad phase's, grouped by vertex), and each
  // other body: the nearest triangle within the reach (with spread [V] and body_step [B, 3]: the
  // reach grows by spread at the vertex, the triangle's largest spread and |body_step[a] -
  // body_step[b]|), the lowest triangle id among those tied with it within 32 eps (max |p| +
  // reach), and its side by the sum of the tied triangles' normals; a pair within that rounding of
  // the plain reach or past it (with spread) is kept only outside (a triangle tied with it may
  // lie past the limit).
  // contact_count_nearest(x [V, 3], vertices [Sv], vertex_object [Sv], triangles [F, 3],
  //     triangle_object [F], first [Sv + 1], candidate_triangle [C], spread [V]?, body_step [B, 3]?,
  //     reach) -> (counts [Sv] int64, chosen [Sv] int64)
  //   how many pairs each vertex keeps; -1 where a vertex is near more bodies than the kernel holds
  //   (kernels.h: kNearestSlots; the caller then takes the reference). chosen: -1 where it keeps
  //   none (or is past the slots), 2 i + (1 if outside) where it keeps one pair, its chosen
  //   candidate candidate_triangle[i], -2 where it keeps more; for the fill.
  m.def("contact_count_nearest(Tensor x, Tensor vertices, Tensor vertex_object, Tensor triangles, "
        "Tensor triangle_object, Tensor first, Tensor candidate_triangle, Tensor? spread, Tensor? body_step, "
        "float reach) -> (Tensor, Tensor)");
  // contact_fill_nearest(the same, offsets [Sv], chosen [Sv], pair_vertex! [P], pair_triangle! [P],
  //     weights! [P, 3], diff! [P, 3], distance! [P], normal! [P, 3], side! [P]) -> ()
  //   the pairs, vertex s's from offsets[s] in the order of their chosen candidates: the vertex
  //   (into vertices), the triangle, the closest point's weights, p minus it, its distance, the
  //   triangle's unit normal and the side (+-1). chosen: the count's, for the same inputs.
  m.def("contact_fill_nearest(Tensor x, Tensor vertices, Tensor vertex_object, Tensor triangles, "
        "Tensor triangle_object, Tensor first, Tensor candidate_triangle, Tensor? spread, Tensor? body_step, "
        "float reach, Tensor offsets, Tensor chosen, Tensor(a!) pair_vertex, Tensor(b!) pair_triangle, "
        "Tensor(c!) weights, Tensor(d!) diff, Tensor(e!) distance, Tensor(f!) normal, Tensor(g!) side) -> ()");
  // contact_pair_product(dx [V, 3], nodes [C, 4], coef [C, 4], direction [C, 3], normal [C],
  //     friction [C], order [4 C], offsets [V + 1], vector! [C, 3], out! [V, 3], accumulate) -> ()
  //   the pairs' part of the step's matrix times dx (body_contact.PairStiffness): per pair
  //   vector = b J dx + (a - b) (u . J dx) u (a = normal, b = friction, u = direction, J dx =
  //   sum_i coef_i dx[node_i]); out[v] = the sum of coef_i vector over node v's entries, in the
  //   order order[offsets[v]:offsets[v + 1]] lists them (4 c + i); with accumulate, out[v] plus that
  //   sum (a node with no entry left as it is: the pairs' product added to another's in place,
  //   with no pass of its own). vector is scratch.
  m.def("contact_pair_product(Tensor dx, Tensor nodes, Tensor coef, Tensor direction, Tensor normal, "
        "Tensor friction, Tensor order, Tensor offsets, Tensor(a!) vector, Tensor(b!) out, "
        "bool accumulate=False) -> ()");
}
