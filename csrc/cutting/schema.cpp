// Schema of the mesh-cutting op: the whole of mesh.cutting.cut (the faces a blade crosses part, their
// nodes split) as one host algorithm (ops.h; registered for the CPU only by cpu.cpp: the simulator
// calls it on host copies of the mesh and positions, whatever device it runs on). The conventions
// every op follows: library.cpp. Fake kernel: the Python module named below (set_python_module).
//
// Its reference is tensormass_torch.mesh.cutting.cut (tensormass_torch.ops.cutting's OpDef wraps it
// in this signature); the op computes the same elements, parents, pairs and slit, bit for bit: the
// centroids, cross products, norms and dot products are evaluated in the order torch's CPU kernels
// evaluate them, with fused multiply-adds where those kernels fuse (ops.h asks them once).
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
}
