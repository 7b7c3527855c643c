// The tensormass torch library and the Python module tensormass_torch._C.
//
// TORCH_LIBRARY(tensormass) is claimed here and defines nothing: each family of ops has a folder
// with its schemas (schema.cpp: a TORCH_LIBRARY_FRAGMENT that documents each op beside its schema
// and names the Python module of its fake kernels and autograd, tensormass_torch.ops.<family>,
// which torch imports when it needs them: set_python_module), its host side (ops.h, templated on
// a launcher), its per-item kernels (kernels.h) and its CPU and CUDA registrations (cpu.cpp,
// cuda.cu):
//   stress/       the stress form: element forces and differentials, the corotational rotations
//   tensor_form/  the tensor form (hooke on edges, stvk on elements): forces and differentials
//   gather/       kernel 2 (each node's sum of its slots) alone and as the CG matvec's epilogue
//   node_graph/   the node graph: its CG matvec in one kernel, implicit Euler's right-hand side,
//                 a stress-form group's tangent as the graph's slot tensors, edges written again
//                 after a removal
//   cg/           the CG iteration's ops over the chunk plan, the end of an implicit Euler step
//   solve/        whole CG solves over the node graph in one op
//   topology/     element removal in place: the touched nodes' masses and hooke edges summed again
// What several families share (checks, compile-time dispatch, element math, kernel loads and
// writes, the shared kernels, the CPU and CUDA launchers, the CG's scalar logic): common/.
//
// Conventions: u, du [V, d] (float32 or float64, one dtype for all floating inputs); index tensors
// (elements, edges, force_index, incidences) all int32 or all int64; every input contiguous and on
// one device. `model`: 0 = hooke, 1 = stvk, 2 = corotational, 3 = stvk with a definite tangent
// (stress/schema.cpp). A plan (force_index, num_slots, incidences) must come from
// topology.GatherPlan over the same items: force_index < num_slots and the slots of a node are
// 0 .. incidences[i]-1 (not re-checked here: it would cost a pass).
#include <pybind11/pybind11.h>
#include <torch/library.h>

TORCH_LIBRARY(tensormass, m) {}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.doc() = "tensormass_torch._C: Tensor-Mass element kernels (the ops live in torch.ops.tensormass)";
  m.def("has_cuda", []() {
#ifdef TENSORMASS_WITH_CUDA
    return true;
#else
    return false;
#endif
  }, "Whether the extension was built with its CUDA kernels.");
}
