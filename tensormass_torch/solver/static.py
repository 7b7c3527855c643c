"""Static equilibrium: Newton's method with CG on K du = -(f_int + f_ext)."""
from __future__ import annotations

from typing import Optional, Sequence

import torch

from ..constraints import node_mask
from ..errors import SceneError, SolverError
from .cg import batched_cg
from .segments import Segments


def solve_static(model, fixed=None, gravity: Sequence[float] = (0.0, 0.0, -9.81), tol: float = 1e-6,
                 external: Optional[torch.Tensor] = None, max_newton: int = 50, cg_tol: Optional[float] = None,
                 cg_max_iter: Optional[int] = None, planes=None) -> torch.Tensor:
    """Displacement ``u [V, d]`` at static equilibrium of a :class:`TensorMass` model.

    Solves f_int(X + u) + M g + external (+ contact) = 0 on the free nodes by Newton's method, each
    step a CG solve of (-K) du = residual (one step for ``hooke``), with a backtracking line search
    on the potential energy for non-linear models.

    Args:
        model: a ``TensorMass``.
        fixed: nodes held at rest: bool mask ``[V]`` or indices ``[k]``. A body held by nothing
            has a singular stiffness: CG then reports a breakdown or no convergence.
        gravity: acceleration ``[d]`` applied to the lumped masses.
        tol: stop when ||residual|| <= tol * ||load|| on the free nodes.
        external: extra nodal forces ``[V, d]``.
        cg_tol, cg_max_iter: inner CG settings (default tol / 10 and 10 V).
        planes: ``contact.Planes`` or None.

    Raises:
        SolverError when CG breaks down (the tangent stiffness is not positive definite: buckling,
        inverted elements) or Newton does not converge in ``max_newton`` steps.
    """
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
        r = model.displacement_forces(u) + load
        if planes is not None:
            r = r + planes.forces(rest + u)
        return r * free

    def potential(u):
        value = model.displacement_energy(u) - (load * u).sum()
        if planes is not None:  # penalty energy k/2 pen^2
            value = value + 0.5 * (planes.stiffness * planes.penetration(rest + u) ** 2).sum()
        return value

    def tangent(u):
        x = rest + u
        stiffness = model.displacement_tangent(u)  # shared state (rotations) once per Newton step

        def matvec(p):
            ap = -stiffness(p)
            return ap if planes is None else ap - planes.dforces(x, p)

        return matvec

    linear = all(g.model == "hooke" for g in model.groups) and planes is None  # corotational is not
    u = torch.zeros_like(rest)
    r = residual(u)
    for _ in range(max_newton):
        if float(torch.linalg.vector_norm(r)) <= tol * load_norm:
            return u
        result = batched_cg(tangent(u), r, segments, free, tol=cg_tol, max_iter=cg_max_iter)
        if bool(result.breakdown.any() | result.nonfinite.any()):
            raise SolverError(f"static solve: CG {result.status()[0]} (tangent stiffness not positive definite)",
                              result.status(), result)
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
