// Schemas of the cutting ops. Host algorithms registered for the CPU only (cpu.cpp), which the
// simulator calls on host copies whatever device it runs on, and the cut on the device (the last
// three, registered for the CPU and CUDA: kernels.h, device_ops.h). cutting_cut_mesh: the whole of
// mesh.cutting.cut (the faces a blade crosses part, their nodes split; ops.h);
// cutting_edit_element_tables and cutting_edit_edge_tables: the integer tables a cut in place
// edits (tables.h). The conventions every op follows: library.cpp. Fake kernels: the Python module
// named below (set_python_module).
//
// cutting_cut_mesh's reference is tensormass_torch.mesh.cutting.cut (tensormass_torch.ops.cutting's
// OpDef wraps it in this signature); the op computes the same elements, parents, pairs and slit,
// bit for bit: the centroids, cross products, norms and dot products are evaluated in the order
// torch's CPU kernels evaluate them, with fused multiply-adds where those kernels fuse (ops.h asks
// them once).
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tensormass, m) {
  m.set_python_module("tensormass_torch.ops.cutting");
  // cutting_cut_mesh(elements [N, n], alive [N] bool, x [V, 3], blade_vertices [B, 3],
  //                  blade_triangles [T, 3] int64, slit [S, 2] int64)
  //     -> (elements [N, n], parents [V_new] int64, first [C] int64, second [C] int64,
  //         slit [S', 2] int64)
  //   elements: tetrahedra (n = 4) or membrane triangles (n = 3), int32 or int64, node ids in
  //   [0, V) for every alive element; x: the positions the blade cuts at (float32 or float64),
  //   blade_vertices of x's dtype; slit: element pairs parted by earlier cuts that still share their
  //   face (the previous call's slit output), rows in [0, N).
  //   1. The interior faces of the alive elements (n - 1 nodes shared by two of them) whose
  //      centroid-to-centroid segment crosses a blade triangle (Moller-Trumbore, as
  //      mesh.cutting._segments_cross): first < second, ordered by the face's sorted node ids.
  //   2. pairs = (first, second) rows, then the slit rows whose two elements are alive.
  //   3. Around each node of a face a pair shares (pairs sharing no face are ignored), its alive
  //      elements fall into groups joined through the faces holding the node that two alive
  //      elements share and that are no pair; the group of the node's first element keeps it,
  //      every other group gets a new node, numbered from V on in the order (node, the group's
  //      first element): elements re-pointed, parents = arange(V) then each new node's original.
  //   4. slit = the pairs whose elements still share a face after the split.
  //   No face crossed (C = 0): nothing is split (elements copied, parents = arange(V)) and slit is
  //   the alive slit rows that share a face; the Python caller raises there.
  //   A face is taken to be held by at most two alive elements (as in any conforming tetrahedral
  //   mesh or manifold membrane): where more hold one, the reference pairs consecutive owners among
  //   the elements it looks at, which this op may choose otherwise.
  m.def("cutting_cut_mesh(Tensor elements, Tensor alive, Tensor x, Tensor blade_vertices, Tensor blade_triangles, "
        "Tensor slit) -> (Tensor, Tensor, Tensor, Tensor, Tensor)");

  // The integer tables a cut in place edits (TensorMass.repoint_elements: elements ids [M], one
  // group's, re-pointed to nodes [M, n]), planned on the host: one group's elements [N, n], its
  // gather plan (force_index [items, w], incidences [V], and its lists node_items [S, V]: slot s of
  // node i holds the item row w + a whose force_index is s, -1 past the last; S = the plan's
  // num_slots) and the model's lists node_slots [S', V] (model element ids, -1 past the last),
  // edited in place as the reference (tensormass_torch.ops.cutting) edits them, bit for bit; the
  // results are what the caller sends to the device. Index tensors all of the elements' index
  // type (int32 or int64) but ids (int64, the model ids of the rows); host tensors (CPU only).
  // rows [M]: the group's rows of ids, unique; a node id that changes must be one no alive element
  // holds (a cut's new node, which takes the elements of one node).
  //
  // cutting_edit_element_tables(elements! [N, n], force_index! [N, n], incidences! [V],
  //                             node_items! [S, V], node_slots! [S', V], rows [M], ids [M] int64,
  //                             nodes [M, n])
  //     -> (incidence_nodes [K] int64, incidences [K], items [J] int64, force_index [J],
  //         slot_nodes [C] int64, node_slot_lists [S', C], both [2M, n])
  //   A group whose plan's items are its elements (w = n: the stress forms, the stvk tensor form):
  //   each entry (m, a) whose node changes leaves the old node's lists (node_items and node_slots,
  //   each list packed in order) and joins the new node's after the items there, in row-major
  //   order; force_index and incidences follow, elements[rows] = nodes. Returns the nodes whose
  //   incidences changed and their incidences now, the items whose force_index changed and it now,
  //   the node_slots columns changed and their lists now, and cat(the rows before, nodes).
  m.def("cutting_edit_element_tables(Tensor(a!) elements, Tensor(b!) force_index, Tensor(c!) incidences, "
        "Tensor(d!) node_items, Tensor(e!) node_slots, Tensor rows, Tensor ids, Tensor nodes) "
        "-> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)");
  // cutting_edit_edge_tables(elements! [N, n], force_index! [Ed, 2], incidences! [V],
  //                          node_items! [S, V], node_slots! [S', V], edges! [Ed, 2],
  //                          edge_slots! [Se, Ed], element_edges! [N, P], rows [M], ids [M] int64,
  //                          nodes [M, n], element_row [N_model], removed [N_model] bool,
  //                          int edge_rows_used)
  //     -> (status [3] int64, refresh_rows [R], dead [D] int64, graph_edges [G],
  //         incidence_nodes [K] int64, incidences [K], items [J] int64, force_index [J],
  //         slot_edges [L] int64, edge_slot_lists [Se, L], edge_rows [Q] int64, edge_values [Q, 2],
  //         element_edges [M, P], slot_nodes [C] int64, node_slot_lists [S', C], both [2M, n])
  //   A hooke tensor-form group, whose plan's items are its edges (w = 2; edge_slots: each edge's
  //   model element ids in the order its tensor was summed; element_edges: the edge of each local
  //   pair a < b; the edge rows past edge_rows_used: the pool of zero edges (0, 0) in the sink
  //   slot S - 1 that new edges take). A pair of the rows with a changed node moves: its new edge
  //   (lower, higher node) is a new edge row, the new edges sorted by (lower, higher) and taking
  //   the pool's first rows (their elements listed in the pairs' order); an old edge keeps the
  //   elements that stay, and one left with no alive element (removed: the model's flags) leaves
  //   its nodes' lists (a zero edge (0, 0) in the sink slot, its row kept); node_items, force_index
  //   and incidences follow (new edges' items appended at both ends), node_slots as above.
  //   First the room: status = (need, new edges, edited): need is the most edges of any node after
  //   the cut; where need > S - 1 (a plan without room: the caller raises) or the pool holds fewer
  //   than the new edges (the caller grows it and calls again) nothing is written, edited = 0, and
  //   the other results are empty. Else (edited = 1) the rows whose edges are summed again (the
  //   cut's and, for each old edge the moved pairs left that keeps an alive element, the row of
  //   its first one: element_row), the emptied edges, the edges whose node-graph entries change
  //   (those of the items whose slots moved and those of the rows summed again), the incidences
  //   and items changed as above, the edge_slots columns changed (the old edges left, then the new
  //   rows) and their lists, the edge rows written (the new, then the emptied) and their values,
  //   the rows' element_edges now, node_slots as above and cat(the rows before, nodes).
  m.def("cutting_edit_edge_tables(Tensor(a!) elements, Tensor(b!) force_index, Tensor(c!) incidences, "
        "Tensor(d!) node_items, Tensor(e!) node_slots, Tensor(f!) edges, Tensor(g!) edge_slots, "
        "Tensor(h!) element_edges, Tensor rows, Tensor ids, Tensor nodes, Tensor element_row, Tensor removed, "
        "int edge_rows_used) -> (Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, Tensor, "
        "Tensor, Tensor, Tensor, Tensor, Tensor, Tensor)");

  // The cut on the device: the cut of cutting_cut_mesh (and of its reference) made of fixed-size
  // passes over preallocated tables, with no allocation and no host synchronisation (kernels.h
  // says how, and what the tables hold). Elements are tetrahedra [N, 4] or membrane triangles
  // [N, 3]; index tensors of the elements' type (int32 or int64) but where said.
  //
  // cutting_cross_faces(x [V, 3], elements [N, n], face_elements [F, 2], alive [N] bool,
  //                     blade_vertices [B, 3], blade_triangles [T, 3] int64, parted! [F] bool,
  //                     crossed! [F] bool) -> ()
  //   crossed[f] = the two elements of face f are alive, still share it (n - 1 nodes) and the
  //   segment between their centroids at x crosses a blade triangle; parted[f] |= crossed[f].
  m.def("cutting_cross_faces(Tensor x, Tensor elements, Tensor face_elements, Tensor alive, Tensor blade_vertices, "
        "Tensor blade_triangles, Tensor(a!) parted, Tensor(b!) crossed) -> ()");
  // cutting_split_stars(elements [N, n], node_slots [S, V], alive [N] bool, element_faces [N, n],
  //                     face_elements [F, 2], parted [F] bool, crossed [F] bool, recheck! [F] bool,
  //                     group! [S, V] int32, new_count! [V] int32, on_cut! [V] uint8) -> ()
  //   node_slots: each node's elements (ids into elements), -1 past the last, S <= 64. For each
  //   node held by a parted face that is still shared and that this blade crossed or recheck
  //   names (recheck: the parted faces no cut examined yet, cleared on return; the nodes of
  //   other parted faces cannot split: their stars did not change): its alive elements grouped through the
  //   faces holding it that are joined (shared, not parted, both alive), the groups ranked by
  //   their smallest element id; group[s, i] = rank * n + the node's local index in its s-th
  //   element (-1 for a removed element and past the last), new_count[i] = groups - 1 (on_cut[i]
  //   = 1). Every other node: new_count 0, on_cut 0, group -1.
  m.def("cutting_split_stars(Tensor elements, Tensor node_slots, Tensor alive, Tensor element_faces, "
        "Tensor face_elements, Tensor parted, Tensor crossed, Tensor(d!) recheck, Tensor(a!) group, "
        "Tensor(b!) new_count, Tensor(c!) on_cut) -> ()");
  // cutting_repoint_stars(node_slots [S, V], group [S, V] int32, new_count [V] int32,
  //                       offset [V] int64, limits [2] int64, elements! [N, n], parents! [P] int64)
  //     -> ()
  //   offset: the exclusive prefix sum of new_count; limits = (the first new node's id, the room:
  //   how many new nodes fit). The elements of rank r >= 1 at node i get the node
  //   limits[0] + offset[i] + r - 1, and parents of that node = i. Where the new nodes do not fit
  //   (their total over room, or past P) nothing is written.
  m.def("cutting_repoint_stars(Tensor node_slots, Tensor group, Tensor new_count, Tensor offset, Tensor limits, "
        "Tensor(a!) elements, Tensor(b!) parents) -> ()");
  // cutting_move_lists(elements [N, n], group [S, V] int32, new_count [V] int32, offset [V] int64,
  //                    limits [2] int64, parents [P] int64, element_share [N], alive [N] bool,
  //                    node_slots! [S, V], mass! [V], node_elements! [V] int32, touched! [V] uint8)
  //     -> ()
  //   After cutting_repoint_stars (the same group, new_count, offset, limits, parents; elements as
  //   it left them), where the cut was made: each split node's list keeps its elements of rank 0
  //   and its removed ones, each copy's (empty) list gets the elements of its rank, in order; the
  //   mass of the node and its copies = the sum of element_share over their alive elements in list
  //   order, node_elements = their number; touched = 1 at every node of their elements (the rest
  //   of touched as it was: the caller zeroes it).
  m.def("cutting_move_lists(Tensor elements, Tensor group, Tensor new_count, Tensor offset, Tensor limits, "
        "Tensor parents, Tensor element_share, Tensor alive, Tensor(a!) node_slots, Tensor(b!) mass, "
        "Tensor(c!) node_elements, Tensor(d!) touched) -> ()");
  // cutting_copy_rows(rows [2] int64, parents [P] int64, max_rows, values! [P', ...]) -> ()
  //   rows = (first, count), count <= max_rows: values[first + r] = values[parents[first + r]] for
  //   r < count, row by row, byte for byte (any dtype): the state of the new nodes a cut made,
  //   copied from their parents'. max_rows bounds the launch (the most new nodes a cut can add).
  m.def("cutting_copy_rows(Tensor rows, Tensor parents, int max_rows, Tensor(a!) values) -> ()");
  // cutting_count_new_nodes(ends [V + 1] int64, limits [2] int64, rows! [2] int64, status! [1] int32) -> ()
  //   After the new nodes are numbered (ends: 0, then the inclusive prefix sum of new_count), with
  //   total = ends[V]: rows = (limits[0], total where total <= limits[1], else 0) (the rows
  //   cutting_copy_rows fills), and status = 1 where total > limits[1] (else as it was).
  m.def("cutting_count_new_nodes(Tensor ends, Tensor limits, Tensor(a!) rows, Tensor(b!) status) -> ()");
  // cutting_close_cut(rows [2] int64, incidences [V] int32, chunk_start [C + 1] int64, chunk_slots,
  //                   limits! [2] int64, status! [1] int32, outcome! [2] int64) -> ()
  //   The end of a cut: status = 1 where a chunk of nodes [chunk_start[c], chunk_start[c + 1])
  //   holds more than chunk_slots slots (the sum of their incidences; C may be 0); then limits =
  //   (limits[0] + rows[1], limits[1] - rows[1]) and outcome = (limits[0], status) (after).
  m.def("cutting_close_cut(Tensor rows, Tensor incidences, Tensor chunk_start, int chunk_slots, "
        "Tensor(a!) limits, Tensor(b!) status, Tensor(c!) outcome) -> ()");
}
