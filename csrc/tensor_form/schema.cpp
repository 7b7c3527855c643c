// Schemas of the tensor-form ops (the host side: ops.h, its kernels: kernels.h; registered for the
// CPU and CUDA by cpu.cpp and cuda.cu). The conventions every op follows (dtypes, index types,
// devices, gather plans): library.cpp. Fake kernels and autograd: the Python module named below
// (set_python_module), imported when torch needs them.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tensormass, m) {
  m.set_python_module("tensormass_torch.ops.tensor_form");
  // tensor_hooke_element_forces(u [V, d], edges [Ed, 2], edge_k [Ed, d, d]) -> [Ed, 2, d]
  //   kernel 1 of the hooke tensor form, one edge (i, j) an item: w = u_j - u_i, f_i = -K w,
  //   f_j = K^T w. Linear, so the differential along du is the forces of du (no dforces ops).
  m.def("tensor_hooke_element_forces(Tensor u, Tensor edges, Tensor edge_k) -> Tensor");
  // tensor_hooke_partial_forces(u, edges, force_index [Ed, 2], num_slots, edge_k)
  //   -> PartialForce [num_slots, V, d]
  //   kernel 1 in the paper's padded layout (slots >= incidences[i] left uninitialised).
  m.def("tensor_hooke_partial_forces(Tensor u, Tensor edges, Tensor force_index, int num_slots, "
        "Tensor edge_k) -> Tensor");
  // tensor_hooke_forces(u, edges, force_index, num_slots, incidences [V], edge_k) -> [V, d]
  //   kernels 1 + 2 fused: F_i = -sum_j K_ij (u_j - u_i).
  m.def("tensor_hooke_forces(Tensor u, Tensor edges, Tensor force_index, int num_slots, Tensor incidences, "
        "Tensor edge_k) -> Tensor");
  // tensor_stvk_element_forces(u [V, d], elements [N, n], tensor_b [N, n, n, d, d],
  //                            tensor_c [N, n, n, n, d], tensor_d [N, n, n, n, n]) -> [N, n, d]
  //   kernel 1 of the stvk tensor form (Picinbono's tensors B, C, D), one element an item.
  m.def("tensor_stvk_element_forces(Tensor u, Tensor elements, Tensor tensor_b, Tensor tensor_c, "
        "Tensor tensor_d) -> Tensor");
  // tensor_stvk_element_dforces(u, du [V, d], elements, tensor_b, tensor_c, tensor_d) -> [N, n, d]
  //   the force differential at u along du, per element.
  m.def("tensor_stvk_element_dforces(Tensor u, Tensor du, Tensor elements, Tensor tensor_b, Tensor tensor_c, "
        "Tensor tensor_d) -> Tensor");
  // tensor_stvk_partial_forces(u, elements, force_index [N, n], num_slots, tensor_b, tensor_c, tensor_d)
  //   -> PartialForce [num_slots, V, d]
  //   kernel 1 in the paper's padded layout (slots >= incidences[i] left uninitialised).
  m.def("tensor_stvk_partial_forces(Tensor u, Tensor elements, Tensor force_index, int num_slots, "
        "Tensor tensor_b, Tensor tensor_c, Tensor tensor_d) -> Tensor");
  // tensor_stvk_partial_dforces(u, du, elements, force_index, num_slots, tensor_b, tensor_c, tensor_d)
  //   -> PartialForce [num_slots, V, d]
  //   the same for the differential along du.
  m.def("tensor_stvk_partial_dforces(Tensor u, Tensor du, Tensor elements, Tensor force_index, int num_slots, "
        "Tensor tensor_b, Tensor tensor_c, Tensor tensor_d) -> Tensor");
  // tensor_stvk_forces(u, elements, force_index, num_slots, incidences [V], tensor_b, tensor_c, tensor_d)
  //   -> [V, d]
  //   kernels 1 + 2 fused: the total elastic force on each node.
  m.def("tensor_stvk_forces(Tensor u, Tensor elements, Tensor force_index, int num_slots, Tensor incidences, "
        "Tensor tensor_b, Tensor tensor_c, Tensor tensor_d) -> Tensor");
  // tensor_stvk_dforces(u, du, elements, force_index, num_slots, incidences, tensor_b, tensor_c, tensor_d)
  //   -> [V, d]
  //   the same for the differential along du.
  m.def("tensor_stvk_dforces(Tensor u, Tensor du, Tensor elements, Tensor force_index, int num_slots, "
        "Tensor incidences, Tensor tensor_b, Tensor tensor_c, Tensor tensor_d) -> Tensor");
}
