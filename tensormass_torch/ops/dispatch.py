"""Ops: the paper's kernels as functions, dispatched to the extension or the pure-torch reference.

    element_forces(group, u)        kernel 1: partial forces of each item  [N, n, d]
    node_gather(partial, plan, t)   kernel 2: per-node sums                 [V, d]
    forces(group, u)                kernel 1 + kernel 2                     [V, d]
    dforces(group, u, du)           the same pair with DForce(): (dF/du) du [V, d]
    energy(group, u)                elastic energy                          scalar
    linearize(group, u)             per-element state of dforces at u (the corotational
                                    rotations [N, d, d]; None for the other models)
    system_matvec(groups, u, p, ...) implicit-Euler CG matvec: (Ap [V, d], p . Ap per node [V])
    system_matvec_alpha(...)        the same into a buffer, ending in the CG step length (fused)
    system_cg(...)                  a whole CG solve of that system in one op, where there is one
    step_rhs(...)                   implicit Euler's right-hand side in one op, where there is one

``u`` and ``du`` are global nodal displacements ``[V, d]``.

Dispatch: when ``_backend.use_extension(u.device)`` is true (the compiled extension is loaded,
built for that device type, not forced off by ``TENSORMASS_BACKEND=torch``) and the group's data
has u's dtype (float32/float64) and device, the compiled ops ``torch.ops.tensormass.*`` run
(``ops.native`` composes them per group; the op families ``ops.stress``, ``ops.tensor_form``,
``ops.gather``, ``ops.node_graph``, ``ops.cg``, ``ops.solve`` define them); otherwise the
pure-torch reference. ``variants`` (``ops.variants.KernelVariants``) picks among equivalent
kernels; the solver passes its ``StepOptions.variants``. Both paths are differentiable: the
reference through autograd (double backward included), the ops through their registered
autograd (first order everywhere; second order where the backward formulas are themselves ops
with autograd, e.g. the energy Hessian of the hooke tensor form). ``energy`` always runs the
reference (the hooke tensor form through ``forces``).
"""
from __future__ import annotations

from typing import Optional

import torch

from .. import _backend
from ..mesh.topology import GatherPlan
from . import library
from .reference import corotational, stress_form, tensor_form
from .reference import gather as ref_gather
from .variants import DEFAULT, KernelVariants


def _element_values(group, u):
    return u[group.elements]


def linearize(group, u: torch.Tensor) -> Optional[torch.Tensor]:
    """What ``dforces`` at ``u`` can reuse across calls: the corotational rotations ``[N, d, d]``
    (computed once per implicit step, not per CG iteration); None for the other models.

    Through the extension's ``corotational_rotations`` op when it serves the group, else the
    reference below (both: ``group.rotation`` "qr" = SOFA's frame, "polar" = closest rotation).
    """
    if group.model != "corotational":
        return None
    native = _native(group, u)
    if native is not None:
        return native.corotational_rotations(group, u)
    u_e = _element_values(group, u)
    if group.rotation == "qr":
        return corotational.qr_rotations(group.rest_elements + u_e, group.rest_elements)
    F = corotational.deformation_gradient(u_e, group.shape_vectors, group.projector)
    if not group.membrane:
        return corotational.polar_rotations(F)
    x_e = group.rest_elements + u_e  # a membrane's F maps its plane only: map the normals too
    normal = torch.linalg.cross(x_e[:, 1] - x_e[:, 0], x_e[:, 2] - x_e[:, 0])
    normal = normal / torch.linalg.vector_norm(normal, dim=1, keepdim=True)
    return corotational.polar_rotations(F, group.rest_normals, normal)


def node_tangent(group, u: torch.Tensor, state: Optional[torch.Tensor] = None,
                 out: Optional[torch.Tensor] = None, variants: KernelVariants = DEFAULT) -> Optional[torch.Tensor]:
    """The force differential of ``group`` at displacements ``u [V, d]`` as the slot tensors of
    its node graph (``node_graph.tangent_node_k``: once per linearisation; the CG products then run
    over the graph instead of recomputing each element's differential), into ``out`` when it
    fits; ``state``: ``linearize(group, u)``. None where that does not serve (not a stress-form
    stvk or corotational group, the pure-torch backend, a gradient wanted, or
    ``variants.node_tangent`` off): the products then run element by element."""
    if _native(group, u) is None:
        return None
    from . import node_graph

    if not node_graph.tangent_serves(group, u, variants=variants):
        return None
    return node_graph.tangent_node_k(group, u, state, out, variants)


def _native(group, u: torch.Tensor):
    """The module of the compiled ops when they should evaluate ``group`` at ``u``, else None."""
    if not _backend.use_extension(u.device):
        return None
    if not library.ensure_registered() or not library.supports(group, u):
        return None
    from . import native

    return native


def _native_gather(partial: torch.Tensor, plan: GatherPlan, node_term):
    """The module of the compiled ops when they should run this gather, else None."""
    if (partial.dtype not in (torch.float32, torch.float64) or partial.dim() != 3
            or partial.shape[1] not in (2, 3, 4) or partial.shape[2] not in (2, 3)
            or plan.index.device != partial.device
            or (node_term is not None and (node_term.dtype != partial.dtype or node_term.device != partial.device))
            or not _backend.use_extension(partial.device)):
        return None
    if not library.ensure_registered():
        return None
    from . import gather

    return gather


def element_forces(group, u: torch.Tensor, state: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Kernel 1: partial forces ``[N, n, d]`` of every item of ``group`` at displacements ``u [V, d]``.

    ``state``: the corotational rotations the forces take ``[N, d, d]`` (normally ``linearize(group,
    u)``, which None computes here); the forces are then affine in u."""
    native = _native(group, u)
    if native is not None:  # corotational: R at u from the rotations op, then the force op with it
        return native.element_forces(group, u, state)
    if group.model == "corotational":
        lam, mu = group.lame()
        return corotational.forces(_element_values(group, u), group.shape_vectors, group.measure, lam, mu,
                                   linearize(group, u) if state is None else state, group.projector)
    if group.form == "stress":
        lam, mu = group.lame()
        element_forces_of = stress_form.FORCES[stress_form.kernel_model(group)]
        return element_forces_of(_element_values(group, u), group.shape_vectors, group.measure, lam, mu,
                                 group.projector)
    if group.model == "hooke":
        return tensor_form.hooke_edge_partial_forces(u, group.edges, group.edge_k)
    return tensor_form.stvk_forces(_element_values(group, u), group.tensor_b, group.tensor_c, group.tensor_d)


def element_dforces(group, u: torch.Tensor, du: torch.Tensor, state: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Kernel 1 with DForce(): partial force differentials ``[N, n, d]`` along ``du [V, d]``.

    ``state``: ``linearize(group, u)`` when the caller keeps it across calls (None: computed here).
    """
    native = _native(group, u)
    if native is not None:
        return native.element_dforces(group, u, du, linearize(group, u) if state is None else state)
    if group.model == "corotational":
        lam, mu = group.lame()
        rotations = linearize(group, u) if state is None else state
        return corotational.dforces(_element_values(group, du), group.shape_vectors, group.measure, lam, mu,
                                    rotations, group.projector)
    if group.form == "stress":
        lam, mu = group.lame()
        element_dforces_of = stress_form.DFORCES[stress_form.kernel_model(group)]
        return element_dforces_of(_element_values(group, u), _element_values(group, du), group.shape_vectors,
                                  group.measure, lam, mu, group.projector)
    if group.model == "hooke":
        return tensor_form.hooke_edge_partial_forces(du, group.edges, group.edge_k)
    return tensor_form.stvk_dforces(_element_values(group, u), _element_values(group, du),
                                    group.tensor_b, group.tensor_c, group.tensor_d)


def node_gather(partial: torch.Tensor, plan: GatherPlan, node_term: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Kernel 2: ``[N, n, d]`` partial forces -> ``[V, d]`` totals (+ ``node_term [V, d]``)."""
    native = _native_gather(partial, plan, node_term)
    if native is not None:
        return native.node_gather(partial, plan, node_term)
    return ref_gather.node_gather(partial, plan.index, plan.force_index, plan.num_slots, plan.num_nodes, node_term)


def forces(group, u: torch.Tensor, state: Optional[torch.Tensor] = None,
           variants: KernelVariants = DEFAULT) -> torch.Tensor:
    """Elastic forces of the group on every node ``[V, d]``; ``state``: as :func:`element_forces`
    (``linearize(group, u)`` when the caller has it: then not computed again)."""
    native = _native(group, u)
    if native is not None:  # corotational: as element_forces
        return native.forces(group, u, state, variants)
    return node_gather(element_forces(group, u, state), group.plan)


def dforces(group, u: torch.Tensor, du: torch.Tensor, state: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(dF/du) du on every node ``[V, d]``: the matrix-free product with the stiffness.

    ``state``: ``linearize(group, u)``, reused across calls at the same ``u`` (corotational).
    """
    native = _native(group, u)
    if native is not None:
        return native.dforces(group, u, du, linearize(group, u) if state is None else state)
    return node_gather(element_dforces(group, u, du, state), group.plan)


def energy(group, u: torch.Tensor) -> torch.Tensor:
    """Elastic energy of the group (0-dim tensor); corotational: with the rotations at u held fixed."""
    if group.model == "corotational":
        lam, mu = group.lame()
        return corotational.energy(_element_values(group, u), group.shape_vectors, group.measure, lam, mu,
                                   linearize(group, u).detach(), group.projector).sum()
    if group.form == "stress":
        lam, mu = group.lame()
        element_energies_of = stress_form.ENERGIES[stress_form.kernel_model(group)]
        return element_energies_of(_element_values(group, u), group.shape_vectors, group.measure, lam, mu,
                                   group.projector).sum()
    if group.model == "hooke":  # W = 1/2 u^T K u = -1/2 u . F(u)
        return -0.5 * (u * forces(group, u)).sum()
    return tensor_form.stvk_energy(_element_values(group, u), group.tensor_b, group.tensor_c, group.tensor_d).sum()


def _tangent_of(tangents) -> Optional[torch.Tensor]:
    """The one group's node-graph tangent of ``tangents`` (``[node_tangent(g, u) for g in
    groups]``, or None): what the fused paths (one group) read."""
    return None if tangents is None else tangents[0]


def _fused_native(groups, u: torch.Tensor, p: torch.Tensor, node_tensors):
    """The native module when the system matvec of ``groups`` has a fused path: one group the
    extension serves with a fused matvec, p like u, and every node tensor (``[V, ...]`` or None)
    of u's dtype and device; else None."""
    if len(groups) != 1 or p.dtype != u.dtype or p.device != u.device or p.shape != u.shape:
        return None
    native = _native(groups[0], u)
    if native is None or not native.system_fusable(groups[0]):
        return None
    if not all(t is None or (t.dtype == u.dtype and t.device == u.device and t.shape[0] == u.shape[0])
               for t in node_tensors):
        return None
    return native


def system_matvec(groups, u: torch.Tensor, p: torch.Tensor, mass: torch.Tensor, free: Optional[torch.Tensor],
                  c_mass: float, c_stiff: float, states=None, node_stiffness: Optional[torch.Tensor] = None,
                  tangents=None, variants: KernelVariants = DEFAULT):
    """The CG matvec of implicit Euler, ``A p = c_mass M p - c_stiff K p`` projected on the free nodes.

    Args:
        groups: the model's element groups (``TensorMass.groups``); K p = sum of their ``dforces``.
        u: displacements ``[V, d]`` (positions minus rest) where K is evaluated; p: ``[V, d]``.
        mass: lumped masses ``[V]`` or ``[V, 1]``; free: ``[V]`` or ``[V, 1]`` float 0/1 mask, or None.
        states: ``[linearize(g, u) for g in groups]`` kept by the caller across CG iterations (the
            corotational rotations ``[N, d, d]``, read by the kernels as they are), or None
            (computed here).
        node_stiffness: ``[V, d, d]`` stiffness acting on each node alone (contact penalties k n n^T),
            subtracted from K p: ``(K p)_i -= node_stiffness_i p_i``; or None.
        tangents: ``[node_tangent(g, u) for g in groups]`` kept by the caller (the differential on
            the node graph: the product then runs over it), or None (element by element).
        variants: the kernel variants (``KernelVariants``).
    Returns:
        (Ap ``[V, d]``, p . Ap per node ``[V]``) with ``Ap_i = free_i (c_mass m_i p_i - c_stiff (K p)_i)``.

    Fused (kernel 1 = the group's padded partial-dforce op, kernel 2 = ``gather_system`` with the
    mass term, subtraction, projection and per-node dot in its epilogue) when there is exactly one
    group and the extension has its partial-dforce op for that device (every form: the hooke tensor
    form included) and mass/free share p's dtype and device;
    otherwise the composed reference below.
    """
    groups = list(groups)
    mass_v = mass.reshape(-1)
    free_v = None if free is None else free.reshape(-1)
    native = _fused_native(groups, u, p, (mass_v, free_v, node_stiffness))
    if native is not None:
        state = linearize(groups[0], u) if states is None else states[0]
        return native.system_matvec(groups[0], u, p, mass_v, free_v, c_mass, c_stiff, state, node_stiffness,
                                    node_k=_tangent_of(tangents), variants=variants)
    kp = None
    for i, group in enumerate(groups):
        f = dforces(group, u, p, None if states is None else states[i])
        kp = f if kp is None else kp + f
    if node_stiffness is not None:
        kp = kp - torch.einsum("vab,vb->va", node_stiffness, p)
    ap = (c_mass * mass_v.unsqueeze(-1)) * p - c_stiff * kp
    if free_v is not None:
        ap = ap * free_v.unsqueeze(-1)
    return ap, (p * ap).sum(-1)


def system_matvec_alpha(groups, u: torch.Tensor, p: torch.Tensor, mass: torch.Tensor, free: Optional[torch.Tensor],
                        c_mass: float, c_stiff: float, states, node_stiffness: Optional[torch.Tensor],
                        ap: torch.Tensor, plan, cg_state, tangents=None, variants: KernelVariants = DEFAULT,
                        add=None) -> bool:
    """:func:`system_matvec` fused with the CG step length where the extension has it: A p into
    ``ap [V, d]`` (in place) and, per object of the CG's chunk ``plan`` (``ChunkPlan``),
    ``cg_state.alpha`` and ``.status`` exactly as ``solver.cg_ops.cg_alpha`` sets them (one
    kernel instead of two per CG iteration; objects that stopped are skipped). ``add``: a
    function returning another product's rows ``[V, d]`` added to A p before the step length
    (``native.system_matvec_alpha``), or None. Returns False, having done nothing, where there is
    no fused path (several groups, the pure-torch backend, a gradient wanted): then the caller
    runs :func:`system_matvec` and ``cg_alpha``."""
    groups = list(groups)
    mass_v = mass.reshape(-1)
    free_v = None if free is None else free.reshape(-1)
    native = _fused_native(groups, u, p, (mass_v, free_v, node_stiffness, ap))
    if native is None:
        return False
    state = linearize(groups[0], u) if states is None else states[0]
    return native.system_matvec_alpha(groups[0], u, p, mass_v, free_v, c_mass, c_stiff, state, node_stiffness, ap,
                                      plan.tensors(), cg_state, node_k=_tangent_of(tangents), variants=variants,
                                      add=add)


def _system_cg_native(groups, u: torch.Tensor, mass: torch.Tensor, free: Optional[torch.Tensor],
                      node_stiffness: Optional[torch.Tensor], cg_state, rhs: Optional[torch.Tensor] = None):
    """(native module or None, mass ``[V]``, free ``[V]`` or None): the module when the inputs
    allow a fused path at all (``solve.system_cg_serves`` says whether it has the one op)."""
    mass_v = mass.reshape(-1)
    free_v = None if free is None else free.reshape(-1)
    return _fused_native(groups, u, cg_state.p, (mass_v, free_v, node_stiffness, rhs)), mass_v, free_v


def system_cg_serves(groups, u: torch.Tensor, mass: torch.Tensor, free: Optional[torch.Tensor],
                     node_stiffness: Optional[torch.Tensor], cg_state, tangents=None,
                     variants: KernelVariants = DEFAULT) -> bool:
    """Whether :func:`system_cg` runs these systems' CG solves in one op (see there)."""
    groups = list(groups)
    native, mass_v, free_v = _system_cg_native(groups, u, mass, free, node_stiffness, cg_state)
    if native is None:
        return False
    from . import solve

    return solve.system_cg_serves(groups[0], (cg_state.p, mass_v, free_v, node_stiffness), cg_state.scratch.numel(),
                                  _tangent_of(tangents), variants)


def system_cg(groups, u: torch.Tensor, mass: torch.Tensor, free: Optional[torch.Tensor], c_mass: float,
              c_stiff: float, node_stiffness: Optional[torch.Tensor], ap: torch.Tensor, rhs: Optional[torch.Tensor],
              tol: float, plan, cg_state, max_iter: int, count: int, tangents=None, step_end=None,
              pipelined: bool = True, variants: KernelVariants = DEFAULT, started: bool = False) -> bool:
    """A CG solve of the :func:`system_matvec` system in ONE op where the extension has it (the
    hooke tensor form over the node graph: one persistent kernel on the GPU, convergence decided
    on the device): with ``rhs [V, d]``, the start from x0 = 0 (rhs projected on ``free``;
    relative tolerance ``tol``, already clamped to the dtype's epsilon by the caller), then up to
    ``count`` iterations on ``cg_state`` (a ``CGState`` over the chunk ``plan``), stopping once no
    object is active; ``ap [V, d]``: the products' buffer. Bitwise what ``CGSolver`` computes op by
    op, except a whole solve (``rhs`` given, ``count >= max_iter``) on the GPU where the pipelined
    CG fits (``solve.system_solve``: the same iterates in exact arithmetic, rounded otherwise;
    it also does ``step_end``, a ``solve.StepEnd``, where given, and sets its ``done``; a
    ``step_end`` whose ``rhs`` is set leaves ``rhs`` to that solve: nothing else runs;
    ``pipelined=False`` never takes it). ``started`` (with ``rhs`` None): ``cg_state`` is what a
    start from a guess left (``CGSolver.start`` with x0 and no preconditioner: p = r, no
    iteration yet), so a whole solve may also go on by the pipelined CG from that iterate
    (``solve.system_solve``'s ``from_iterate``); else the iterations go on as they are.
    Returns False, having done nothing, where there is no such op (then the caller iterates)."""
    groups = list(groups)
    native, mass_v, free_v = _system_cg_native(groups, u, mass, free, node_stiffness, cg_state, rhs)
    if native is None:
        return False
    from . import solve

    # A whole solve on the GPU: the pipelined CG where it fits (one grid barrier an iteration)
    node_k = _tangent_of(tangents)
    from_iterate = rhs is None and started and step_end is None  # goes on from the start's residual
    if (pipelined and count >= max_iter and (rhs is not None or from_iterate)
            and solve.system_solve(groups[0], mass_v, free_v, c_mass, c_stiff, node_stiffness,
                                   cg_state.r if from_iterate else rhs, tol, plan, cg_state, max_iter, node_k,
                                   step_end, variants, from_iterate=from_iterate)):
        return True
    if step_end is not None and step_end.rhs is not None:  # rhs is the solve's to compute: nothing else can
        return False
    # solve.system_cg checks what it serves (and does nothing where it has no one op)
    return solve.system_cg(groups[0], mass_v, free_v, c_mass, c_stiff, node_stiffness, ap, rhs, tol, plan.tensors(),
                           cg_state, max_iter, count, node_k, variants)


def step_rhs_serves(groups, u: torch.Tensor, node_tensors=(), variants: KernelVariants = DEFAULT) -> bool:
    """Whether :func:`step_rhs` is one op for ``groups`` with inputs like ``u [V, d]`` and
    ``node_tensors`` (``[V, ...]``), no contact planes (what a solve that computes the step's
    right-hand side itself serves: ``solve.StepRhs``)."""
    groups = list(groups)
    if _fused_native(groups, u, u, node_tensors) is None:
        return False
    from . import node_graph

    return node_graph.step_rhs_serves(groups[0], (u, *node_tensors), variants)


def step_rhs(groups, x: torch.Tensor, v: torch.Tensor, rest: torch.Tensor, mass: torch.Tensor,
             external: torch.Tensor, planes, h: float, w_coef: float, rayleigh_mass: float, u: torch.Tensor,
             rhs: torch.Tensor, node_stiffness: Optional[torch.Tensor], variants: KernelVariants = DEFAULT) -> bool:
    """Implicit Euler's right-hand side in ONE op where the extension has it (one hooke tensor-form
    group over the node graph):
    ``rhs = h (f((x - rest) + w_coef v) + external + contact(x) - Kc(x) (w_coef v) - r_M M v)``
    into ``rhs [V, d]``, ``u = x - rest`` into ``u [V, d]`` and the contact stiffness Kc into
    ``node_stiffness [V, 3, 3]`` (with ``planes``, a ``contact.Planes``). ``x, v, rest, external``
    ``[V, d]``, ``mass`` ``[V]`` or ``[V, 1]``. Returns False, having done nothing, where there is
    no such op: then the caller composes it (``SystemMatvec.load`` + ``forces_along``), which is
    also this op's reference in the tests."""
    groups = list(groups)
    mass_v = mass.reshape(-1)
    if _fused_native(groups, x, v, (rest, mass_v, external, u, rhs, node_stiffness)) is None:
        return False
    from . import node_graph

    if not node_graph.planes_serve(planes, x, node_stiffness):
        return False
    return node_graph.step_rhs(groups[0], x, v, rest, mass_v, external, planes, h, w_coef, rayleigh_mass, u, rhs,
                               node_stiffness, variants)
