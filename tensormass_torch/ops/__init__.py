"""The ops layer: the paper's kernels as functions of element groups and node vectors, each
dispatched to the compiled extension (``torch.ops.tensormass.*``) or its pure-torch reference.

    forces, dforces, energy, linearize, element_forces, element_dforces, node_gather,
    node_tangent, system_matvec, system_matvec_alpha, system_cg(_serves), step_rhs(_serves)
                        the group-level calls (``dispatch``)
    native              the compiled ops: fake kernels, autograd, group-level wrappers
    cg                  the batched CG's per-iteration ops and their reference
    reference           the pure-torch reference of every kernel (the tests' oracle)
    segments            object ranges and the chunk plans of the device reductions

Layers above (physics, solver) call this one; it calls only the mesh layer and the backend.
"""
from .dispatch import (
                       dforces,
                       element_dforces,
                       element_forces,
                       energy,
                       forces,
                       linearize,
                       node_gather,
                       node_tangent,
                       step_rhs,
                       step_rhs_serves,
                       system_cg,
                       system_cg_serves,
                       system_matvec,
                       system_matvec_alpha,
)

__all__ = ["dforces", "element_dforces", "element_forces", "energy", "forces", "linearize", "node_gather",
           "node_tangent", "step_rhs", "step_rhs_serves", "system_cg", "system_cg_serves", "system_matvec",
           "system_matvec_alpha"]
