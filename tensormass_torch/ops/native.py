"""Group-level calls onto the compiled ops: what ``tensormass_torch.ops`` (``dispatch``) runs
when the extension serves a group. Each call picks the op of the group's form and model across
the families (``stress``, ``tensor_form``, ``gather``, ``node_graph``) and feeds it the group's
tensors; the ops' definitions (references, fake kernels, autograd) live in those family modules.

    element_forces, element_dforces     kernel 1 at element level                 [N, n, d]
    forces, dforces                     kernels 1 + 2 fused                        [V, d]
    system_matvec                       implicit Euler's CG product (Ap, p . Ap)
    system_matvec_alpha                 the same ending in the CG step length (in place)

Whole solves and the step's right-hand side: ``ops.solve`` and ``ops.node_graph``.
"""
from __future__ import annotations

from typing import Optional

import torch

from .gather import system_epilogue
from .library import contiguous, plan_indices, supports, wants_grad
from .node_graph import _zeros_like_nodes, node_graph_of
from .stress import corotational_rotations, stress_args
from .tensor_form import stvk_tensors
from .variants import DEFAULT, KernelVariants

__all__ = ["supports", "corotational_rotations", "element_forces", "element_dforces", "forces", "dforces",
           "system_fusable", "system_matvec", "system_matvec_alpha"]


def element_forces(group, u: torch.Tensor, rotations: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Kernel 1 at element level: ``[N, n, d]`` (edges ``[Ed, 2, d]`` for the hooke tensor form).

    ``rotations``: the corotational rotations the forces take ``[N, d, d]`` (those at ``u``,
    computed here, when None).
    """
    u = u.contiguous()
    index, _, _ = plan_indices(group.plan)
    if group.form == "stress":
        return torch.ops.tensormass.stress_element_forces(u, index, *stress_args(group, u, rotations))
    if group.model == "hooke":
        return torch.ops.tensormass.tensor_hooke_element_forces(u, index, group.edge_k.contiguous())
    return torch.ops.tensormass.tensor_stvk_element_forces(u, index, *stvk_tensors(group))


def element_dforces(group, u: torch.Tensor, du: torch.Tensor, rotations: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Kernel 1 with DForce() at element level: ``[N, n, d]``; ``rotations`` as in :func:`element_forces`."""
    u, du = u.contiguous(), du.contiguous()
    index, _, _ = plan_indices(group.plan)
    if group.form == "stress":
        return torch.ops.tensormass.stress_element_dforces(u, du, index, *stress_args(group, u, rotations))
    if group.model == "hooke":
        return torch.ops.tensormass.tensor_hooke_element_forces(du, index, group.edge_k.contiguous())
    return torch.ops.tensormass.tensor_stvk_element_dforces(u, du, index, *stvk_tensors(group))


def forces(group, u: torch.Tensor, rotations: Optional[torch.Tensor] = None,
           variants: KernelVariants = DEFAULT) -> torch.Tensor:
    """Fused kernels 1 + 2: elastic forces ``[V, d]``; ``rotations`` as in :func:`element_forces`;
    the hooke tensor form over its node graph where ``variants.hooke_matvec`` is "node"."""
    u = u.contiguous()
    plan = group.plan
    index, force_index, incidences = plan_indices(plan)
    if group.form == "stress":
        return torch.ops.tensormass.stress_forces(u, index, force_index, plan.num_slots, incidences,
                                                  *stress_args(group, u, rotations))
    if group.model == "hooke":
        graph = node_graph_of(group, variants, (u,), "hooke_node_system")
        if graph is not None:
            # one kernel over the node graph (the system op with c_M = 0, c_K = -1 returns K u = the
            # forces, bitwise the padded gather's sums); not differentiable, hence the condition
            no_mass = _zeros_like_nodes(group, u)
            return torch.ops.tensormass.hooke_node_system(u, *graph, no_mass, None, 0.0, -1.0, None)[0]
        return torch.ops.tensormass.tensor_hooke_forces(u, index, force_index, plan.num_slots, incidences,
                                                        group.edge_k.contiguous())
    return torch.ops.tensormass.tensor_stvk_forces(u, index, force_index, plan.num_slots, incidences,
                                                   *stvk_tensors(group))


def dforces(group, u: torch.Tensor, du: torch.Tensor, rotations: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Fused kernels 1 + 2 with DForce(): (dF/du) du ``[V, d]``; ``rotations``: the corotational
    rotations of the linearisation at ``u`` ``[N, d, d]`` (computed here when None)."""
    u, du = u.contiguous(), du.contiguous()
    plan = group.plan
    index, force_index, incidences = plan_indices(plan)
    if group.form == "stress":
        return torch.ops.tensormass.stress_dforces(u, du, index, force_index, plan.num_slots,
                                                   incidences, *stress_args(group, u, rotations))
    if group.model == "hooke":
        return torch.ops.tensormass.tensor_hooke_forces(du, index, force_index, plan.num_slots, incidences,
                                                        group.edge_k.contiguous())
    return torch.ops.tensormass.tensor_stvk_dforces(u, du, index, force_index, plan.num_slots,
                                                    incidences, *stvk_tensors(group))


def system_fusable(group) -> bool:
    """Whether :func:`system_matvec` has a fused path for ``group``: kernel 1 through a padded
    partial-dforce op (stress form, both tensor forms)."""
    return hasattr(torch.ops.tensormass, "gather_system") and group.form in ("stress", "tensor")


def _partial_dforces(group, u: torch.Tensor, p: torch.Tensor, rotations: Optional[torch.Tensor]):
    """Kernel 1 of the CG product: the padded partial force differentials along ``p``
    (PartialForce ``[N_n, V, d]``) and the plan's incidences ``[V]``."""
    plan = group.plan
    index, force_index, incidences = plan_indices(plan)
    if group.form == "stress":
        partial = torch.ops.tensormass.stress_partial_dforces(u, p, index, force_index, plan.num_slots,
                                                              *stress_args(group, u, rotations))
    elif group.model == "hooke":  # linear: the partial forces of p are its partial dforces
        partial = torch.ops.tensormass.tensor_hooke_partial_forces(p, index, force_index, plan.num_slots,
                                                                   group.edge_k.contiguous())
    else:
        partial = torch.ops.tensormass.tensor_stvk_partial_dforces(u, p, index, force_index, plan.num_slots,
                                                                   *stvk_tensors(group))
    return partial, incidences


def system_matvec(group, u: torch.Tensor, p: torch.Tensor, mass: torch.Tensor, free: Optional[torch.Tensor],
                  c_mass: float, c_stiff: float, rotations: Optional[torch.Tensor] = None,
                  node_stiffness: Optional[torch.Tensor] = None, node_k: Optional[torch.Tensor] = None,
                  variants: KernelVariants = DEFAULT):
    """The CG matvec of implicit Euler for one group: kernel 1 (padded partial dforces along ``p``)
    and kernel 2 with the system epilogue (``gather_system``); for the hooke tensor form with
    ``variants.hooke_matvec`` "node" (the default) and no gradient wanted, one kernel over the node
    graph instead (``hooke_node_system``, bitwise the same result). ``mass`` and
    ``free`` are ``[V]`` (``free`` float 0/1 or None); ``rotations``: the corotational rotations of
    the linearisation at ``u`` ``[N, d, d]``, kept across CG iterations (computed here when None);
    ``node_stiffness`` ``[V, d, d]`` (contact penalties) or None; ``node_k``: the tangent of a
    stress-form group at u on its node graph (``node_graph.tangent_node_k``), then the product runs
    over that graph (``hooke_node_system``). Returns (Ap ``[V, d]``, p . Ap per node ``[V]``)."""
    u, p, mass, free, node_stiffness = contiguous(u, p, mass, free, node_stiffness)
    graph = node_graph_of(group, variants, (p, mass, free, node_stiffness), "hooke_node_system", node_k)
    if graph is not None:
        return torch.ops.tensormass.hooke_node_system(p, *graph, mass, free, float(c_mass), float(c_stiff),
                                                      node_stiffness)
    partial, incidences = _partial_dforces(group, u, p, rotations)
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad
                                       for t in (partial, p, mass, free, node_stiffness)):
        # gather_system has no gradient: the same arithmetic in differentiable ops
        kp = torch.ops.tensormass.gather_partial(partial, incidences, None)
        return system_epilogue(kp, p, mass, free, c_mass, c_stiff, node_stiffness)
    return torch.ops.tensormass.gather_system(partial, incidences, p, mass, free, float(c_mass), float(c_stiff),
                                              node_stiffness)


def system_matvec_alpha(group, u: torch.Tensor, p: torch.Tensor, mass: torch.Tensor, free: Optional[torch.Tensor],
                        c_mass: float, c_stiff: float, rotations: Optional[torch.Tensor],
                        node_stiffness: Optional[torch.Tensor], ap: torch.Tensor, plan_tensors, cg_state,
                        node_k: Optional[torch.Tensor] = None, variants: KernelVariants = DEFAULT,
                        add=None) -> bool:
    """:func:`system_matvec` fused with the CG step length (``gather_system_alpha`` /
    ``hooke_node_system_alpha``): Ap into ``ap [V, d]`` in place and ``cg_state.alpha`` /
    ``.status`` as ``cg_alpha`` would set them, one launch fewer per CG iteration. ``plan_tensors``:
    (chunk_start, chunk_object, object_chunk) of the CG's chunk plan; ``cg_state``: its
    ``CGState``; ``node_k``: as in :func:`system_matvec`. ``add``: a function returning another
    product's rows ``[V, d]`` to add to Ap (projected likewise) before the step length, called
    only where the fused path runs (the node graph's op; the gather path takes none), or None.
    Returns False (nothing done, ``add`` not called) where the ops are missing or a gradient is
    wanted."""
    ops_ns = torch.ops.tensormass
    if not hasattr(ops_ns, "gather_system_alpha") or wants_grad((p, mass, free, node_stiffness)):
        return False
    u, p, mass, free, node_stiffness = contiguous(u, p, mass, free, node_stiffness)
    s = cg_state
    cg_args = (*plan_tensors, s.rr, s.status, s.alpha, s.scratch, s.counter)
    if node_k is not None or (group.form == "tensor" and group.model == "hooke" and variants.hooke_matvec == "node"):
        graph = node_graph_of(group, variants, (), "hooke_node_system_alpha", node_k)
        if graph is None:
            return False
        added = None if add is None else add().contiguous()
        ops_ns.hooke_node_system_alpha(p, *graph, mass, free, float(c_mass), float(c_stiff), node_stiffness, ap,
                                       *cg_args, added)
        return True
    if add is not None:
        return False
    partial, incidences = _partial_dforces(group, u, p, rotations)
    if wants_grad((partial,)):
        return False
    ops_ns.gather_system_alpha(partial, incidences, p, mass, free, float(c_mass), float(c_stiff), node_stiffness, ap,
                               *cg_args)
    return True
