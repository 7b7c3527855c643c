// Schemas of the topology-change ops: element removal in place, the Tensor-Mass way (the host
// side: ops.h, its kernels: kernels.h; registered for the CPU and CUDA by cpu.cpp and cuda.cu).
// The conventions every op follows: library.cpp. Fake kernels: the Python module named below
// (set_python_module).
//
// Once elements are flagged removed, each target one of them touched is summed again from the
// elements still on it, in the order of its incidence list (node_slots, edge_slots: [S, T] model
// element ids, -1 past the last; the order in which the model assembled it): what a model built
// from the remaining elements holds, deterministic, no atomics, no sort, no allocation, no host
// synchronisation. A target left with no element holds exactly 0. The caller guarantees what
// would cost a pass to check: rows in range, the lists those of the model's elements.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tensormass, m) {
  m.set_python_module("tensormass_torch.ops.topology");
  // topology_refresh_nodes(elements [N, n], rows [R], node_slots [S, V], element_share [N_model],
  //                        removed [N_model] bool, mass! [V], node_elements! [V] int32) -> ()
  //   each node of the elements at rows: mass = the sum of element_share (an element's mass over
  //   its node count) of its listed elements not removed, node_elements = their number.
  m.def("topology_refresh_nodes(Tensor elements, Tensor rows, Tensor node_slots, Tensor element_share, "
        "Tensor removed, Tensor(a!) mass, Tensor(b!) node_elements) -> ()");
  // topology_refresh_hooke_edges(rest [V, d], elements [N, n], rows [R], element_edges [N, P],
  //                              edge_slots [S, Ed], element_row [N_model], removed [N_model] bool,
  //                              measure [N], young [N], poisson [N], edge_k! [Ed, d, d]) -> ()
  //   each edge of the elements at rows (element_edges: the edge of each local pair a < b) of a
  //   hooke tensor-form group: edge_k = the sum of the Cotin tensors of its listed elements not
  //   removed (element_row: their rows), formed again from rest (shape vectors, the membrane's
  //   projector, plane-stress Lame constants for triangles), stored from the lower to the higher
  //   node.
  m.def("topology_refresh_hooke_edges(Tensor rest, Tensor elements, Tensor rows, Tensor element_edges, "
        "Tensor edge_slots, Tensor element_row, Tensor removed, Tensor measure, Tensor young, Tensor poisson, "
        "Tensor(a!) edge_k) -> ()");
}
