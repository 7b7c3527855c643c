// Schemas of the stress-form ops (the host side: ops.h, its kernels: kernels.h; registered for the
// CPU and CUDA by cpu.cpp and cuda.cu). The conventions every op follows (dtypes, index types,
// devices, gather plans, `model`): library.cpp. Fake kernels and autograd: the Python module named
// below (set_python_module), imported when torch needs them.
#include <torch/library.h>

TORCH_LIBRARY_FRAGMENT(tensormass, m) {
  m.set_python_module("tensormass_torch.ops.stress");
  // stress_element_forces(u [V, d], elements [N, n], shape_vectors [N, n, d], measure [N], lam [N], mu [N],
  //                       projector [N, d, d]?, model, rest_elements [N, n, 3]?, rotations [N, d, d]?)
  //   -> [N, n, d]
  //   kernel 1 at the element level: each element's elastic forces on its n nodes. Elements: tetrahedra
  //   (n = 4, d = 3), triangles (n = 3) in 2-D, or membranes (triangles in 3-D: projector, the tangent
  //   plane of each, given for membranes and only for them). rest_elements and rotations are for the
  //   corotational model (2) only: given `rotations`, the kernels read R (9 numbers per element, the CG
  //   path); otherwise they recompute SOFA's QR frame from u and `rest_elements` (3-D) at every call.
  m.def("stress_element_forces(Tensor u, Tensor elements, Tensor shape_vectors, Tensor measure, Tensor lam, "
        "Tensor mu, Tensor? projector, int model, "
        "Tensor? rest_elements=None, Tensor? rotations=None) -> Tensor");
  // stress_element_dforces(u, du [V, d], <stress_element_forces' inputs after u>) -> [N, n, d]
  //   the force differential at u along du, per element; the corotational differential holds R fixed,
  //   as SOFA does.
  m.def("stress_element_dforces(Tensor u, Tensor du, Tensor elements, Tensor shape_vectors, Tensor measure, "
        "Tensor lam, Tensor mu, Tensor? projector, int model, "
        "Tensor? rest_elements=None, Tensor? rotations=None) -> Tensor");
  // stress_partial_forces(u, elements, force_index [N, n], num_slots, <shape_vectors .. rotations>)
  //   -> PartialForce [num_slots, V, d]
  //   kernel 1 in the paper's padded layout: node v of element e writes slot force_index[e][v] of its
  //   node; the slots a node does not use (>= incidences[i]) are left uninitialised (kernel 2:
  //   gather_partial, gather/schema.cpp).
  m.def("stress_partial_forces(Tensor u, Tensor elements, Tensor force_index, int num_slots, "
        "Tensor shape_vectors, Tensor measure, Tensor lam, Tensor mu, Tensor? projector, int model, "
        "Tensor? rest_elements=None, Tensor? rotations=None) -> Tensor");
  // stress_partial_dforces(u, du, elements, force_index, num_slots, <shape_vectors .. rotations>)
  //   -> PartialForce [num_slots, V, d]
  //   the same for the differential along du.
  m.def("stress_partial_dforces(Tensor u, Tensor du, Tensor elements, Tensor force_index, int num_slots, "
        "Tensor shape_vectors, Tensor measure, Tensor lam, Tensor mu, Tensor? projector, int model, "
        "Tensor? rest_elements=None, Tensor? rotations=None) -> Tensor");
  // stress_forces(u, elements, force_index, num_slots, incidences [V], <shape_vectors .. rotations>)
  //   -> [V, d]
  //   kernels 1 + 2 fused: the total elastic force on each node.
  m.def("stress_forces(Tensor u, Tensor elements, Tensor force_index, int num_slots, Tensor incidences, "
        "Tensor shape_vectors, Tensor measure, Tensor lam, Tensor mu, Tensor? projector, int model, "
        "Tensor? rest_elements=None, Tensor? rotations=None) -> Tensor");
  // stress_dforces(u, du, elements, force_index, num_slots, incidences, <shape_vectors .. rotations>)
  //   -> [V, d]
  //   the same for the differential along du.
  m.def("stress_dforces(Tensor u, Tensor du, Tensor elements, Tensor force_index, int num_slots, "
        "Tensor incidences, Tensor shape_vectors, Tensor measure, Tensor lam, Tensor mu, Tensor? projector, "
        "int model, Tensor? rest_elements=None, Tensor? rotations=None) -> Tensor");
  // corotational_rotations(u [V, d], elements [N, n], shape_vectors [N, n, d], projector [N, d, d]?,
  //                        rest_elements [N, n, d]?, method) -> R [N, d, d]
  //   the element rotations at u, once per linearisation (the stress ops and stress_tangent_node_k read
  //   them back through `rotations`): method 0 = SOFA's QR frame (3-D only; needs rest_elements);
  //   1 = polar: the closest proper rotation to F, robust to inverted and nearly flat elements
  //   (membranes map their rest normal onto the current one: they need projector and rest_elements).
  m.def("corotational_rotations(Tensor u, Tensor elements, Tensor shape_vectors, Tensor? projector, "
        "Tensor? rest_elements, int method) -> Tensor");
}
