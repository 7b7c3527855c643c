// Schemas of the gather ops: kernel 2 of the paper's Algorithm 1, alone and with the implicit-Euler
// system epilogue (the host side: ops.h, its kernels: kernels.h and common/gather.h; registered for
// the CPU and CUDA by cpu.cpp and cuda.cu). The conventions every op follows (dtypes, index types,
// devices, gather plans): library.cpp; the chunk plan of the CG: cg/schema.cpp. Fake kernels and
// autograd: the Python module named below (set_python_module), imported when torch needs them.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tensormass, m) {
  m.set_python_module("tensormass_torch.ops.gather");
  // gather_partial(partial [N_n, V, d], incidences [V], node_term [V, d]?) -> [V, d]
  //   kernel 2 alone: each node's used slots (s < incidences[i]) summed in slot order, plus node_term
  //   when given.
  m.def("gather_partial(Tensor partial, Tensor incidences, Tensor? node_term) -> Tensor");
  // node_gather(partial [N, n, d], index [N, n], force_index [N, n], num_slots, incidences [V],
  //             node_term [V, d]?) -> [V, d]
  //   kernel 2 on compact partial forces (of elements, n = 3 or 4, or edges, n = 2): scattered into the
  //   padded layout through the plan (force_index, num_slots) at the nodes `index`, then summed per
  //   node as gather_partial does.
  m.def("node_gather(Tensor partial, Tensor index, Tensor force_index, int num_slots, Tensor incidences, "
        "Tensor? node_term) -> Tensor");
  // gather_system(partial [N_n, V, d], incidences [V], p [V, d], mass [V], free [V]?, c_mass, c_stiff,
  //               node_stiffness [V, d, d]?) -> (Ap [V, d], p . Ap per node [V])
  //   kernel 2 with the implicit-Euler system epilogue, the CG matvec from the partial force
  //   differentials along p: Ap = free (c_mass mass p - c_stiff K p), where (K p)_i = the sum of node
  //   i's slots - node_stiffness_i p_i (node_stiffness: the hooke tensor form's vertex term K_ii,
  //   contact penalties). Not differentiable.
  m.def("gather_system(Tensor partial, Tensor incidences, Tensor p, Tensor mass, Tensor? free, float c_mass, "
        "float c_stiff, Tensor? node_stiffness=None) -> (Tensor, Tensor)");
  // gather_system_alpha(<gather_system's inputs>, ap!, chunk_start, chunk_object, object_chunk, rr,
  //                     status!, alpha!, scratch!, counter!) -> ()
  //   gather_system's Ap into ap [V, d] in place, then each object's step length as cg_alpha
  //   (cg/schema.cpp) computes it, in the same kernel (one block per chunk): one launch fewer per CG
  //   iteration. Objects that are not active are skipped. In place, so that a CUDA graph replays it.
  m.def("gather_system_alpha(Tensor partial, Tensor incidences, Tensor p, Tensor mass, Tensor? free, "
        "float c_mass, float c_stiff, Tensor? node_stiffness, Tensor(a!) ap, Tensor chunk_start, "
        "Tensor chunk_object, Tensor object_chunk, Tensor rr, Tensor(b!) status, Tensor(c!) alpha, "
        "Tensor(d!) scratch, Tensor(e!) counter) -> ()");
}
