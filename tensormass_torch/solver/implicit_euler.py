"""Implicit (backward) Euler with one linearisation per step (Baraff & Witkin), as SOFA's
``EulerImplicitSolver``, with Rayleigh damping (r_M, r_K) and K = dF/dx never assembled:

    ((1 + h r_M) M - h (h + r_K) K) dv = h (f + (h + r_K) K v - r_M M v)
    v += dv;  x += h v

Optional further Newton iterations solve the non-linear backward Euler equations
R(v') = M (v' - v) - h f(x + h v') + h r_M M v' - h r_K K v' = 0 (the first iteration,
started from x' = x, is exactly the system above).

The same system with theta h in place of h where it weighs the step's end gives Newmark's
average acceleration (``integrator="newmark"``, theta = 1/2: the trapezoidal rule). With the
damped forces F(x, v) = f(x) - r_M M v + r_K K v and

    M dv = h ((1 - theta) F(x, v) + theta F(x', v')),     x' = x + (1 - theta) h v + theta h v',

F(x', v') linearised at x (x' - x = h v + theta h dv) gives

    ((1 + theta h r_M) M - theta h (theta h + r_K) K) dv = h (f + (theta h + r_K) K v - r_M M v)

(theta = 1: the system above). For a linear undamped system theta = 1/2 is Newmark's
beta = 1/4, gamma = 1/2: it keeps the energy (no amplitude lost per period, where backward Euler
loses a fraction that grows with h / T), at the same cost per step. Friction stays implicit in v'.

BDF2 (``integrator="bdf2"``) is backward Euler from an extrapolated state with a shorter step
(:func:`bdf2_step`): second order, its damping falling as h^3, at backward Euler's cost.
"""
from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass, field
from typing import List, Optional

import numpy as np
import torch

from ..errors import SolverError
from ..ops import cg as cg_ops
from ..ops import library, node_graph, solve
from ..ops.segments import Segments
from ..ops.variants import DEFAULT, KernelVariants
from .capture import run_captured
from .cg import CGResult, CGSolver
from .guess import SolutionSpace, warm_start_mode
from .preconditioner import (
    PRECONDITIONERS,
    BlockJacobi,
    JacobiScaling,
    MultigridSolve,
    PairTerms,
    system_diagonal_blocks,
    system_rest_preconditioner,
)
from .refine import MAX_ROUNDS, PRECISIONS, Refinement
from .rigid_modes import RigidModeCorrection


def auto_cg_max_iter(free_dofs: int) -> int:
    """The CG cap a simulator uses when none is given: 10 x the free degrees of freedom of its
    largest object (at least 100).

    CG reaches the exact solution in at most n iterations in exact arithmetic; in float32 the
    loss of orthogonality on an ill-conditioned system (a nearly incompressible or a stiff body
    at a large step) costs several times n (docs/solver-defaults.md). A converging solve stops at
    its tolerance, so the cap never shortens it: it only bounds how long a hopeless solve runs
    before it is reported as not converged."""
    return max(100, 10 * int(free_dofs))


@dataclass
class StepOptions:
    """Settings of one implicit Euler step.

    Attributes:
        dt: time step h (> 0).
        rayleigh_mass, rayleigh_stiffness: r_M, r_K (>= 0).
        cg_tol: per-object relative residual tolerance; cg_max_iter: iteration cap (the
            Simulator's default is :func:`auto_cg_max_iter`).
        require_convergence: if False, a CG stopped by its cap is accepted (SOFA's fixed iteration
            budget); breakdowns and NaN/inf are always errors.
        newton_iters: linearisations per step (1 = Baraff-Witkin).
        check_every: host convergence check period inside CG (the CG iterations between two
            checks run as one CUDA graph on the GPU).
        cuda_graphs: capture the CG iterations in CUDA graphs (CUDA devices only).
        pipelined: whole solves on the GPU by the pipelined CG where it fits (one grid barrier an
            iteration; the fastest); False: the classic CG. In float32 the pipelined recurrences
            lose accuracy on ill-conditioned systems: more iterations, and at worst a false
            breakdown, where the classic CG converges (the Simulator retries such a step so).
        preconditioner: ``"auto"`` (default: for the solves that body contact pairs join, block
            Jacobi with the rigid bodies' coarse correction (3-D; 2-D: block Jacobi alone), none
            elsewhere), ``"none"``, ``"jacobi"``, ``"rigid"`` (block Jacobi with a coarse
            correction over each body's rigid motions, coupled by the contact pairs: 3-D),
            ``"multigrid"`` or ``"cholesky"`` (every solve of a TensorMass; not the whole-solve op
            or the captured steps): see ``solver.preconditioner``, ``solver.rigid_modes``,
            ``solver.multigrid`` and ``solver.direct``. With Jacobi and rigid, ``cg_tol`` holds the
            residual scaled by the diagonal blocks' factors; with the others, the true residual.
        variants: the kernel variants the ops run (``ops.variants.KernelVariants``: equivalent
            kernels that differ in speed); the default reads the benchmarks' ``TENSORMASS_*``
            variables once (``KernelVariants.from_env``).
        integrator: ``"backward_euler"`` (default), ``"newmark"`` (Newmark's average
            acceleration, the trapezoidal rule: no numerical damping) or ``"bdf2"`` (the
            two-step backward differentiation formula: second order, damping that falls as h^3;
            its steps are :func:`bdf2_step`'s); :data:`INTEGRATORS`.
        warm_start: where each step's CG starts (:data:`guess.WARM_STARTS`; ``False`` is
            ``"none"``, ``True`` ``"extrapolate"``): ``"none"`` (default) from zero;
            ``"extrapolate"`` from the simulator's extrapolation of the solutions of the steps
            before (``sim.simulator``; the step functions take it as ``guess``); ``"project"``
            from the projection of the step's solution on the span of the last steps' solutions
            (``guess.SolutionSpace``, kept by the system: exact in its span for a constant
            matrix, as hooke's without contact). The stopping rule is unchanged (the true
            residual relative to the right-hand side), so the step means the same; fewer
            iterations where the motion is smooth.
        paired_blocks: with block Jacobi (``"auto"``, ``"jacobi"``, ``"rigid"``) on a solve that
            body contact pairs join, merge the two nodes of different bodies a pair couples most
            into one 6 x 6 block (``preconditioner.BlockJacobi``; 3-D): fewer iterations where
            contacts press (default True); False: each node's own block.
        precision: ``"full"`` (default: every solve in the state's dtype) or ``"mixed"`` (a float64
            state's solves by iterative refinement: float64 residuals, float32 CG corrections;
            ``solver.refine``): the same stopping rule on the float64 residual at float32's cost
            per iteration. TensorMass models, planes and tools, no body contact, no
            preconditioner (:data:`refine.PRECISIONS`).
    """

    dt: float
    rayleigh_mass: float = 0.0
    rayleigh_stiffness: float = 0.0
    cg_tol: float = 1e-6
    cg_max_iter: int = 200
    require_convergence: bool = True
    newton_iters: int = 1
    check_every: int = 8
    cuda_graphs: bool = True
    pipelined: bool = True
    preconditioner: str = "auto"
    variants: KernelVariants = field(default_factory=KernelVariants.from_env)
    integrator: str = "backward_euler"
    warm_start: str = "none"
    paired_blocks: bool = True
    precision: str = "full"

    def __post_init__(self):
        self.warm_start = warm_start_mode(self.warm_start)
        if self.precision not in PRECISIONS:
            raise ValueError(f"unknown precision {self.precision!r}; known: {', '.join(map(repr, PRECISIONS))}")
        if self.precision == "mixed" and self.preconditioner not in ("auto", "none"):
            raise ValueError(f"precision='mixed' runs unpreconditioned float32 corrections: preconditioner must be "
                             f"'auto' or 'none', got {self.preconditioner!r}")
        if self.preconditioner not in PRECONDITIONERS:
            raise ValueError(f"unknown preconditioner {self.preconditioner!r}; known: "
                             f"{', '.join(map(repr, PRECONDITIONERS))}")
        if self.integrator not in INTEGRATORS:
            raise ValueError(f"unknown integrator {self.integrator!r}; known: {', '.join(map(repr, INTEGRATORS))}")
        if self.theta != 1.0 and self.newton_iters != 1:
            raise ValueError(f"newton_iters={self.newton_iters} needs integrator='backward_euler' or 'bdf2' (the "
                             f"{self.integrator!r} step is one linearisation)")

    @property
    def theta(self) -> float:
        """The weight theta of the step's end in its forces and motion: 1 for backward Euler,
        1/2 for Newmark's average acceleration (the module's docstring)."""
        return INTEGRATORS[self.integrator]

    @property
    def velocity_coefficient(self) -> float:
        """theta h + r_K: the multiple of the velocities the right-hand side's stiffness acts on."""
        return self.theta * self.dt + self.rayleigh_stiffness

    @property
    def old_velocity_share(self) -> float:
        """(1 - theta) h: the part of the step's motion taken at the old velocities,
        x' = x + (1 - theta) h v + theta h v'."""
        return (1.0 - self.theta) * self.dt


@dataclass
class StepReport:
    """What one step did: the CG result of each solve (each Newton iteration; with body contact,
    each solve again for pairs the one before left out)."""

    cg: List[CGResult] = field(default_factory=list)
    #: each solve of the step's contact set: (the body contact's pairs it held, ``ContactPairs``;
    #: the end velocities it gave ``[V, d]``), the last the step's; None without body contact (or
    #: with a model without a fused product: its solves find their pairs)
    contact_solves: Optional[list] = None

    @property
    def cg_iterations(self) -> torch.Tensor:
        """Total CG iterations of each object over the step ``[B]``."""
        return sum(r.iterations for r in self.cg)

    # -- filled by the Simulator (sim.simulator), never by implicit_euler_step --------------------
    #: inverted elements per object ``[B]`` (int64) at the end of the step when the simulator's
    #: ``check_inversion`` is on; None otherwise.
    inverted: torch.Tensor | None = None
    #: sub-steps the step took: 1, or 2^k after a failed step was retried at dt / 2^k
    #: (``substeps_on_failure``); ``cg`` then holds every sub-step's solves.
    substeps: int = 1
    #: the tools' reactions, contact counts and penetrations at the end of the step
    #: (``sim.diagnostics.ContactReport``) when the simulator has tools; None otherwise.
    contact: object = None


class DynamicsSystem:
    """Everything the integrator needs about the packed objects.

    Args:
        model: force model (``TensorMass``) over V nodes in d dimensions.
        mass: lumped masses ``[V]``.
        external: constant external forces ``[V, d]`` (gravity times mass).
        segments: the objects' node ranges.
        constrained: ``[V]`` bool, nodes whose velocity is imposed (fixed or prescribed).
        planes: ``contact.Planes`` or None.
        tools: ``tools.ToolSet`` or None (rigid tools: node-wise penalties, like the planes, whose
            poses the caller sets before each step: ``ToolSet.set_time``).
        body_contact: ``body_contact.SurfaceContact`` or None (vertex-triangle contact between the
            bodies' surfaces: pairs found at each linearisation; a step solves the bodies they
            join as one system).
        keep_mask: keep the mask of free nodes (``free [V, 1]``) even when nothing is constrained,
            for a caller that constrains nodes later in place (topology changes); without it such
            a system has no mask (``free`` None) and its products skip the projection.
    """

    def __init__(self, model, mass, external, segments: Segments, constrained, planes=None, keep_mask: bool = False,
                 tools=None, body_contact=None):
        self.model = model
        self.mass = mass.unsqueeze(-1)
        self.external = external
        self.segments = segments
        if hasattr(model, "groups"):  # a TensorMass: its node graphs' rows keep to one object each
            node_graph.set_objects(model, segments.ptr)
        self.free = (None if not (keep_mask or bool(constrained.any()))
                     else (~constrained).to(mass.dtype).unsqueeze(-1))
        self.planes = planes if planes is not None and len(planes) else None
        self.tools = tools if tools is not None and len(tools) else None
        self.body_contact = body_contact
        self._cg = None  # CGSolver, kept across steps (its buffers and CUDA graphs)
        self._matvecs = {}  # (c_mass, c_stiff) -> SystemMatvec
        self._step_graphs = {}  # step options -> StepGraphs (CUDA)
        self._differentiable_steps = {}  # (forward, adjoint options) -> solver.adjoint.DifferentiableStep
        self._coupled_cg = {}  # object ptr of coupled solves -> (CGSolver, each object's run [B])
        self._coupled_ptr = None  # the coupled solves' layout so far (runs only merge; None: none yet)
        self._pair_stiffness = None  # body_contact.PairStiffness: the pairs' product, its buffers kept
        self._block_jacobi = None  # preconditioner.BlockJacobi: its B^-1 kept (graphs replay with each load's)
        self._rigid = None  # rigid_modes.RigidModeCorrection: its buffers kept (as _block_jacobi's)
        self._check_stream = None  # the CUDA stream contact checks run on beside the CG (_check_beside)
        #: stretches of a paused solve launched before its contact check on the GPU (0: the check
        #: runs after the solve, not beside it; :func:`_check_beside`)
        self.check_ahead = CHECK_AHEAD_STRETCHES
        self._rest_preconditioner = None  # (key, cache) of preconditioner.system_rest_preconditioner
        self._multigrid_solve = None  # preconditioner.MultigridSolve over it (its diagonal buffer kept)
        self._solution_spaces = {}  # step coefficients -> (tensors, versions, guess.SolutionSpace)
        self._refinements = {}  # step product's key -> (tensors, versions, refine.Refinement)

    def solution_space(self, opts: "StepOptions", like: torch.Tensor) -> SolutionSpace:
        """The ``warm_start="project"`` space of the steps with these options' matrix (made at the
        first call; one per step coefficients). It is emptied, in place, when the model's tensors
        (a cut edits them), the masses or the constraints change: its basis was orthonormal for
        the matrix before."""
        tensors = self._matrix_tensors()
        key = (*_coefficients(opts), like.dtype, like.device)
        kept = self._solution_spaces.get(key)
        if kept is None or kept[2].basis.shape[1:] != like.shape:
            kept = (tensors, tuple(t._version for t in tensors), SolutionSpace(like, self.segments))
        elif not library.unchanged(kept, tensors):
            kept[2].reset()
            kept = (tensors, tuple(t._version for t in tensors), kept[2])
        self._solution_spaces[key] = kept
        return kept[2]

    def refinement(self, opts: "StepOptions") -> Refinement:
        """The float32 side of this (float64) system's refined solves (``precision="mixed"``) for
        these options' step matrix: made at the first call, and again (a new object: graphs over
        the old one must be dropped) when the model's tensors, the masses or the constraints
        change, as :meth:`solution_space`'s keys."""
        from ..physics.tensor_mass import TensorMass

        if not isinstance(self.model, TensorMass):
            raise ValueError(f"precision='mixed' needs a TensorMass model, got a {type(self.model).__name__}")
        if self.body_contact is not None:
            raise ValueError("precision='mixed' does not take body contact (its pairs' product is not in the "
                             "float32 copy)")
        if self.model.rest.dtype != torch.float64:
            raise ValueError(f"precision='mixed' needs a float64 state (float32 corrections), got "
                             f"{self.model.rest.dtype}")
        tensors = self._matrix_tensors()
        key = (*_coefficients(opts), opts.pipelined, opts.variants, opts.cuda_graphs)
        kept = self._refinements.get(key)
        if not library.unchanged(kept, tensors):
            kept = self._refinements[key] = (tensors, tuple(t._version for t in tensors),
                                             Refinement(self, *key))
        return kept[2]

    def _matrix_tensors(self) -> tuple:
        """The tensors a step's matrix at rest is made of: the model's groups', the masses, the
        free-node mask (what the caches built from that matrix key on: the solution spaces here,
        ``preconditioner.system_rest_preconditioner``)."""
        groups = getattr(self.model, "groups", ())
        return tuple(t for group in groups for t in group.buffers()) + (self.mass,) + (
            () if self.free is None else (self.free,))

    def pair_stiffness(self, pairs, coefficient: float, damping: float = 0.0):
        """The body contact's :class:`PairStiffness` loaded with ``pairs``, their stiffness scaled by
        ``coefficient`` and their friction by ``damping`` (its buffers kept across steps; where
        they grow, the graphs captured over the old ones are dropped)."""
        from ..physics.body_contact import PairStiffness

        if self._pair_stiffness is None:
            self._pair_stiffness = PairStiffness()
        if self._pair_stiffness.load(pairs, coefficient, damping):
            self._coupled_cg.clear()
            if self._cg is not None:
                self._cg._graphs = {k: g for k, g in self._cg._graphs.items()
                                    if not (isinstance(k[0], tuple) and "pairs" in k[0])}
        return self._pair_stiffness

    def cg_solver(self, like: torch.Tensor, cuda_graphs: bool) -> CGSolver:
        """The batched CG over these objects (made once, on ``like``'s device and dtype)."""
        cg = self._cg
        if (cg is None or cg.state.x.dtype != like.dtype or cg.state.x.device != like.device
                or cg.cuda_graphs != (cuda_graphs and like.device.type == "cuda")):
            cg = self._cg = CGSolver(self.segments, like.shape, like.dtype, like.device, self.free,
                                     cuda_graphs=cuda_graphs)
        return cg

    def system_matvec(self, mass_coef: float, stiffness_coef: float, pipelined: bool = True,
                      variants: KernelVariants = DEFAULT):
        """The :class:`SystemMatvec` for these coefficients, CG and kernel variants, or None when the
        model is not a TensorMass."""
        from ..physics.tensor_mass import TensorMass

        if not isinstance(self.model, TensorMass):
            return None
        key = (float(mass_coef), float(stiffness_coef), bool(pipelined), variants)
        if key not in self._matvecs:
            self._matvecs[key] = SystemMatvec(self, *key)
        return self._matvecs[key]

    def forces(self, x, variants: KernelVariants = DEFAULT):
        """All forces ``[V, d]``: elastic, external, contact; ``variants``: the kernels of the
        elastic forces."""
        from ..physics.tensor_mass import TensorMass

        # another force model (any module x -> forces) has no kernel variants
        f = (self.model(x, variants) if isinstance(self.model, TensorMass) else self.model(x)) + self.external
        for contact in self.contacts:
            f = f + contact.forces(x)
        if self.body_contact is not None:
            f = f + self.body_contact.forces(x)
        return f

    @property
    def contacts(self) -> list:
        """The contact terms (planes, tools) present: each has ``forces``, ``dforces``, ``linearize``."""
        return [c for c in (self.planes, self.tools) if c is not None]

    @property
    def has_node_friction(self) -> bool:
        """Whether a plane or a tool has friction (``friction_damping`` is then not None)."""
        return any(c.has_friction for c in self.contacts)

    def friction_damping(self, x, v):
        """The planes' and tools' friction over a step from ``x, v [V, 3]`` as a damper
        (``contact.NodeDamping``: forces ``drive - C v``), or None where none has friction."""
        damping = None
        for contact in self.contacts:
            if contact.has_friction:
                term = contact.friction_damping(x, v)
                damping = term if damping is None else damping + term
        return damping

    def dforces(self, x, dx):
        """(dF/dx) dx ``[V, d]`` of the elastic and contact forces."""
        return self.tangent(x)(dx)

    def tangent(self, x, pairs=None):
        """dx -> (dF/dx) dx at ``x``, with what the products share computed once; ``pairs``: the
        body contact's pairs at x where the caller has them (else found here)."""
        elastic = self.model.tangent(x)
        contacts = self.contacts
        if pairs is None and self.body_contact is not None:
            pairs = self.body_contact.detect(x)
        if not contacts and pairs is None:
            return elastic

        def apply(dx):
            total = elastic(dx)
            for contact in contacts:
                total = total + contact.dforces(x, dx)
            return total if pairs is None else total + pairs.dforces(dx)

        return apply


class SystemMatvec:
    """p -> (A p, p . Ap per node) for ``A = c_M M - c_K dF/dx`` through ``ops.system_matvec`` (the
    fused kernel-2 epilogue where the extension has it: mass term, subtraction, contact
    stiffness, fixed-node projection and per-node dot in one pass).

    What the product depends on (the displacements at the linearisation point, the corotational
    rotations, the contact stiffness) lives in buffers that keep their storage from one solve to
    the next, refreshed in place by :meth:`load`: the CG iterations can then be captured once in a
    CUDA graph and replayed at every step.
    """

    def __init__(self, system: DynamicsSystem, mass_coef: float, stiffness_coef: float, pipelined: bool = True,
                 variants: KernelVariants = DEFAULT):
        self.system = system
        self.mass_coef = mass_coef
        self.stiffness_coef = stiffness_coef
        #: whole solves by the pipelined CG where it fits (``StepOptions.pipelined``)
        self.pipelined = pipelined
        #: the kernel variants of every op this matvec runs (``StepOptions.variants``)
        self.variants = variants
        self.u = torch.zeros_like(system.model.rest)
        self.states = None
        #: the differential at the loaded positions on the node graph (``ops.node_tangent``, one
        #: group: ``[node_k [N_n, V, d, d]]``), or None where the products run element by element
        self.tangents = None
        self.node_stiffness = None
        self.loads = 0  # how many times load or load_step ran (what was derived from a load is kept by it)
        self.diagonal_blocks = None  # (loads, coefficients, the step's diagonal blocks without pairs): _jacobi
        #: contact forces ``[V, d]`` at the loaded positions (None without planes)
        self.contact_forces = None
        self._ap = None  # A p of matvec_alpha (kept: a CUDA graph replays into it)
        self._rhs = None  # the step's right-hand side of load_step (kept, as _ap)
        self._zero_mass = None  # [V, 1] zeros: forces_along's product over the node graph has no mass term
        self.graph_key = ("system", mass_coef, stiffness_coef, pipelined, variants, id(self))

    def load(self, x: torch.Tensor) -> "SystemMatvec":
        """Linearise at positions ``x [V, d]``: rotations, contact forces and contact stiffness
        computed once here, for the CG products and the right-hand side alike."""
        from .. import ops

        system = self.system
        system.model._check_positions("x", x)
        self.loads += 1
        torch.sub(x, system.model.rest, out=self.u)
        states = [ops.linearize(group, self.u) for group in system.model.groups]
        if self.states is None or [s is None for s in states] != [s is None for s in self.states]:
            self.states = [None if s is None else s.clone() for s in states]
        else:
            for dst, src in zip(self.states, states):
                if src is not None:
                    dst.copy_(src)
        if system.contacts:
            self.contact_forces, stiffness = None, None
            for contact in system.contacts:
                forces, node_stiffness = contact.linearize(x)
                self.contact_forces = forces if self.contact_forces is None else self.contact_forces + forces
                stiffness = node_stiffness if stiffness is None else stiffness + node_stiffness
            if self.node_stiffness is None:
                self.node_stiffness = stiffness.clone()
            else:
                self.node_stiffness.copy_(stiffness)
        self._load_tangents()
        return self

    def _load_tangents(self):
        """The differential at ``self.u`` on the node graph, into the kept buffer (the fused paths
        serve one group), where ``ops.node_tangent`` serves the group."""
        from .. import ops

        groups = self.system.model.groups
        tangent = None
        if len(groups) == 1:
            state = None if self.states is None else self.states[0]
            tangent = ops.node_tangent(groups[0], self.u, state, None if self.tangents is None else self.tangents[0],
                                       self.variants)
        self.tangents = None if tangent is None else [tangent]

    def load_step(self, x: torch.Tensor, v: torch.Tensor, h: float, rayleigh_mass: float,
                  w_coef: float) -> torch.Tensor:
        """Linearise at positions ``x [V, d]`` (as :meth:`load`) and return the implicit step's
        right-hand side there for velocities ``v [V, d]``:
        ``h (f(x) + w_coef K v - r_M M v)`` ``[V, d]`` (K = dF/dx, contact included; w_coef =
        ``StepOptions.velocity_coefficient``, theta h + r_K).

        One op where the extension has it (``ops.step_rhs``: the hooke tensor form over the node
        graph, one pass over the nodes instead of a dozen ops); then :attr:`contact_forces` is
        not kept (only the stiffness, which the CG products read) and the returned tensor is a
        buffer of this matvec, overwritten by the next call. Otherwise :meth:`load` and
        :meth:`forces_along`, the op's reference."""
        from .. import ops

        system = self.system
        self._node_rhs_buffers()
        model = system.model
        model._check_positions("x", x)
        self.loads += 1
        # the op takes planes, not tools
        if system.tools is None and ops.step_rhs(model.groups, x, v, model.rest, system.mass, system.external,
                                                 system.planes, h, w_coef, rayleigh_mass, self.u, self._rhs,
                                                 self.node_stiffness, self.variants):
            self._loaded_by_node_rhs()
            return self._rhs
        self.load(x)
        rhs = self.forces_along(w_coef * v)
        if rayleigh_mass:  # no damping term without damping
            rhs = rhs - rayleigh_mass * system.mass * v
        return h * rhs

    def step_rhs_in_solve(self, h: float, rayleigh_mass: float, w_coef: float):
        """What a solve needs to compute :meth:`load_step`'s right-hand side itself, at the state
        its step end starts from (``solve.StepRhs``: into :attr:`u`, :attr:`node_stiffness` with
        planes, and the buffer returned with it: ``(StepRhs, rhs [V, d])``), where ``load_step``
        would be one op; None otherwise. Leaves this matvec as ``load_step``'s op does (the solve
        may still decline: then ``load_step`` runs as before)."""
        from .. import ops

        system, model = self.system, self.system.model
        # the op takes planes, not tools, and no friction (added to the stiffness after the op)
        if system.tools is not None or system.has_node_friction or len(model.groups) != 1:
            return None
        if not ops.step_rhs_serves(model.groups, self.u, (model.rest, system.external), self.variants):
            return None
        self._node_rhs_buffers()
        self._loaded_by_node_rhs()
        rest, external = (t.contiguous() for t in (model.rest, system.external))
        return solve.StepRhs(rest, external, w_coef, rayleigh_mass, self.u, system.planes), self._rhs

    def _node_rhs_buffers(self):
        """The buffers the right-hand side's op writes besides u: the rhs ``[V, d]`` and, with
        planes, the contact stiffness ``[V, d, d]`` (kept: CUDA graphs replay into them)."""
        u = self.u
        if self.system.planes is not None and self.node_stiffness is None:
            self.node_stiffness = torch.zeros(*u.shape, u.shape[-1], dtype=u.dtype, device=u.device)
        if self._rhs is None:
            self._rhs = torch.empty_like(u)

    def _loaded_by_node_rhs(self):
        """This matvec as the right-hand side's op leaves it: the hooke tensor form keeps no
        per-element state, its node graph is its own, and only the contact stiffness is kept."""
        self.states = [None] * len(self.system.model.groups)
        self.tangents = None
        self.contact_forces = None

    def tangent(self, dx: torch.Tensor) -> torch.Tensor:
        """(dF/dx) dx ``[V, d]`` at the loaded positions (elastic and contact), with the loaded
        rotations."""
        total = self.system.model.displacement_tangent(self.u, self.states)(dx)
        if self.node_stiffness is not None:
            total = total - (self.node_stiffness * dx[:, None, :]).sum(-1)
        return total

    def forces_along(self, w: torch.Tensor) -> torch.Tensor:
        """All forces at the loaded positions plus the stiffness along ``w``: ``f(x) + (dF/dx) w
        [V, d]`` (elastic, external and contact), one pass over the elements for a linear model."""
        system = self.system
        if system.contacts and self.contact_forces is None:
            raise RuntimeError("forces_along needs the contact forces of load(x); load_step does not keep them")
        if self.tangents is not None:
            # (dF/dx) w over the node graph, the contact stiffness in its epilogue: one pass over
            # the nodes instead of an element pass that recomputes each element's differential
            from .. import ops

            if self._zero_mass is None:
                self._zero_mass = torch.zeros_like(system.mass)
            stiffness_along, _ = ops.system_matvec(system.model.groups, self.u, w, self._zero_mass, None, 0.0, -1.0,
                                                   self.states, self.node_stiffness, self.tangents, self.variants)
            elastic = ops.forces(system.model.groups[0], self.u, self.states[0], self.variants)
            total = elastic + system.external + stiffness_along
            return total if self.contact_forces is None else total + self.contact_forces
        total = system.model.linearized_forces(self.u, w, self.states) + system.external
        if self.contact_forces is not None:
            total = total + self.contact_forces - (self.node_stiffness * w[:, None, :]).sum(-1)
        return total

    def matvec_alpha(self, p: torch.Tensor, plan, cg_state, add=None):
        """A p into a buffer of this matvec and the CG step length (``cg_state.alpha``, ``.status``)
        in one fused kernel (the objects that stopped skipped): returns that buffer ``[V, d]``, or
        None where there is no fused path (then nothing was done). ``add``: a function returning
        another product's rows ``[V, d]`` that A p takes in (``ops.system_matvec_alpha``), called
        only where the fused path runs."""
        from .. import ops

        system = self.system
        if self._ap is None:
            self._ap = torch.empty_like(self.u)
        done = ops.system_matvec_alpha(system.model.groups, self.u, p, system.mass, system.free, self.mass_coef,
                                       self.stiffness_coef, self.states, self.node_stiffness, self._ap, plan, cg_state,
                                       self.tangents, self.variants, add=add)
        return self._ap if done else None

    def _one_op_args(self, cg):
        """The system's inputs to ``ops.system_cg`` when ``cg`` solves over this system's free mask."""
        system = self.system
        return cg.free is system.free, (system.model.groups, self.u, system.mass, system.free)

    def solves_in_one_op(self, cg) -> bool:
        """Whether :meth:`solve_in_one_op` runs ``cg``'s solves in one op (``ops.system_cg_serves``)."""
        from .. import ops

        same_free, args = self._one_op_args(cg)
        if self.tangents is None and self.states is None:  # not loaded yet: the graph it would have
            self._load_tangents()
        return same_free and ops.system_cg_serves(*args, self.node_stiffness, cg.state, self.tangents, self.variants)

    def solve_in_one_op(self, cg, rhs, tol: float, max_iter: int, count: int, step_end=None,
                        started: bool = False) -> bool:
        """With ``rhs [V, d]``: start ``cg`` (a ``CGSolver`` over this system's objects) from x0 = 0,
        then (with or without rhs) up to ``count`` iterations, in ONE op (``ops.system_cg``: a
        persistent kernel on the GPU, stopping on the device once every object has stopped;
        ``step_end``: as ``CGSolver.begin``; ``started``: as ``CGSolver.iterate``). Returns False,
        having done nothing, where there is no such op."""
        from .. import ops

        same_free, args = self._one_op_args(cg)
        if not same_free:
            return False
        if self._ap is None:
            self._ap = torch.empty_like(self.u)
        return ops.system_cg(*args, self.mass_coef, self.stiffness_coef, self.node_stiffness, self._ap, rhs, tol,
                             cg.plan, cg.state, max_iter, count, self.tangents, step_end, self.pipelined, self.variants,
                             started)

    def __call__(self, p: torch.Tensor):
        from .. import ops

        system = self.system
        return ops.system_matvec(system.model.groups, self.u, p, system.mass, system.free, self.mass_coef,
                                 self.stiffness_coef, self.states, self.node_stiffness, self.tangents, self.variants)


def _coefficients(opts: StepOptions):
    """(c_M, c_K) of the system matrix c_M M - c_K K: 1 + theta h r_M and theta h (theta h + r_K)."""
    h = opts.theta * opts.dt
    return 1.0 + h * opts.rayleigh_mass, h * (h + opts.rayleigh_stiffness)


def _end_positions(x: torch.Tensor, v: torch.Tensor, v_new: torch.Tensor, opts: StepOptions) -> torch.Tensor:
    """x' = x + (1 - theta) h v + theta h v' ``[V, d]`` (backward Euler: x + h v', as its kernels)."""
    if opts.theta == 1.0:
        return torch.add(x, v_new, alpha=opts.dt)
    return x + opts.old_velocity_share * v + (opts.dt - opts.old_velocity_share) * v_new


def _fold_damping(matvec: "SystemMatvec", damping, opts: StepOptions) -> None:
    """Put the planes' and tools' friction C (``contact.NodeDamping``) into the loaded matvec's
    node stiffness as h C / c_K: the step's matrix then holds h C (the friction is implicit in
    the end velocities whatever the integrator), and the products that read the node stiffness
    (CG, the imposed velocities' term) take the damper in with the contact stiffness."""
    if damping is not None:
        matvec.node_stiffness.add_(damping.matrix, alpha=opts.dt / _coefficients(opts)[1])


def _solve(system: DynamicsSystem, x, rhs, opts: StepOptions, loaded=None, pairs=None, damping=None,
           x0=None, space: Optional[SolutionSpace] = None) -> CGResult:
    """Solve the step's system linearised at ``x``; ``loaded``: the SystemMatvec already loaded at x
    (with ``damping`` folded in); ``pairs``: the body contact's pairs at x (found here when the
    system has body contact and they are not given); ``damping``: the planes' and tools' friction
    (``contact.NodeDamping``: h C joins the matrix) or None; ``x0``: the CG's initial guess (None:
    zeros); ``space``: a ``warm_start="project"`` space that gives the initial guess (in place of
    ``x0``) and takes the solution."""
    return _solve_pausing(system, x, rhs, opts, loaded, pairs, damping, x0, space)[0]


def _solve_pausing(system: DynamicsSystem, x, rhs, opts: StepOptions, loaded=None, pairs=None, damping=None,
                   x0=None, space: Optional[SolutionSpace] = None, pause_tol: Optional[float] = None):
    """:func:`_solve` pausing at the relative residual ``pause_tol`` (``CGSolver.solve``'s): returns
    (result, resume), resume None where the solve did not pause. Else ``resume(True)`` goes on to
    ``opts.cg_tol`` and returns that result (the solve to cg_tol, bit for bit), and
    ``resume(False)`` leaves the solve where it paused (``space`` then takes the paused solution);
    either is valid only before the next solve of this system. ``resume.ahead(k)`` launches k
    stretches of the resumed iterations with no host read (``CGSolver.run_ahead``), for the
    device to run while the host checks the paused solution; either resume then is unchanged."""
    mass_coef, stiffness_coef = _coefficients(opts)
    if pairs is None and system.body_contact is not None:
        pairs = system.body_contact.detect(x)
    fused = (loaded if loaded is not None
             else system.system_matvec(mass_coef, stiffness_coef, opts.pipelined, opts.variants))
    graph_key = None
    stiffness = None  # the pairs' PairStiffness, where their product is one
    if fused is None:  # a model that is not a TensorMass: the composed product
        tangent = system.tangent(x, pairs)

        def matvec(p):
            product = mass_coef * system.mass * p - stiffness_coef * tangent(p)
            return product if damping is None else product + opts.dt * damping.product(p)
    else:
        if loaded is None:
            fused.load(x)
            _fold_damping(fused, damping, opts)
        matvec, graph_key = fused, fused.graph_key
        if pairs is not None and len(pairs) and pairs.hessians is None:
            # the pairs' stiffness beside the fused product (it projects; the CG projects again), on
            # buffers kept across steps: the iterations' graphs replay with each step's pairs
            stiffness = system.pair_stiffness(pairs, stiffness_coef, opts.dt)
            graph_key = (fused.graph_key, "pairs", stiffness.capacity)
            matvec = _WithPairs(fused, stiffness)
        elif pairs is not None and len(pairs):  # the exact tangent: each step's own Hessians, eager
            graph_key = None

            def matvec(p):  # (with friction, its damping h C: minus h times its forces)
                return fused(p)[0] - stiffness_coef * pairs.dforces(p) - opts.dt * pairs.friction_forces(p)
    product = matvec  # the system's own, for the warm-start space (a JacobiScaling below scales matvec)
    if space is not None:
        space.watch(None if fused is None else fused.node_stiffness, changing=pairs is not None and len(pairs) > 0)
        x0 = space.guess(rhs if system.free is None else rhs * system.free)
    multigrid = _rest_preconditioner(system, opts, fused, matvec, pairs, mass_coef, stiffness_coef, rhs)
    if multigrid is not None:
        key = getattr(multigrid, "key", None)  # None: not capturable (cholespy's solves)
        graph_key = None if graph_key is None or key is None else (graph_key, key)
    scaling = None
    jacobi = _jacobi(system, opts, fused, pairs, mass_coef, stiffness_coef, stiffness)
    if isinstance(jacobi, JacobiScaling):  # CG on S^T A S y = S^T b, x = S y (solver.preconditioner)
        scaling = jacobi
        matvec = scaling.product(matvec)
        graph_key = None if graph_key is None else (graph_key, scaling.key)
        rhs = scaling.apply_transpose(rhs)
        x0 = None if x0 is None else scaling.unapply(x0)
    elif jacobi is not None:  # BlockJacobi: B^-1 applied inside the CG's update
        multigrid = jacobi
        graph_key = None if graph_key is None else (graph_key, jacobi.key)
    rigid = _rigid(system, opts, fused, pairs, mass_coef, stiffness_coef, jacobi)
    if rigid is not None:  # block Jacobi with the rigid bodies' coarse correction
        multigrid = rigid
        graph_key = None if graph_key is None else (graph_key, rigid.key)
    coupled = _coupled_solver(system, rhs, opts, pairs) if pairs is not None and len(pairs) else None
    if coupled is not None:
        solver, run = coupled
    elif fused is None:  # a one-off solver (batched_cg's)
        solver, run = CGSolver(system.segments, rhs.shape, rhs.dtype, rhs.device, system.free, cuda_graphs=False), None
    else:
        solver, run = system.cg_solver(rhs, opts.cuda_graphs), None

    def outcome(result: CGResult, final: bool, image: Optional[torch.Tensor] = None) -> CGResult:
        if run is not None:  # each object of a coupled run takes the run's outcome
            result = CGResult(result.solution, *(t[run] for t in (result.iterations, result.residual_norm,
                                                                  result.rhs_norm, result.converged,
                                                                  result.breakdown, result.nonfinite)))
        if scaling is not None:
            result = dataclasses.replace(result, solution=scaling.apply(result.solution))
        if space is not None and final:
            space.add(result.solution, lambda p: _projected_product(product, p, system.free), image)
        return result

    if opts.precision == "mixed":  # float64 residuals, float32 corrections (no preconditioner, no pairs, no pause)
        refinement = system.refinement(opts)
        result = refinement.solve(solver, matvec, x, rhs, x0, opts.cg_tol, opts.cg_max_iter, opts.check_every)
        # (its residual is the true one: A x = b - r, one product fewer for the space)
        image = None if space is None else solver._project(rhs) - solver.state.r
        return outcome(result, True, image), None
    result = solver.solve(matvec, rhs, x0=x0, tol=opts.cg_tol, max_iter=opts.cg_max_iter, check_every=opts.check_every,
                          graph_key=graph_key, preconditioner=multigrid, pause_tol=pause_tol)
    if not solver.paused:
        return outcome(result, True), None

    paused = outcome(result, False)

    def resume(go_on: bool) -> Optional[CGResult]:
        if go_on:
            return outcome(solver.resume(matvec, opts.cg_max_iter, opts.check_every, graph_key, multigrid), True)
        if space is not None:
            space.add(paused.solution, lambda p: _projected_product(product, p, system.free))
        return None

    def ahead(stretches: int) -> None:  # (CGSolver.run_ahead: the same solve whatever resume then does)
        solver.run_ahead(matvec, opts.cg_max_iter, opts.check_every, graph_key, multigrid, stretches)

    resume.ahead = ahead
    return paused, resume


class _WithPairs:
    """The step's product with the body contact pairs' beside the fused one (``fused``, a
    :class:`SystemMatvec`; ``stiffness``, the pairs' ``body_contact.PairStiffness``): called, A p
    ``[V, d]`` (the pairs' product added to the fused one's output in place); in the CG's
    iterations, :meth:`matvec_alpha`: the pairs' product first, then the fused product taking it
    in and ending in the step length, which skips the objects (coupled runs of bodies) that have
    stopped: the runs of a pile stop at different iterations (docs/contact.md). The same A p
    either way (the same sums in the same order)."""

    def __init__(self, fused: "SystemMatvec", stiffness):
        self.fused = fused
        self.stiffness = stiffness

    def __call__(self, p: torch.Tensor) -> torch.Tensor:
        return self.stiffness(p, add_to=self.fused(p)[0])

    def matvec_alpha(self, p: torch.Tensor, plan, cg_state) -> Optional[torch.Tensor]:
        return self.fused.matvec_alpha(p, plan, cg_state, add=lambda: self.stiffness.rows_of(p))


def _projected_product(matvec, p: torch.Tensor, free: Optional[torch.Tensor]) -> torch.Tensor:
    """A p ``[V, d]`` on the free nodes, for a product that returns A p or (A p projected, per-node
    dot) as the fused ones do."""
    out = matvec(p)
    if isinstance(out, tuple):
        return out[0]
    return out if free is None else out * free


def _rest_preconditioner(system: DynamicsSystem, opts: StepOptions, fused, matvec, pairs, mass_coef: float,
                         stiffness_coef: float, like: torch.Tensor):
    """This solve's preconditioner built from the rest matrix where ``opts.preconditioner`` asks
    for one and the model has a loaded product ``fused`` (a TensorMass), else None: the
    system's ``direct.RestCholesky`` (``"cholesky"``), or its ``preconditioner.MultigridSolve``
    loaded with this solve's product ``matvec``, node stiffness and pairs (``"multigrid"``)."""
    if fused is None or opts.preconditioner not in ("multigrid", "cholesky"):
        return None
    built = system_rest_preconditioner(system, opts.preconditioner, mass_coef, stiffness_coef, like)
    if opts.preconditioner == "cholesky":
        return built
    if system._multigrid_solve is None or system._multigrid_solve.multigrid is not built:
        system._multigrid_solve = MultigridSolve(built)
    with_pairs = pairs is not None and len(pairs) > 0
    node_stiffness = None if fused.node_stiffness is None else stiffness_coef * fused.node_stiffness
    return system._multigrid_solve.load(matvec, node_stiffness, system.free,
                                        pairs.stiffness_row_l1(stiffness_coef, opts.dt) if with_pairs else None)


def _jacobi(system: DynamicsSystem, opts: StepOptions, fused, pairs, mass_coef: float, stiffness_coef: float,
            pair_stiffness=None):
    """The system's ``preconditioner.BlockJacobi`` (B^-1, applied in the CG's update) loaded with
    this solve's diagonal blocks where ``opts.preconditioner`` asks for it (``"auto"``: where body
    contact ``pairs`` join the solve, under the coarse correction of :func:`_rigid` on 3-D bodies;
    ``"rigid"``: under that correction always) and
    the model has a loaded product ``fused`` (a TensorMass); None otherwise. ``pair_stiffness``:
    the pairs' loaded ``PairStiffness`` or None. (A ``preconditioner.JacobiScaling`` put in its
    place makes the solve CG on the scaled system.)"""
    with_pairs = pairs is not None and len(pairs) > 0
    wanted = opts.preconditioner in ("jacobi", "rigid") or (opts.preconditioner == "auto" and with_pairs)
    if fused is None or not wanted:
        return None
    if system._block_jacobi is None:
        system._block_jacobi = BlockJacobi()
    jacobi = system._block_jacobi
    # the blocks without pairs, kept for this load of the product: a step's contact rounds change
    # only the pairs (a load counter, not tensor versions: the ops write the node stiffness in place)
    key = (fused.loads, mass_coef, stiffness_coef)
    if fused.diagonal_blocks is None or fused.diagonal_blocks[0] != key:
        fused.diagonal_blocks = (key, system_diagonal_blocks(system, mass_coef, stiffness_coef, fused.node_stiffness))
    blocks = fused.diagonal_blocks[1]
    if with_pairs:  # (from the loaded PairStiffness where there is one: its entries are sorted already)
        blocks = blocks + (pair_stiffness.stiffness_blocks() if pair_stiffness is not None
                           else pairs.stiffness_blocks(stiffness_coef, opts.dt))
    if with_pairs and opts.paired_blocks and hasattr(jacobi, "paired"):  # (a JacobiScaling: each node alone)
        node_object = system.segments.node_object.to(blocks.device)
        if pair_stiffness is not None:  # its buffers keep their storage: the load may be captured
            terms = PairTerms(pair_stiffness.nodes, pair_stiffness.coef, pair_stiffness.pair_matrices,
                              pair_stiffness.key)
            return jacobi.load(blocks, terms, node_object, system.free, capture=opts.cuda_graphs)
        terms = PairTerms(pairs.nodes, pairs._coefficients(), lambda: pairs._pair_matrices(stiffness_coef, opts.dt))
        return jacobi.load(blocks, terms, node_object, system.free)
    return jacobi.load(blocks)


def _takes_rigid(system: DynamicsSystem, opts: StepOptions, with_pairs: bool) -> bool:
    """Whether the step's solve takes the rigid bodies' coarse correction (3-D bodies only):
    ``"rigid"``, and ``"auto"`` where body contact pairs join the solve (measured faster there
    than block Jacobi alone: docs/preconditioners.md, "Measured 2026-12-03")."""
    wanted = opts.preconditioner == "rigid" or (opts.preconditioner == "auto" and with_pairs)
    return wanted and system.model.rest.shape[-1] == 3


def _rigid(system: DynamicsSystem, opts: StepOptions, fused, pairs, mass_coef: float, stiffness_coef: float,
           scaling):
    """The system's ``rigid_modes.RigidModeCorrection`` loaded for this solve (on block Jacobi's
    loaded ``scaling``: a ``BlockJacobi``, or a ``JacobiScaling``) where ``opts.preconditioner`` is
    ``"rigid"``, or ``"auto"`` with body contact ``pairs``, and the bodies are 3-D; None otherwise
    (a 2-D system keeps block Jacobi alone)."""
    with_pairs = pairs is not None and len(pairs) > 0
    if scaling is None or not _takes_rigid(system, opts, with_pairs):
        return None
    if system._rigid is None:
        system._rigid = RigidModeCorrection()

    def weights():  # c_M m_i I + c_K N_i [V, 3, 3], made only where the bodies' part is
        eye = torch.eye(3, dtype=fused.u.dtype, device=fused.u.device)
        node = (mass_coef * system.mass)[:, :, None] * eye
        return node if fused.node_stiffness is None else node + stiffness_coef * fused.node_stiffness

    # A step's contact rounds solve at one load of the product: its modes and bodies' blocks stay.
    # Across steps they are lagged (RigidModeCorrection.refresh) only while the bodies' contacts
    # hold still: where the last step's first contact check found nothing to add (a pile at
    # rest). A step whose check found pairs (bodies still moving into each other) computes them
    # afresh: lagged there, the groups miss the new pairs and the iterations grow.
    body_contact = system.body_contact
    contacts_still = body_contact is not None and not body_contact.first_check_found
    return system._rigid.load(fused.u + system.model.rest, system.mass.reshape(-1), system.segments, system.free,
                              weights, scaling, pairs if with_pairs else None,
                              pairs._pair_matrices(stiffness_coef, opts.dt) if with_pairs else None,
                              kept=(id(fused), fused.loads, mass_coef, stiffness_coef),
                              lag=(mass_coef, stiffness_coef), renew=not contacts_still)


def _coupled_solver(system: DynamicsSystem, rhs, opts: StepOptions, pairs):
    """The solver when contact pairs join objects: one CG over each run of objects they join
    (``body_contact.coupled_ranges``), and ``run [B]``, each object's run (its outcome is its
    run's); None where no pair has ever joined two objects (the per-object solver applies).

    Runs merge as bodies meet and stay merged when they part (the layout is the coarsest of
    this step's and the layouts before): the layout changes at most B - 1 times in a
    simulation, so its solver, buffers and captured graphs are made a bounded number of times
    instead of at every contact that comes or goes. A merged run is one system: solving bodies
    that no longer touch together costs iterations of the slower, not correctness."""
    from ..physics.body_contact import coupled_ranges

    objects = system.segments.num_objects
    ptr = coupled_ranges(pairs, objects)
    if system._coupled_ptr is not None:  # a boundary stays only where every layout so far had one
        kept = set(system._coupled_ptr)
        ptr = [i for i in ptr if i in kept]
    system._coupled_ptr = ptr
    if len(ptr) == objects + 1:
        return None
    kept = system._coupled_cg.get(tuple(ptr))
    if kept is None:
        system._coupled_cg.clear()  # layouts only coarsen: an older one does not come back
        node_ptr = system.segments.ptr.tolist()
        lengths = [node_ptr[ptr[i + 1]] - node_ptr[ptr[i]] for i in range(len(ptr) - 1)]
        solver = CGSolver(Segments.from_lengths(lengths, rhs.device), rhs.shape, rhs.dtype, rhs.device, system.free,
                          cuda_graphs=opts.cuda_graphs)
        run = torch.repeat_interleave(torch.arange(len(ptr) - 1, device=rhs.device),
                                      torch.tensor(ptr, device=rhs.device).diff())
        kept = system._coupled_cg[tuple(ptr)] = (solver, run)
    return kept


#: What to do about each way a step's solve fails (the end of SolverError's message).
_FAILURE_HINTS = {
    "not converged": "raise cg_max_iter (None: automatic) or cg_tol, shorten dt, or pass "
                     "require_convergence=False to accept a fixed CG budget",
    "breakdown": "the system is not positive definite: inverted elements, or stvk with tangent='exact' under "
                 "compression (the default tangent='auto' avoids that); shorten dt or set substeps_on_failure",
    "non-finite": "NaN/inf: dt is too large for the stiffness or the state blew up; shorten dt or set "
                  "substeps_on_failure",
}


def _raise_if_failed(result: CGResult, opts: StepOptions, what: str):
    failed = result.breakdown | result.nonfinite
    if opts.require_convergence:
        failed = failed | ~result.converged
    if bool(failed.any()):
        status = result.status()
        iterations = result.iterations.tolist()
        residual = result.relative_residual.tolist()
        bad = []
        for i, word in enumerate(status):
            if not bool(failed[i]):
                continue
            if word == "not converged":
                word += (f": relative residual {residual[i]:.2e} > cg_tol {opts.cg_tol:g} after "
                         f"{iterations[i]} iterations (cg_max_iter {opts.cg_max_iter})")
            elif word == "breakdown":
                word += f" at iteration {iterations[i]}"
            bad.append(f"object {i}: {word}")
        kinds = [word for word in _FAILURE_HINTS if any(s == word for s, f in zip(status, failed.tolist()) if f)]
        hints = "; ".join(_FAILURE_HINTS[word] for word in kinds)
        more = f"; and {len(bad) - 10} more objects" if len(bad) > 10 else ""
        raise SolverError(f"{what} failed ({'; '.join(bad[:10])}{more}); the state was not changed. {hints}",
                          status, result)


def _step_system(system: DynamicsSystem, x, v, opts: StepOptions, imposed_velocity, matvec=None):
    """The right-hand side ``[V, d]`` of the first linear system of a step, the velocity change
    of the constrained nodes ``[V, d]`` (None when there is none to impose), and the planes' and
    tools' friction over the step (``contact.NodeDamping``, or None without). ``matvec``: the
    step's SystemMatvec, loaded here at ``x`` (its rotations and contact terms, friction
    included, are then reused by the CG: computed once per step), or None. The body contact
    pairs' part is :func:`_pairs_rhs`'s."""
    h = opts.dt
    # Constrained nodes take their imposed velocity exactly; CG solves for the free nodes only.
    # With no imposed velocity, constrained nodes are fixed: they are at rest and stay there.
    dv_imposed = None
    if system.free is not None and imposed_velocity is not None:
        dv_imposed = (1.0 - system.free) * (imposed_velocity - v)
    mass_coef, stiffness_coef = _coefficients(opts)
    # the planes' and tools' friction, lagged: the damper drive - C v_new, implicit: h (drive - C v)
    # in the right-hand side, h C in the matrix
    damping = system.friction_damping(x, v) if system.has_node_friction else None
    if matvec is not None:
        tangent = matvec.tangent
        rhs = matvec.load_step(x, v, h, opts.rayleigh_mass, opts.velocity_coefficient)
        _fold_damping(matvec, damping, opts)  # (after the right-hand side, which must not see it)
    else:
        tangent = system.tangent(x)
        rhs = system.forces(x, opts.variants) + tangent(opts.velocity_coefficient * v)
        if opts.rayleigh_mass:  # no damping term without damping
            rhs = rhs - opts.rayleigh_mass * system.mass * v
        rhs = h * rhs
    if damping is not None:
        rhs = rhs + h * damping.forces(v)
    if dv_imposed is not None:
        rhs = rhs - (mass_coef * system.mass * dv_imposed - stiffness_coef * tangent(dv_imposed))
        if damping is not None and matvec is None:  # (with a matvec, tangent has it: folded in)
            rhs = rhs - h * damping.product(dv_imposed)
    return rhs, dv_imposed, damping


def _pairs_rhs(pairs, v, dv_imposed, opts: StepOptions):
    """The body contact pairs' part ``[V, d]`` of a step's right-hand side (the rest being
    :func:`_step_system`'s without pairs): their forces and stiffness along the velocities
    ``v``, and, for the velocity change ``dv_imposed`` of the constrained nodes (or None), what
    their stiffness and friction in the matrix make of it."""
    h = opts.dt
    _, stiffness_coef = _coefficients(opts)
    rhs = h * pairs.linear_forces(opts.velocity_coefficient * v)
    if pairs.friction is not None:  # the damping -C v_new, implicit: -h C v here, h C in the matrix
        rhs = rhs + h * pairs.friction_forces(v)
    if dv_imposed is not None:
        rhs = rhs + stiffness_coef * pairs.dforces(dv_imposed)
        if pairs.friction is not None:
            rhs = rhs + h * pairs.friction_forces(dv_imposed)
    return rhs


def _raise_if_nonfinite(system: DynamicsSystem, norms: torch.Tensor, report):
    finite = torch.isfinite(norms)
    if not bool(finite.all()):
        status = ["ok" if ok else "non-finite" for ok in finite.tolist()]
        bad = [i for i, ok in enumerate(finite.tolist()) if not ok]
        raise SolverError(f"implicit Euler produced NaN/inf for objects {bad[:10]}; the state was not changed",
                          status, report)


#: ``StepOptions.integrator`` -> theta, the weight of the step's end (module docstring); BDF2's
#: solve is a backward Euler one (:func:`bdf2_step`)
INTEGRATORS = {"backward_euler": 1.0, "newmark": 0.5, "bdf2": 1.0}

#: The most steps chained with one host synchronisation (rows of StepGraphs' summary ring, for
#: small batches; fewer for large ones: the ring holds at most 2^17 object summaries).
MAX_CHAIN = 512
#: Chained steps captured in one CUDA graph (StepGraphs.run_steps): one kernel where the solve
#: computes each step's right-hand side (``solve.StepRhs``). More steps a graph only lengthen
#: the chain a failure must replay (docs/cuda-graphs.md).
STEPS_PER_GRAPH = 8


class StepGraphs:
    """One implicit Euler step (one linearisation) as device work on buffers that persist across
    steps, captured in CUDA graphs after a first eager run and replayed from then on:

        A: linearisation, right-hand side, CG set-up and its first ``check_every`` iterations, or
        the whole CG where it is one op that stops on the device (``CGSolver.solves_in_one_op``)
        (host, only when A leaves iterations to run: "is any object still iterating?",
        replaying the CG graph until none is)
        C: the new velocities and positions, their per-object norms, and the step's summary
        (CG status, iterations, residuals, norms) packed in one small buffer; done by A's solve
        in its own kernel where that is the pipelined CG (``solve.StepEnd``)
        (host: one copy of that buffer; a failed step raises and the state is unchanged)

    Where that solve also computes the right-hand side (``solve.StepRhs``: the hooke tensor
    form, no imposed velocity), a step is ONE kernel, and chained steps are one kernel for all the
    steps of a graph.

    A step then costs a few graph launches and one host synchronisation, whatever the number of
    kernels in it; its report holds host tensors (already copied, so reading them costs nothing).
    Made by :func:`implicit_euler_step` when the device is CUDA, the model is a ``TensorMass`` and
    ``newton_iters == 1``; any phase that cannot be captured runs eagerly (same arithmetic).
    """

    def __init__(self, system: DynamicsSystem, opts: StepOptions, imposed: bool):
        self.system, self.opts = system, opts
        like = system.model.rest
        self.x, self.v = torch.zeros_like(like), torch.zeros_like(like)
        self.imposed = torch.zeros_like(like) if imposed else None
        self.x_new, self.v_new = torch.zeros_like(like), torch.zeros_like(like)
        self.dv_imposed = torch.zeros_like(like)
        self.cg = system.cg_solver(like, cuda_graphs=True)
        self.norms = torch.zeros_like(self.cg.rhs_sq)
        # status, iterations, r.r, b.b, |v|^2 per object: what the host reads, in one copy
        self.summary = torch.zeros(5, self.norms.numel(), dtype=torch.float64, device=like.device)
        self.matvec = system.system_matvec(*_coefficients(opts), opts.pipelined, opts.variants)
        #: whether the solves are multigrid-preconditioned CG (:meth:`_preconditioned_solve`)
        self.preconditioned = opts.preconditioner == "multigrid"
        # Where the whole CG is one op that stops on the device, graph A holds all of it;
        # otherwise its first check_every iterations, then the host looks.
        self.first = (opts.cg_max_iter if not self.preconditioned and self.cg.solves_in_one_op(self.matvec)
                      else min(opts.check_every, opts.cg_max_iter))
        self._graphs = {}
        self._a_ends = {}  # whether graph A (by key) also does C (set when A first runs)
        self.guess = torch.zeros_like(like) if opts.warm_start != "none" else None  # the CG's initial guess
        # warm_start="project": the system's space (its guess formed in the captured start from
        # the step's right-hand side; the solution joined to it after the solve, in a graph)
        self.space = system.solution_space(opts, like) if opts.warm_start == "project" else None
        #: the float32 side of refined solves (``precision="mixed"``: :meth:`_refined_solve`), or None
        self.refinement = system.refinement(opts) if opts.precision == "mixed" else None
        # the step's right-hand side, where the solve reads it after the phase that made it
        self.rhs = torch.zeros_like(like) if self.preconditioned or self.refinement is not None else None
        self._predicted = None  # iterations of the last preconditioned solve
        self._space_kept = False  # whether a chain kept a copy of the space (rewind)
        # whether the last refined step run on its own took one round: a chained refined step
        # has one, and one that needs more fails its chain, so steps chain only while one serves
        self._one_round = True
        # Chained steps (:meth:`run_steps`): each step's summary lands in row ``ring_pos`` of
        # ``ring`` (a device counter: the captured graph needs no host index), and the new state
        # is copied back into x, v on the device, so steps follow each other with no host sync.
        # The ring's rows bound a chain: the host's work between chains (one copy of the ring,
        # the failure check) idles the GPU, so rows are many where they are cheap (a small batch:
        # the SOFA beam lost ~50 us a step between chains of 64).
        objects = self.norms.numel()
        self.ring = torch.zeros(max(1, min(MAX_CHAIN, 2 ** 17 // max(objects, 1))), 5, objects,
                                dtype=torch.float64, device=like.device)
        self.ring_pos = torch.zeros(1, dtype=torch.long, device=like.device)
        # euler_update's object counters, and one for the objects done (zero between calls)
        self.update_counter = torch.zeros(objects + 1, dtype=torch.int32, device=like.device)

    def _dv_imposed(self):
        return self.dv_imposed if self.imposed is not None and self.system.free is not None else None

    def _phase_a(self, chained: bool = False, warm: bool = False) -> bool:
        """Phase A; returns whether its solve also did phase C (a whole solve in one op that ends
        the step in its own kernel: ``solve.StepEnd``). ``chained``: as :meth:`_phase_c`;
        ``warm``: the CG starts from :attr:`guess` (its start through the ops, then its
        iterations, in one op where they have one)."""
        opts = self.opts
        rhs, dv_imposed, _ = _step_system(self.system, self.x, self.v, opts, self.imposed, self.matvec)
        if dv_imposed is not None:
            self.dv_imposed.copy_(dv_imposed)
        if warm:
            self._project_guess(rhs)
            self.cg.start(self.matvec, rhs, self.guess, opts.cg_tol, opts.cg_max_iter)
            self.cg.iterate(self.matvec, self.first, opts.cg_max_iter, started=True)
            return False
        ring = (self.ring, self.ring_pos) if chained else (None, None)
        end = solve.StepEnd(self.x, self.v, self._dv_imposed(), float(opts.dt), self.x_new, self.v_new, self.norms,
                             self.summary, *ring, chained, h_old=opts.old_velocity_share)
        self.cg.begin(self.matvec, rhs, opts.cg_tol, opts.cg_max_iter, self.first, end)
        return end.done

    def _steps_in_solve(self, count: int, chained: bool) -> bool:
        """``count`` whole steps (right-hand side, solve, end) in ONE kernel where the solve
        computes the right-hand side itself (``SystemMatvec.step_rhs_in_solve``; no imposed
        velocity): bitwise ``count`` times phases A and C, without their launches. Returns
        whether it ran (else nothing was done). ``chained``: as :meth:`_phase_c` (needed beyond
        one step)."""
        opts = self.opts
        if self.imposed is not None:
            return False
        in_solve = self.matvec.step_rhs_in_solve(opts.dt, opts.rayleigh_mass, opts.velocity_coefficient)
        if in_solve is None:
            return False
        step_rhs, rhs = in_solve
        ring = (self.ring, self.ring_pos) if chained else (None, None)
        end = solve.StepEnd(self.x, self.v, None, float(opts.dt), self.x_new, self.v_new, self.norms, self.summary,
                             *ring, chained, rhs=step_rhs, steps=count, h_old=opts.old_velocity_share)
        self.cg.begin(self.matvec, rhs, opts.cg_tol, opts.cg_max_iter, self.first, end)
        return end.done

    def _phase_c(self, chained: bool = False):
        """The new state, its per-object |v|^2 (NaN/inf anywhere in an object's new state shows
        there: x_new is x, finite, plus dt v_new) and the step's summary, in one op
        (``euler_update``); ``chained``: also into the ring's next row, and the new state back
        into x, v for the next step."""
        cg, s = self.cg, self.cg.state
        ring = (self.ring, self.ring_pos) if chained else (None, None)
        cg.native.euler_update(self.x, self.v, s.x, self._dv_imposed(), float(self.opts.dt), self.x_new, self.v_new,
                               *cg.plan.tensors(), s.status, s.iterations, s.rr, cg.rhs_sq, self.norms, self.summary,
                               s.scratch, self.update_counter, *ring, chained, self.opts.old_velocity_share)

    def _chained_steps(self, count: int, warm: bool = False):
        if self.refinement is not None:  # (one round a step: a step that needs more fails the chain)
            for _ in range(count):
                self._refined_start(warm)
                self._phase_c(chained=True)
                if warm:
                    self._add_solution()
            return
        if warm:  # (from the projection's guesses: each solution joins the space, as in step)
            for _ in range(count):
                self._phase_a(chained=True, warm=True)
                self._add_solution()
                self._phase_c(chained=True)
            return
        if self._steps_in_solve(count, chained=True):
            return
        for _ in range(count):
            if not self._phase_a(chained=True):
                self._phase_c(chained=True)

    def _single_phase_a(self, warm: bool):
        # Graph A's outcome, remembered for its replays (which run no Python)
        self._a_ends[warm] = (not warm and self._steps_in_solve(1, chained=False)) or self._phase_a(warm=warm)

    def _rhs_phase(self):
        """A preconditioned step's right-hand side into :attr:`rhs` (and the product loaded)."""
        rhs, dv_imposed, _ = _step_system(self.system, self.x, self.v, self.opts, self.imposed, self.matvec)
        if dv_imposed is not None:
            self.dv_imposed.copy_(dv_imposed)
        self.rhs.copy_(rhs)

    def _project_guess(self, rhs: torch.Tensor):
        """:attr:`guess` from the solution space where ``warm_start="project"``."""
        if self.space is not None:
            self.space.watch(self.matvec.node_stiffness)
            self.guess.copy_(self.space.guess(self.cg._project(rhs)))

    def _add_solution(self):
        """The solve's solution joined to the solution space (two products more; one after a refined
        solve, whose residual is the true one: A x = b - r)."""
        image = None if self.refinement is None else self.cg._project(self.rhs) - self.cg.state.r
        self.space.add(self.cg.state.x, lambda p: self.cg._apply(self.matvec, p)[0], image)

    def _start_phase(self, preconditioner, warm: bool):
        """A preconditioned solve's start (from :attr:`guess` where ``warm``)."""
        opts = self.opts
        if warm:
            self._project_guess(self.rhs)
        self.cg.start(self.matvec, self.rhs, self.guess if warm else None, opts.cg_tol, opts.cg_max_iter,
                      preconditioner)

    def _preconditioned_solve(self, warm: bool):
        """A multigrid-preconditioned step's solve: the right-hand side (graph), the preconditioner
        loaded with the step's node stiffness (eager: a floor's or tool's penalties reach the
        coarse levels when they change), the start (graph) and as many iterations as the last step
        took, as graphs of 2^k iterations (12 = 8 + 4: the graphs made stay few, log2 of the
        largest count, however the count varies from step to step; the iterations stop on the
        device once converged), then one host look and, while it is needed, one iteration a look."""
        opts = self.opts
        run_captured(self._graphs, "rhs", self._rhs_phase)
        mass_coef, stiffness_coef = _coefficients(opts)
        preconditioner = _rest_preconditioner(self.system, opts, self.matvec, self.matvec, None, mass_coef,
                                              stiffness_coef, self.rhs)
        count = min(self._predicted or self.first, opts.cg_max_iter)
        run_captured(self._graphs, ("start", preconditioner.key, warm),
                     lambda: self._start_phase(preconditioner, warm))
        graph_key = (self.matvec.graph_key, preconditioner.key)
        for bit in reversed(range(count.bit_length())):
            if count >> bit & 1:
                self.cg.run_iterations(self.matvec, 1 << bit, opts.cg_max_iter, graph_key, preconditioner)
        self.cg.finish(self.matvec, opts.cg_max_iter, 1, graph_key, done=count, preconditioner=preconditioner)

    def _refined_start(self, warm: bool):
        """A refined step's right-hand side (float64), A_32 loaded where the step linearises, the
        guess, the float64 start and, where a correction is one op, the first round."""
        opts = self.opts
        rhs, dv_imposed, _ = _step_system(self.system, self.x, self.v, opts, self.imposed, self.matvec)
        if dv_imposed is not None:
            self.dv_imposed.copy_(dv_imposed)
        self.rhs.copy_(rhs)
        self.refinement.load(self.x, self.matvec)
        if warm:
            self._project_guess(self.rhs)
        self.cg.start(self.matvec, self.rhs, self.guess if warm else None, opts.cg_tol, opts.cg_max_iter)
        if self.refinement.whole:
            self.refinement.round(self.cg, self.matvec, self.rhs, opts.cg_tol, opts.cg_max_iter)

    def _current_refinement(self) -> Refinement:
        """The system's refinement for these options, the graphs dropped where it is a new one (the
        model changed, a cut: they read the old float32 copy)."""
        refinement = self.system.refinement(self.opts)
        if refinement is not self.refinement:
            self.refinement = refinement
            self._graphs.clear()
        return refinement

    def _refined_solve(self, warm: bool) -> torch.Tensor:
        """A mixed-precision step's solve and end (``solver.refine``); returns the step's summary
        ``[5, B]`` (host). The start and the first round are one graph, the step's end (phase C)
        another, then the summary's read: a step the first round converges makes one host read,
        as a float64 step does. While an object is still active a round follows, each a graph
        where its correction is one op (else its float32 iterations with host looks between two
        graphs), then the end and the read again; after ``MAX_ROUNDS`` the objects still active
        are not converged."""
        opts = self.opts
        refinement = self._current_refinement()
        run_captured(self._graphs, ("refined", warm), lambda: self._refined_start(warm))
        rounds = 1 if refinement.whole else 0
        tol, max_iter = opts.cg_tol, opts.cg_max_iter
        while True:
            run_captured(self._graphs, "C", self._phase_c)
            summary = self.summary.cpu()
            if not (summary[0].numpy() == cg_ops.ACTIVE).any():
                self._one_round = rounds <= 1
                return summary
            if rounds >= MAX_ROUNDS:
                refinement.cap(self.cg)
            elif refinement.whole:
                run_captured(self._graphs, "round",
                             lambda: refinement.round(self.cg, self.matvec, self.rhs, tol, max_iter))
            else:
                run_captured(self._graphs, "prepare", lambda: refinement.prepare(self.cg, tol, max_iter))
                refinement.correct(max_iter, opts.check_every, refinement.matvec32.graph_key)
                run_captured(self._graphs, "absorb", lambda: refinement.absorb(self.cg, self.matvec, self.rhs))
            rounds += 1

    @property
    def chainable(self) -> bool:
        """Whether whole steps run with no host decision inside (every CG iteration is in graph
        A: the whole CG is one op, or ``cg_max_iter <= check_every``, with the projection's guess
        where unpreconditioned; a refined step's correction is one op and the last refined step
        run alone took one round) and no imposed velocity, so :meth:`run_steps` applies."""
        if self.imposed is not None:
            return False
        if self.refinement is not None:  # one round a step in the chain (the first is one op)
            # (not from an extrapolated guess: the host makes it, a chained step would start from
            # zero, need more rounds than the same step alone and fail every chain)
            return self.refinement.whole and self._one_round and self.opts.warm_start != "extrapolate"
        return self.first >= self.opts.cg_max_iter and (self.space is None or not self.preconditioned)

    @property
    def max_chain(self) -> int:
        """The most steps one :meth:`run_steps` call takes (rows of the summary ring)."""
        return self.ring.shape[0]

    def run_steps(self, x, v, count: int) -> torch.Tensor:
        """``count`` steps from ``x, v [V, d]`` back to back, with ONE host synchronisation at the
        end (requires :attr:`chainable`; ``count <= max_chain``). The state after the last step
        is left in ``self.x, self.v`` whatever happened: the caller checks each step's summary
        (:meth:`failure`) before committing anything, and the kernels are deterministic, so
        running the first k of these steps again gives the same state bit for bit (after
        :meth:`rewind` where the steps join their solutions to a projection's space). Refined
        steps (``precision="mixed"``) make one round each: one that leaves an object active
        fails (its summary's status is active) and runs alone, with its rounds.

        Returns the summaries ``[count, 5, B]`` (float64, host): status, iterations, r.r, b.b,
        |v|^2 per object."""
        if self.refinement is not None:
            self._current_refinement()
        if not self.chainable or not 1 <= count <= self.max_chain:
            raise ValueError(f"run_steps: count must be in [1, {self.max_chain}] on chainable step graphs")
        self.x.copy_(x)
        self.v.copy_(v)
        self.ring_pos.zero_()
        warm = self._keep_space()
        done = 0
        while done < count:
            # STEPS_PER_GRAPH steps per graph launch where they fit, else one: a step is only 3
            # kernels, and a launch per phase cost the SOFA beam ~20% of its step time
            steps = STEPS_PER_GRAPH if count - done >= STEPS_PER_GRAPH else 1
            run_captured(self._graphs, ("chain", steps, warm), lambda steps=steps: self._chained_steps(steps, warm))
            done += steps
        return self.ring[:count].cpu()

    def _keep_space(self) -> bool:
        """Before a chain: whether its steps start from the solution space's guesses (the space
        emptied where the model changed, as :meth:`step` does), and a copy of the space as the
        chain finds it (``SolutionSpace.keep``: for :meth:`rewind`)."""
        if self.space is None or self.system.solution_space(self.opts, self.x) is not self.space:
            return False
        self.space.keep()
        self._space_kept = True
        return True

    def rewind(self) -> None:
        """After a chain in which a step failed: the solution space as the chain found it (every
        chained step joined its solution to it), so that its good steps run again give the same
        guesses, hence the same states, and the failed one runs on its own from there."""
        if self._space_kept:
            self.space.rewind()

    # The host-side reading of the summaries below is numpy, not torch: each torch CPU op on a
    # [B]-long vector wakes torch's intra-op thread pool, and on a many-core host that cost a batch
    # of 250,000 bodies more than the GPU step itself (docs/distributed.md, "Batches"). numpy runs
    # these few vector ops on the calling thread.

    def report_of(self, summary: torch.Tensor) -> StepReport:
        """The :class:`StepReport` of the step whose summary ``[5, B]`` (host) is given; its CG
        solution is the CG buffer (the last solve's)."""
        status, iterations, rr, rhs_sq, _ = summary.numpy()
        result = CGResult(self.cg.state.x.clone(), torch.from_numpy(iterations.astype(np.int64)),
                          torch.from_numpy(np.sqrt(np.maximum(rr, 0.0))), torch.from_numpy(np.sqrt(rhs_sq)),
                          torch.from_numpy(status == cg_ops.CONVERGED), torch.from_numpy(status == cg_ops.BREAKDOWN),
                          torch.from_numpy(status == cg_ops.NONFINITE))
        return StepReport(cg=[result])

    def failure(self, summary: torch.Tensor) -> bool:
        """Whether the step of this summary ``[5, B]`` failed (what :meth:`step` raises on)."""
        return _first_failure(summary[None].numpy(), self.opts.require_convergence) == 0

    def first_failure(self, summaries: torch.Tensor) -> int:
        """The index of the first failed step of ``summaries [n, 5, B]`` (host), or n if none
        failed: one vectorised check (a chain's steps are checked together)."""
        return _first_failure(summaries.numpy(), self.opts.require_convergence)

    def step(self, x, v, imposed_velocity=None, guess=None):
        """One step from ``x, v [V, d]`` (``imposed_velocity [V, d]`` and ``guess [V, d]`` or None,
        as :func:`implicit_euler_step`): returns (x_new, v_new, StepReport) or raises SolverError."""
        self.x.copy_(x)
        self.v.copy_(v)
        if self.imposed is not None:
            self.imposed.copy_(imposed_velocity)
        warm = guess is not None and self.guess is not None
        if warm:
            self.guess.copy_(guess)
        if self.space is not None:  # (emptied, in place, where the model changed: the graphs stay valid)
            warm = self.system.solution_space(self.opts, self.x) is self.space
        opts = self.opts
        if self.refinement is not None:  # (the step's end and its host reads are the solve's)
            summary = self._refined_solve(warm)
            if self.space is not None and warm:  # launched after the last read: nothing waits on it
                run_captured(self._graphs, "add", self._add_solution)
        else:
            ends_step = False
            if self.preconditioned:
                self._preconditioned_solve(warm)
            else:
                run_captured(self._graphs, ("A", warm), lambda: self._single_phase_a(warm))
                ends_step = self._a_ends[warm]
                self.cg.finish(self.matvec, opts.cg_max_iter, opts.check_every, self.matvec.graph_key,
                               done=self.first)
            if self.space is not None and warm:
                run_captured(self._graphs, "add", self._add_solution)
            if not ends_step:  # also after a failed solve: its output is discarded
                run_captured(self._graphs, "C", self._phase_c)
            summary = self.summary.cpu()  # the step's one synchronisation
        report = self.report_of(summary)
        if self.preconditioned:
            self._predicted = max(1, int(summary[1].numpy().max()))
        if self.failure(summary):  # (checked in numpy; the raising paths then name the objects)
            _raise_if_failed(report.cg[0], opts, "implicit Euler CG")
            _raise_if_nonfinite(self.system, summary[4], report)
        return self.x_new.clone(), self.v_new.clone(), report


def _first_failure(summaries: np.ndarray, require_convergence: bool) -> int:
    """The index of the first failed step of the host summaries ``[n, 5, B]`` (rows: status,
    iterations, rr, rhs_sq, state norms), or n if none failed."""
    status, norms = summaries[:, 0], summaries[:, 4]
    # (active: a chained refined step that one round left short of the tolerance; it runs alone)
    bad = (status == cg_ops.BREAKDOWN) | (status == cg_ops.NONFINITE) | (status == cg_ops.ACTIVE) | ~np.isfinite(norms)
    if require_convergence:
        bad |= status != cg_ops.CONVERGED
    failed = np.flatnonzero(bad.any(axis=1))
    return int(failed[0]) if failed.size else summaries.shape[0]


#: Stretches (``check_every`` iterations each) of a paused solve launched before a contact check
#: that runs beside them (:func:`_check_beside`): enough to keep the device busy while the host
#: launches the check, few enough that a check that finds pairs wastes little.
CHECK_AHEAD_STRETCHES = 2


def _checks_beside(x: torch.Tensor) -> bool:
    """Whether a contact check runs beside its paused solve's next iterations (on the GPU: a
    stream of its own; the CPU gains nothing from launching them first)."""
    return x.device.type == "cuda"


@contextlib.contextmanager
def _check_beside(system: DynamicsSystem, paused, x: torch.Tensor):
    """Run the body of the ``with`` (a contact check of a paused solve) beside ``paused``'s next
    ``system.check_ahead`` stretches of iterations (``resume`` of :func:`_solve_pausing`; None, or
    no stretches: the body runs as it stands). The iterations are launched first
    (``resume.ahead``) on the current stream; the body's device work runs on the system's side
    stream, which first waits for what was launched before them (the solve's end positions).
    When the body ends the host waits for the side stream, so that what the check made is ready
    for the current stream's later work; and since that stream allocates nothing while the
    check runs, no memory the check reads is reused under it. The check reads nothing the
    iterations write and writes nothing they read. (Where the device is not a GPU, taken only
    when a test asks for it: the iterations first, then the body, in order.)"""
    if paused is None or system.check_ahead < 1 or not _checks_beside(x):
        yield
        return
    if x.device.type != "cuda":
        paused.ahead(system.check_ahead)
        yield
        return
    ready = torch.cuda.Event()
    ready.record(torch.cuda.current_stream(x.device))
    paused.ahead(system.check_ahead)
    if system._check_stream is None or system._check_stream.device != x.device:
        system._check_stream = torch.cuda.Stream(x.device)
    side = system._check_stream
    side.wait_event(ready)
    try:
        with torch.cuda.stream(side):
            yield
    finally:
        side.synchronize()


def step_graphs_for(system: DynamicsSystem, opts: StepOptions, imposed: bool):
    """The system's :class:`StepGraphs` for these options, or None where they do not apply."""
    from ..physics.tensor_mass import TensorMass

    # body contact's pairs change in number from step to step: its steps run eagerly
    if (not opts.cuda_graphs or opts.newton_iters != 1 or not isinstance(system.model, TensorMass)
            or opts.integrator == "bdf2"  # (bdf2_step's backward Euler steps have their own)
            or system.body_contact is not None or opts.preconditioner in ("jacobi", "rigid", "cholesky")
            or system.model.rest.device.type != "cuda"
            or not hasattr(cg_ops.native_ops_for(system.model.rest), "euler_update")):
        return None
    key = (opts.dt, opts.rayleigh_mass, opts.rayleigh_stiffness, opts.cg_tol, opts.cg_max_iter,
           opts.require_convergence, opts.check_every, opts.pipelined, opts.variants, opts.integrator,
           opts.preconditioner == "multigrid", opts.warm_start, opts.precision, imposed)
    graphs = system._step_graphs.get(key)
    if graphs is None:
        graphs = system._step_graphs[key] = StepGraphs(system, opts, imposed)
    return graphs


def bdf2_step(system: DynamicsSystem, x, v, previous, opts: StepOptions, imposed_velocity=None, guess=None):
    """One BDF2 step from ``x, v [V, d]`` and the state one step of the same dt before,
    ``previous = (x_prev, v_prev)`` (None: the first step, backward Euler's). BDF2,

        3/2 x' - 2 x + 1/2 x_prev = h v',    M (3/2 v' - 2 v + 1/2 v_prev) = h F(x', v'),

    is backward Euler from the extrapolated state x^ = (4 x - x_prev) / 3, v^ = (4 v - v_prev) / 3
    with the step h' = 2 h / 3: x' = x^ + h' v', M (v' - v^) = h' F(x', v'). So its steps are
    backward Euler steps of other inputs, on every path the backward Euler step has (captured
    steps, preconditioners, contact, Newton iterations). ``imposed_velocity``: the constrained
    nodes' v' (with ``previous``, the velocity that takes them from x^ to their target over h').
    ``guess``: as :func:`implicit_euler_step`. Returns what :func:`implicit_euler_step` returns."""
    if previous is None:
        return implicit_euler_step(system, x, v, dataclasses.replace(opts, integrator="backward_euler"),
                                   imposed_velocity, guess)
    x_hat, v_hat = bdf2_extrapolation(x, v, previous)
    return implicit_euler_step(system, x_hat, v_hat, bdf2_options(opts), imposed_velocity, guess)


def bdf2_extrapolation(x: torch.Tensor, v: torch.Tensor, previous) -> tuple:
    """(x^, v^) = ((4 x - x_prev) / 3, (4 v - v_prev) / 3) ``[V, d]`` (:func:`bdf2_step`)."""
    x_prev, v_prev = previous
    return (4.0 * x - x_prev) / 3.0, (4.0 * v - v_prev) / 3.0


def bdf2_options(opts: StepOptions) -> StepOptions:
    """The backward Euler step a BDF2 step with ``opts`` is: dt' = 2 dt / 3."""
    return dataclasses.replace(opts, dt=2.0 * opts.dt / 3.0, integrator="backward_euler")


def implicit_euler_step(system: DynamicsSystem, x, v, opts: StepOptions, imposed_velocity=None, guess=None):
    """One step from positions/velocities ``x, v [V, d]``.

    Args:
        imposed_velocity: ``[V, d]`` velocities at the end of the step of the constrained nodes;
            ignored elsewhere. None: every constrained node is fixed (and at rest).
        guess: ``[V, d]`` the first solve's initial guess of its solution (the free nodes' velocity
            change beyond the imposed one), or None (zeros); used where ``opts.warm_start`` is
            ``"extrapolate"`` (with ``"project"`` the system's ``SolutionSpace`` gives it).

    Returns:
        (x_new, v_new, StepReport). Raises SolverError, leaving inputs untouched, when a solve
        fails or the new state is not finite.
    """
    if opts.integrator == "bdf2":
        raise ValueError("a BDF2 step needs the state before: use bdf2_step")
    if opts.warm_start != "extrapolate":
        guess = None
    graphs = step_graphs_for(system, opts, imposed_velocity is not None)
    if graphs is not None:
        return graphs.step(x, v, imposed_velocity, guess)
    h = opts.dt
    report = StepReport()
    loaded = system.system_matvec(*_coefficients(opts), opts.pipelined, opts.variants)
    # the body contact's pairs where the step linearises (without a matvec the system finds them)
    near = pairs = None
    if system.body_contact is not None and loaded is not None:
        near, active, pairs = system.body_contact.at_state(x, v, h)
    rhs, dv_imposed, damping = _step_system(system, x, v, opts, imposed_velocity, loaded)  # loads it at x
    space = system.solution_space(opts, x) if opts.warm_start == "project" else None
    # Contact(check_tol): a solve whose end a contact-set check reads pauses at check_tol; where
    # the check adds nothing, it goes on to cg_tol (the same iterations as one solve), else the
    # round solves again from the paused solution. Where nothing is within reach at the start (a
    # check then rarely adds a pair) and in the last round, no solve pauses.
    rounds = system.body_contact.settings.rounds if near is not None else 0
    check_tol = system.body_contact.settings.check_tol if rounds else None

    def with_pairs(pairs):  # the right-hand side with the pairs' terms
        return rhs if pairs is None or not len(pairs) else rhs + _pairs_rhs(pairs, v, dv_imposed, opts)

    def end_velocity(solution):
        return v + solution if dv_imposed is None else v + dv_imposed + solution

    result, resume = _solve_pausing(system, x, with_pairs(pairs), opts, loaded, pairs, damping, x0=guess, space=space,
                                    pause_tol=check_tol if rounds and len(near) else None)
    report.cg.append(result)
    _raise_if_failed(result, opts, "implicit Euler CG")
    v_new = end_velocity(result.solution)
    if near is not None:
        report.contact_solves = [(pairs, v_new)]

    # The contact set: the pairs were chosen by the gap each would have at the end of the step at
    # the step's starting velocities, but the solve changes the velocities (the other pairs'
    # forces, the floor, a bounce) and a pair left out has no force at all, whatever its end
    # gap: a vertex separating at the start can be driven through the other surface in one step.
    # So the step is solved again (from the last solution) with every nearby pair whose linear
    # end gap g + h u . J v_new is below -tolerance (SurfaceContact.tolerance: an end gap just
    # short of zero is left to the next step, which finds the pair in contact) joined to the set,
    # and with the pairs whose vertex ends deeper than their linear model says (a slide over a
    # crease or a turning triangle) linearised where it ends (SurfaceContact.relinearise), by
    # the same tolerance. A (vertex, body) in the set stays
    # in it (a pair whose end gap comes out positive keeps its force, as a predicted pair does;
    # re-linearising replaces its pair, never removes it); a step that misses nothing is solved
    # once, and at most Contact.rounds more solves follow.
    # The settled test (one host read, a detection's worth of reductions) only skips a check that
    # would find nothing, so whether it runs changes no result; after a step whose first check
    # found pairs (a pile still jostling) it nearly always fails, and that step goes straight to
    # the check (SurfaceContact.first_check_found); after tests that failed in a row (a pile
    # still creeping) the next waits a few steps (SurfaceContact.settled_if_due).
    # The check beside the resumed solve: where the last step's first check found nothing (a
    # pile at rest, whose checks nearly always find nothing), the paused solve's next iterations
    # are launched before the check, which runs on a side stream (_check_beside): the device
    # iterates while the host launches the check's many small ops and reads its outcome. The
    # same solve and the same check either way; a check that does find pairs wastes those
    # iterations.
    for round_ in range(rounds):
        dx = h * v_new if opts.theta == 1.0 else _end_positions(x, v, v_new, opts) - x
        at_rest = round_ == 0 and not system.body_contact.first_check_found
        with _check_beside(system, resume if at_rest else None, x):
            if at_rest and system.body_contact.settled_if_due(x, dx, near, active):
                break  # the bodies' motion provably leaves nothing for the check to find
            # a round's own solve is checked for deep misses only (Contact.recheck_tolerance)
            tolerance = system.body_contact.tolerance if round_ == 0 else system.body_contact.recheck_tolerance
            missed = ~active & (near.end_gap(dx) < -tolerance)
            near, active, moved = system.body_contact.relinearise(x, dx, near, active | missed, v,
                                                                  solution=len(report.contact_solves) - 1,
                                                                  tolerance=tolerance, later=round_ < rounds - 1)
            found = moved or bool(missed.any())
        if round_ == 0:
            system.body_contact.first_check_found = found
        if not found:
            break
        if resume is not None:
            resume(False)
        pairs = system.body_contact.select(x, near, active.nonzero().squeeze(1))
        result, resume = _solve_pausing(system, x, with_pairs(pairs), opts, loaded, pairs, damping,
                                        x0=result.solution, pause_tol=check_tol if round_ < rounds - 1 else None)
        report.cg.append(result)
        _raise_if_failed(result, opts, "implicit Euler CG (contact set)")
        v_new = end_velocity(result.solution)
        report.contact_solves.append((pairs, v_new))
    if resume is not None:  # the last solve paused for a check that found nothing: on to cg_tol
        result = report.cg[-1] = resume(True)
        _raise_if_failed(result, opts, "implicit Euler CG")
        v_new = end_velocity(result.solution)
        report.contact_solves[-1] = (pairs, v_new)

    for _ in range(opts.newton_iters - 1):
        x_new = torch.add(x, v_new, alpha=h)
        residual = (system.mass * (v_new - v) - h * system.forces(x_new, opts.variants)
                    + h * opts.rayleigh_mass * system.mass * v_new
                    - h * opts.rayleigh_stiffness * system.dforces(x_new, v_new))
        if damping is not None:
            residual = residual - h * damping.forces(v_new)
        result = _solve(system, x_new, -residual, opts, damping=damping)
        report.cg.append(result)
        _raise_if_failed(result, opts, "Newton iteration CG")
        v_new = v_new + result.solution

    x_new = _end_positions(x, v, v_new, opts)
    _raise_if_nonfinite(system, system.segments.sum(x_new.abs() + v_new.abs()), report)
    return x_new, v_new, report
