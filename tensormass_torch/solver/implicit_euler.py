"""Implicit (backward) Euler with one linearisation per step (Baraff & Witkin), as SOFA's
``EulerImplicitSolver``, with Rayleigh damping (r_M, r_K) and K = dF/dx never assembled:

    ((1 + h r_M) M - h (h + r_K) K) dv = h (f + (h + r_K) K v - r_M M v)
    v += dv;  x += h v

Optional further Newton iterations solve the non-linear backward Euler equations
R(v') = M (v' - v) - h f(x + h v') + h r_M M v' - h r_K K v' = 0 (the first iteration,
started from x' = x, is exactly the system above).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import List

import torch

from ..errors import SolverError
from .cg import CGResult, batched_cg
from .segments import Segments


@dataclass
class StepOptions:
    """Settings of one implicit Euler step.

    Attributes:
        dt: time step h (> 0).
        rayleigh_mass, rayleigh_stiffness: r_M, r_K (>= 0).
        cg_tol: per-object relative residual tolerance; cg_max_iter: iteration cap.
        require_convergence: if False, a CG stopped by its cap is accepted (SOFA's fixed iteration
            budget); breakdowns and NaN/inf are always errors.
        newton_iters: linearisations per step (1 = Baraff-Witkin).
        check_every: host convergence check period inside CG.
    """

    dt: float
    rayleigh_mass: float = 0.0
    rayleigh_stiffness: float = 0.0
    cg_tol: float = 1e-6
    cg_max_iter: int = 200
    require_convergence: bool = True
    newton_iters: int = 1
    check_every: int = 8


@dataclass
class StepReport:
    """What one step did: the CG result of each Newton iteration."""

    cg: List[CGResult] = field(default_factory=list)

    @property
    def cg_iterations(self) -> torch.Tensor:
        """Total CG iterations of each object over the step ``[B]``."""
        return sum(r.iterations for r in self.cg)


class DynamicsSystem:
    """Everything the integrator needs about the packed objects.

    Args:
        model: force model (``TensorMass``) over V nodes in d dimensions.
        mass: lumped masses ``[V]``.
        external: constant external forces ``[V, d]`` (gravity times mass).
        segments: the objects' node ranges.
        constrained: ``[V]`` bool, nodes whose velocity is imposed (fixed or prescribed).
        planes: ``contact.Planes`` or None.
    """

    def __init__(self, model, mass, external, segments: Segments, constrained, planes=None):
        self.model = model
        self.mass = mass.unsqueeze(-1)
        self.external = external
        self.segments = segments
        self.free = None if not bool(constrained.any()) else (~constrained).to(mass.dtype).unsqueeze(-1)
        self.planes = planes if planes is not None and len(planes) else None

    def forces(self, x):
        """All forces ``[V, d]``: elastic, external, contact."""
        f = self.model(x) + self.external
        return f if self.planes is None else f + self.planes.forces(x)

    def dforces(self, x, dx):
        """(dF/dx) dx ``[V, d]`` of the elastic and contact forces."""
        return self.tangent(x)(dx)

    def tangent(self, x):
        """dx -> (dF/dx) dx at ``x``, with what the products share computed once."""
        elastic = self.model.tangent(x)
        if self.planes is None:
            return elastic
        return lambda dx: elastic(dx) + self.planes.dforces(x, dx)


def _system_matvec(system: DynamicsSystem, x, mass_coef: float, stiffness_coef: float):
    """p -> A p through ``ops.system_matvec`` (the fused kernel-2 epilogue where the extension has
    it: mass term, subtraction and fixed-node projection in one pass), or None where the matvec
    stays composed: contact planes (their ``-c_K planes.dforces`` term) or a model that is not a
    ``TensorMass``. CG projects the product again (idempotent) and computes p . Ap itself."""
    from .. import ops
    from ..modules import TensorMass

    model = system.model
    if system.planes is not None or not isinstance(model, TensorMass):
        return None
    model._check_positions("x", x)
    u = x - model.rest
    free = system.free
    states = [ops.linearize(group, u) for group in model.groups]  # once per solve, not per iteration

    def matvec(p):
        return ops.system_matvec(model.groups, u, p, system.mass, free, mass_coef, stiffness_coef, states)[0]

    return matvec


def _solve(system: DynamicsSystem, x, rhs, opts: StepOptions) -> CGResult:
    h = opts.dt
    mass_coef = 1.0 + h * opts.rayleigh_mass
    stiffness_coef = h * (h + opts.rayleigh_stiffness)

    fused = _system_matvec(system, x, mass_coef, stiffness_coef)
    tangent = system.tangent(x) if fused is None else None

    def matvec(p):
        if fused is not None:
            return fused(p)
        return mass_coef * system.mass * p - stiffness_coef * tangent(p)

    return batched_cg(matvec, rhs, system.segments, system.free, tol=opts.cg_tol, max_iter=opts.cg_max_iter,
                      check_every=opts.check_every)


def _raise_if_failed(result: CGResult, opts: StepOptions, what: str):
    failed = result.breakdown | result.nonfinite
    if opts.require_convergence:
        failed = failed | ~result.converged
    if bool(failed.any()):
        status = result.status()
        bad = [f"object {i}: {s}" for i, s in enumerate(status) if bool(failed[i])]
        raise SolverError(f"{what} failed ({'; '.join(bad[:10])}); the state was not changed", status, result)


def implicit_euler_step(system: DynamicsSystem, x, v, opts: StepOptions, imposed_velocity=None):
    """One step from positions/velocities ``x, v [V, d]``.

    Args:
        imposed_velocity: ``[V, d]`` velocities at the end of the step of the constrained nodes;
            ignored elsewhere. None: every constrained node is fixed (and at rest).

    Returns:
        (x_new, v_new, StepReport). Raises SolverError, leaving inputs untouched, when a solve
        fails or the new state is not finite.
    """
    h = opts.dt
    report = StepReport()
    # Constrained nodes take their imposed velocity exactly; CG solves for the free nodes only.
    # With no imposed velocity, constrained nodes are fixed: they are at rest and stay there.
    dv_imposed = None
    if system.free is not None and imposed_velocity is not None:
        dv_imposed = (1.0 - system.free) * (imposed_velocity - v)

    mass_coef = 1.0 + h * opts.rayleigh_mass
    stiffness_coef = h * (h + opts.rayleigh_stiffness)
    f = system.forces(x)
    rhs = h * (f + system.dforces(x, (h + opts.rayleigh_stiffness) * v) - opts.rayleigh_mass * system.mass * v)
    if dv_imposed is not None:
        rhs = rhs - (mass_coef * system.mass * dv_imposed - stiffness_coef * system.dforces(x, dv_imposed))
    result = _solve(system, x, rhs, opts)
    report.cg.append(result)
    _raise_if_failed(result, opts, "implicit Euler CG")
    v_new = v + result.solution if dv_imposed is None else v + dv_imposed + result.solution

    for _ in range(opts.newton_iters - 1):
        x_new = x + h * v_new
        residual = (system.mass * (v_new - v) - h * system.forces(x_new) + h * opts.rayleigh_mass * system.mass * v_new
                    - h * opts.rayleigh_stiffness * system.dforces(x_new, v_new))
        result = _solve(system, x_new, -residual, opts)
        report.cg.append(result)
        _raise_if_failed(result, opts, "Newton iteration CG")
        v_new = v_new + result.solution

    x_new = x + h * v_new
    finite = torch.isfinite(system.segments.sum(x_new.abs() + v_new.abs()))
    if not bool(finite.all()):
        status = ["ok" if ok else "non-finite" for ok in finite.tolist()]
        bad = [i for i, ok in enumerate(finite.tolist()) if not ok]
        raise SolverError(f"implicit Euler produced NaN/inf for objects {bad[:10]}; the state was not changed",
                          status, report)
    return x_new, v_new, report
