"""Static equilibrium: Newton's method with CG on K du = -(f_int + f_ext)."""
from __future__ import annotations

import copy
from typing import Optional, Sequence

import torch

from ..errors import SceneError, SolverError
from ..ops.segments import Segments
from ..physics.constraints import node_mask
from ..physics.tools import ToolSet
from .cg import batched_cg


def solve_static(model, fixed=None, gravity: Sequence[float] = (0.0, 0.0, -9.81), tol: float = 1e-6,
                 external: Optional[torch.Tensor] = None, max_newton: int = 50, cg_tol: Optional[float] = None,
                 cg_max_iter: Optional[int] = None, planes=None, precision: str = "float64",
                 tools=None, body_contact=None) -> torch.Tensor:
    """Displacement ``u [V, d]`` at static equilibrium of a :class:`TensorMass` model.

    Solves f_int(X + u) + M g + external (+ contact) = 0 on the free nodes by Newton's method, each
    step a CG solve of (-K) du = residual (one step for ``hooke``), with a backtracking line search
    on the potential energy for non-linear models.

    The equilibrium residual is a difference of internal forces much larger than the load (in a
    bent beam, by about its slenderness squared), so float32 resolves it only to about 1e-7 times
    that ratio: 1e-2 of the load on the README's stvk beam, far above ``tol``. By default the
    iterations therefore run on a float64 copy of the model and the result comes back in the
    model's dtype; ``precision="model"`` keeps the model's dtype and, should the residual stop
    falling above ``tol``, raises at once with the floor it reached.

    Args:
        model: a ``TensorMass``.
        fixed: nodes held at rest: bool mask ``[V]`` or indices ``[k]``. A body held by nothing
            has a singular stiffness: CG then reports a breakdown or no convergence.
        gravity: acceleration ``[d]`` applied to the lumped masses.
        tol: stop when ||residual|| <= tol * ||load|| on the free nodes.
        external: extra nodal forces ``[V, d]``.
        cg_tol, cg_max_iter: inner CG settings (default tol / 10 and 10 V).
        planes: ``contact.Planes`` or None.
        tools: ``tools.ToolSet`` (at the pose it is set to) or a list of ``tm.Tool`` (at time 0),
            or None.
        body_contact: contact between the bodies a packed model holds (a
            ``body_contact.SurfaceContact``, as ``Simulator.body_contact``), or None. Its penalty
            is piecewise quadratic: Newton takes the pairs in contact at each iterate.
        precision: ``"float64"`` (default: Newton and CG in float64 whatever the model's dtype) or
            ``"model"`` (in the model's dtype).

    Gradients: ``u`` is differentiable (by the implicit-function theorem) with respect to
    ``gravity`` and ``external`` when they require grad, and to the model's material where its
    tensors do (a stress-form model built from a ``Material`` whose young, poisson or density
    requires grad): see :class:`_StaticEquilibrium`.

    Raises:
        SolverError when CG breaks down (the tangent stiffness is not positive definite: buckling,
        inverted elements) or Newton does not converge in ``max_newton`` steps.
    """
    if precision not in PRECISIONS:
        raise SceneError(f"precision must be one of {', '.join(map(repr, PRECISIONS))}, got {precision!r}")
    args = dict(fixed=fixed, tol=tol, max_newton=max_newton, cg_tol=cg_tol, cg_max_iter=cg_max_iter, planes=planes,
                precision=precision, tools=tools, body_contact=body_contact)
    params = [t for t in model.buffers() if t.requires_grad]
    gravity_grad = isinstance(gravity, torch.Tensor) and gravity.requires_grad
    external_grad = external is not None and external.requires_grad
    if torch.is_grad_enabled() and (params or gravity_grad or external_grad):
        _check_differentiable(model, tools, body_contact)
        gravity = torch.as_tensor(gravity, dtype=model.rest.dtype, device=model.rest.device)
        return _StaticEquilibrium.apply(model, args, gravity, external, *params)
    return _solve_static(model, gravity=gravity, external=external, **args)


def _solve_static(model, fixed, gravity, tol, external, max_newton, cg_tol, cg_max_iter, planes, precision, tools,
                  body_contact) -> torch.Tensor:
    out_dtype = model.rest.dtype
    contacts = _contacts_of(planes, tools, body_contact, model.rest)
    if precision == "float64" and out_dtype != torch.float64:
        model = _variant(model, torch.float64)
        contacts = [c.to(dtype=torch.float64) for c in contacts]
        external = None if external is None else external.to(torch.float64)
    u = _solve(model, fixed, gravity, tol, external, max_newton, cg_tol, cg_max_iter, contacts)
    return u.to(out_dtype)


#: ``solve_static(precision=...)`` values.
PRECISIONS = ("float64", "model")
#: Newton steps over which the residual must fall by STALL_FACTOR, else the solve has stalled.
STALL_STEPS = 8
STALL_FACTOR = 0.5


def _variant(model, dtype, tangent: Optional[str] = None):
    """``model`` in ``dtype`` with its stress-form stvk groups on ``tangent`` (None: as they are):
    ``model`` itself where nothing changes, otherwise a copy, its buffers detached (the static
    solve is not differentiated). Forces and energy are the same whatever the tangent."""
    def changes(group):
        return tangent is not None and group.model == "stvk" and group.form == "stress" and group.tangent != tangent

    if model.rest.dtype == dtype and not any(changes(g) for g in model.groups):
        return model
    memo = {id(t): t.detach() for t in model.buffers() if t.requires_grad}
    clone = copy.deepcopy(model, memo).to(dtype)
    for group in clone.groups:
        if changes(group):
            group.tangent = tangent
    return clone


def _solve(model, fixed, gravity, tol, external, max_newton, cg_tol, cg_max_iter, contacts):
    # Newton steps on the exact tangent (quadratic convergence); where it is indefinite (a
    # compressed stvk body: CG breaks down) that step is taken on the definite tangent instead.
    exact = _variant(model, model.rest.dtype, "exact")
    definite = None
    has_stvk = any(g.model == "stvk" and g.form == "stress" for g in model.groups)
    rest = model.rest
    num_nodes, dim = rest.shape
    gravity = torch.as_tensor(gravity, dtype=rest.dtype, device=rest.device)
    if gravity.shape != (dim,):
        raise SceneError(f"gravity must have {dim} components for this {dim}-D model, got {tuple(gravity.shape)}")
    fixed_mask = node_mask(fixed, num_nodes, "fixed", device=rest.device)
    if bool(fixed_mask.all()):
        raise SceneError("every node is fixed: there is nothing to solve")
    free = (~fixed_mask).to(rest.dtype).unsqueeze(-1)
    load = model.lumped_mass().unsqueeze(-1) * gravity
    if external is not None:
        if external.shape != rest.shape:
            raise SceneError(f"external forces have shape {tuple(external.shape)}; expected {tuple(rest.shape)}")
        load = load + external
    segments = Segments.single(num_nodes, rest.device)
    load_norm = float(torch.linalg.vector_norm(load * free))
    if load_norm == 0.0:
        return torch.zeros_like(rest)
    cg_tol = tol / 10.0 if cg_tol is None else cg_tol
    cg_max_iter = 10 * num_nodes * dim if cg_max_iter is None else cg_max_iter

    # The model is evaluated at displacements, not at positions rest + u: in float32 the
    # positions would round the small displacements of a stiff body (see TensorMass).
    def residual(u):
        r = exact.displacement_forces(u) + load
        for contact in contacts:
            r = r + contact.forces(rest + u)
        return r * free

    def potential(u):
        value = exact.displacement_energy(u) - (load * u).sum()
        for contact in contacts:  # penalty energies
            value = value + contact.energy(rest + u)
        return value

    def tangent(on, u):
        x = rest + u
        stiffness = on.displacement_tangent(u)  # shared state (rotations) once per Newton step

        def matvec(p):
            ap = -stiffness(p)
            for contact in contacts:
                ap = ap - contact.dforces(x, p)
            return ap

        return matvec

    def failed(result):
        return bool(result.breakdown.any() | result.nonfinite.any())

    linear = all(g.model == "hooke" for g in model.groups) and not contacts  # corotational is not
    u = torch.zeros_like(rest)
    r = residual(u)
    history = []
    for _ in range(max_newton):
        ratio = float(torch.linalg.vector_norm(r)) / load_norm
        if ratio <= tol:
            return u
        history.append(ratio)
        if _stalled(history):
            _raise_if_rounding(model, u, r, load, free, contacts, tol)
        result = batched_cg(tangent(exact, u), r, segments, free, tol=cg_tol, max_iter=cg_max_iter)
        if failed(result) and has_stvk:
            definite = definite or _variant(model, model.rest.dtype, "definite")
            result = batched_cg(tangent(definite, u), r, segments, free, tol=cg_tol, max_iter=cg_max_iter)
        if failed(result):
            raise SolverError(f"static solve: CG {result.status()[0]} (tangent stiffness not positive definite: "
                              "buckling, a body held too little, or inverted elements)", result.status(), result)
        du = result.solution
        step = 1.0
        if not linear:  # Armijo backtracking on the potential energy
            step = _line_search(potential, residual, u, du, r)
        u = u + step * du
        r = residual(u)
        if linear and bool(result.converged.all()):
            return u
    if float(torch.linalg.vector_norm(r)) <= tol * load_norm:
        return u
    raise SolverError(f"static solve did not converge in {max_newton} Newton steps "
                      f"(residual ratio {float(torch.linalg.vector_norm(r)) / load_norm:.3e} > {tol})",
                      ["not converged"])


def _stalled(history) -> bool:
    """Whether the residual ratios ``history`` have stopped falling: the best of the last
    STALL_STEPS Newton steps is not STALL_FACTOR below the best before them."""
    return len(history) > STALL_STEPS and min(history[-STALL_STEPS:]) > STALL_FACTOR * min(history[:-STALL_STEPS])


def _raise_if_rounding(model, u, r, load, free, contacts, tol: float):
    """Raise when a stalled solve below float64 stalled on rounding: its residual ``r [V, d]`` at
    ``u [V, d]`` differs from the float64 residual there by as much as it measures. A stall that
    float64 shares (a slow non-linear solve) is left to max_newton."""
    if u.dtype == torch.float64:
        return
    wide = _variant(model, torch.float64)
    u64 = u.to(torch.float64)
    r64 = wide.displacement_forces(u64) + load.to(torch.float64)
    for contact in contacts:
        r64 = r64 + contact.to(dtype=torch.float64).forces(wide.rest + u64)
    r64 = r64 * free.to(torch.float64)
    noise = float(torch.linalg.vector_norm(r.to(torch.float64) - r64))
    if noise > 0.5 * float(torch.linalg.vector_norm(r)):
        floor = noise / float(torch.linalg.vector_norm(load * free))
        raise SolverError(f"static solve stalled at a residual ratio of about {floor:.1e} > tol {tol:g}: in "
                          f"{str(u.dtype).replace('torch.', '')} the internal forces cancel to the load only within "
                          f"rounding; use precision='float64' (the default) or tol >= {2 * floor:.0e}",
                          ["not converged"])


def _line_search(potential, residual, u, du, r) -> float:
    """Armijo backtracking along ``du`` from ``u`` (residual ``r``) on the potential energy.

    Near equilibrium the potential's decrease falls below its rounding (its value is a sum of
    large terms: in float32 a change under ~1e-7 of it is invisible), and the sufficient-decrease
    test would then reject every step. A trial whose change is within that rounding is judged by
    the residual instead: accepted when it lowers the residual norm.
    """
    p0 = potential(u)
    slope = -(r * du).sum()
    eps = torch.finfo(u.dtype).eps
    r0 = torch.linalg.vector_norm(r)
    step = 1.0
    while step > 1e-4:
        trial = u + step * du
        p = potential(trial)
        if bool(p <= p0 + 1e-4 * step * slope):
            return step
        if float((p - p0).abs()) <= 16 * eps * max(float(p0.abs()), float(p.abs())):
            if bool(torch.linalg.vector_norm(residual(trial)) < r0):
                return step
        step *= 0.5
    return step


class _StaticEquilibrium(torch.autograd.Function):
    """``u`` at equilibrium as a function of the load and the model's material, by the
    implicit-function theorem: on the free rows r(u, p) = f(u; p) + M(p) g + external (+ contact)
    = 0, so with A = -dr/du (the exact tangent, and the contacts' stiffness; symmetric positive
    definite at a stable equilibrium) du/dp = A^-1 dr/dp and, for the cotangent g of u,

        A lam = P g,   dL/dp = lam . dr/dp

    one CG solve at the equilibrium and one vector-Jacobian product of the residual through the
    model's ops (its buffers that require grad: Lame constants' sources, masses).

    Inputs: the model, the other arguments of ``solve_static``, gravity ``[d]``, external
    ``[V, d]`` or None, then the model's buffers that require grad (so autograd reaches them)."""

    @staticmethod
    def forward(ctx, model, args, gravity, external, *params):
        u = _solve_static(model, gravity=gravity.detach(), external=None if external is None else external.detach(),
                          **args)
        ctx.model, ctx.args = model, args
        ctx.save_for_backward(u, gravity, external, *params)
        return u

    @staticmethod
    def backward(ctx, grad):
        u, gravity, external, *params = ctx.saved_tensors
        u = u.detach()  # this function's output: autograd must not come back through it
        model, args = ctx.model, ctx.args
        rest = model.rest
        free = (~node_mask(args["fixed"], rest.shape[0], "fixed", device=rest.device)).to(rest.dtype).unsqueeze(-1)
        contacts = _contacts_of(args["planes"], args["tools"], args["body_contact"], rest)
        exact = _variant(model, rest.dtype, "exact")
        stiffness = exact.displacement_tangent(u)
        x = rest + u

        def matvec(p):
            ap = -stiffness(p)
            for contact in contacts:
                ap = ap - contact.dforces(x, p)
            return ap

        tol = 1e-12 if rest.dtype == torch.float64 else 1e-6
        result = batched_cg(matvec, grad * free, Segments.single(rest.shape[0], rest.device), free, tol=tol,
                            max_iter=10 * u.numel())
        if not bool(result.converged.all()):
            raise SolverError(f"the static solve's adjoint CG: {result.status()[0]} (the tangent at the "
                              "equilibrium is not positive definite, or the tolerance is out of reach)",
                              result.status(), result)
        lam = result.solution
        needs = ctx.needs_input_grad  # (model, args, gravity, external, *params)
        with torch.enable_grad():
            g = gravity.detach().requires_grad_(needs[2])
            ext = None if external is None else external.detach().requires_grad_(needs[3])
            residual = model.displacement_forces(u) + model.lumped_mass().unsqueeze(-1) * g
            if ext is not None:
                residual = residual + ext
            for contact in contacts:
                residual = residual + contact.forces(x)
            wanted = [t for t, need in zip([g, ext, *params], needs[2:]) if need and t is not None]
            grads = iter(torch.autograd.grad((lam * residual).sum(), wanted, allow_unused=True)) if wanted else iter(())
        out = [next(grads) if need and t is not None else None for t, need in zip([g, ext, *params], needs[2:])]
        return (None, None, *out)


def _check_differentiable(model, tools, body_contact) -> None:
    """The implicit-function theorem needs the residual's exact Jacobian, which the solve's tangent
    is only for hooke and stvk elements and planes: raise naming anything else."""
    reasons = []
    if any(g.model == "corotational" for g in model.groups):
        reasons.append("corotational elements (their forces' Jacobian through the rotations is not the "
                       "symmetric tangent the solve uses)")
    if tools is not None and len(tools):
        reasons.append("rigid tools")
    if body_contact is not None:
        reasons.append("contact between bodies")
    if reasons:
        raise SolverError("gradients of the static equilibrium are not available with " + "; ".join(reasons)
                          + " (hooke and stvk bodies, fixed nodes and planes are differentiable; for the others, "
                          "tm.rollout differentiates the dynamic steps)")


def _contacts_of(planes, tools, body_contact, rest: torch.Tensor) -> list:
    """The contact terms of ``solve_static``'s arguments present (planes, tools: a ``ToolSet`` or
    a list of tools, body contact), tools in the model's dtype."""
    if tools is not None and not isinstance(tools, ToolSet):
        tools = ToolSet(list(tools), rest.dtype, rest.device)
    contacts = [c for c in (planes, tools) if c is not None and len(c)]
    if body_contact is not None:
        contacts.append(body_contact)
    return contacts
