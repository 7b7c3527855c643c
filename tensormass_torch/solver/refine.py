"""Mixed precision: a float64 step whose CG iterations run in float32 (iterative refinement).

A float32 step cannot be converged to 1e-6 in any meaningful sense: near equilibrium its
right-hand side b = h (f + h K v) is the small difference of large forces, and computed in
float32 it carries new rounding of 1e-4-1e-3 of itself at every step (docs/preconditioners.md,
"Float64 gains, float32 does not"). A float64 step knows b and can verify 1e-6, but each of its
iterations reads twice the bytes. Refinement keeps in float64 what must be exact (the state, the
right-hand side, the warm start and the residuals) and does the iterations in float32:

    x = x0                                       (the step's guess, float64)
    r = b - A x;  stop where |r| <= tol |b|      (float64)
    repeat:  d = CG_32(A_32 d = r_32) from 0, to max(INNER_TOL |r|, tol |b| / 2)
             x = x + d;  r = b - A x;  stop where |r| <= tol |b|

where A_32 is the same step matrix built by a float32 copy of the model. Each round cuts the
float64 residual by about INNER_TOL (the correction's own accuracy, float32's roundoff bounds it
far below that) until the float64 tolerance holds: the step is then converged exactly as a
float64 CG step is, the same stopping rule on the same residual, at the cost of float32
iterations and one float64 product a round.

Invariants:
- The float64 solver's state is the solve's: ``x`` the solution, ``r`` its float64 residual,
  ``rr`` = r.r, ``threshold`` = tol^2 b.b, ``status`` and ``iterations`` (the sum of the float32
  iterations); its reports, the step's end and the warm-start space read it as they read a plain
  solve's.
- An object that stopped (converged, or failed: a correction's breakdown or NaN becomes its
  status) gets an infinite correction threshold (``cg_start_status``'s gate): its float32 solve
  stops at once and its correction stays zero.
- Every round is device work on buffers that keep their storage, with no host read: the
  captured steps (``implicit_euler.StepGraphs``) replay it as a graph.

Scope: TensorMass models with planes and tools (their penalties reach A_32 through the float64
product's node stiffness), unpreconditioned corrections (the float32 CG runs the pipelined
whole-solve op on the GPU where it serves), no body contact (its pairs' product is not in the
float32 copy): the simulator refuses the rest with one error.
"""
from __future__ import annotations

import copy
from typing import Optional

import torch

from ..ops import cg as cg_ops
from ..ops.cg import ACTIVE, CAPPED
from .cg import CGResult, CGSolver

#: each float32 correction's tolerance relative to the float64 residual it corrects: a round cuts
#: the residual about this much (1e-6 from a guess at 1e-3 of b: one round)
INNER_TOL = 1e-3
#: the most corrections a solve makes; one still short of the tolerance is then "not converged"
MAX_ROUNDS = 10
#: what ``StepOptions.precision`` takes: every solve in the state's dtype, or refinement
PRECISIONS = ("full", "mixed")


def float32_system(system):
    """A ``DynamicsSystem`` like ``system`` (float64) in float32: a copy of its model, masses,
    external forces and free-node mask (the step matrix A_32 of the corrections). No contact terms:
    their stiffness is the float64 product's, copied in (:meth:`Refinement.load`)."""
    from .implicit_euler import DynamicsSystem

    model = copy.deepcopy(system.model).to(torch.float32)
    constrained = (torch.zeros(system.mass.shape[0], dtype=torch.bool, device=system.mass.device)
                   if system.free is None else system.free[:, 0] == 0)
    return DynamicsSystem(model, system.mass[:, 0].to(torch.float32), system.external.to(torch.float32),
                          system.segments, constrained, keep_mask=system.free is not None)


class Refinement:
    """The float32 side of a float64 system's refined solves: a float32 copy of the system, its
    product and CG solver, and the buffers a round reads (kept: graphs replay over them).

    Args:
        system: the float64 ``DynamicsSystem`` (a TensorMass model).
        mass_coef, stiffness_coef: the step matrix's coefficients; pipelined, variants: as the
            float64 product's (``StepOptions``).
        cuda_graphs: whether the float32 solver captures its iterations (CUDA only).
    """

    def __init__(self, system, mass_coef: float, stiffness_coef: float, pipelined: bool, variants,
                 cuda_graphs: bool):
        self.system32 = float32_system(system)
        like = self.system32.model.rest
        self.matvec32 = self.system32.system_matvec(mass_coef, stiffness_coef, pipelined, variants)
        self.cg32: CGSolver = self.system32.cg_solver(like, cuda_graphs)
        self.x32 = torch.zeros_like(like)  # the float64 positions rounded, where A_32 is linearised
        # each correction's least threshold [B]: tol^2 b.b / 4 of the float64 solve, rounded
        self.floor32 = torch.zeros_like(self.cg32.state.rr)
        self._whole = None  # (node stiffness absent, whole) once asked: see whole
        #: each correction's tolerance relative to the residual it corrects (read when a round is
        #: captured: set it before the first step)
        self.inner_tol = INNER_TOL

    @property
    def whole(self) -> bool:
        """Whether a correction is one op that stops on the device (then a round has no host read).
        Asked once a step, answered once per form of the float32 product (with or without node
        stiffness): the copy's other inputs are fixed for its life."""
        form = self.matvec32.node_stiffness is None
        if self._whole is None or self._whole[0] != form:
            self._whole = (form, self.cg32.solves_in_one_op(self.matvec32))
        return self._whole[1]

    def load(self, x: torch.Tensor, matvec) -> None:
        """Linearise A_32 at ``x [V, d]`` (float64) as ``matvec`` (the float64 product, loaded
        there) is: its node stiffness (the planes' and tools' penalties, friction) is copied into a
        buffer of the float32 product (made at the first load, kept: graphs replay over it), so
        the two matrices differ by rounding only."""
        self.x32.copy_(x)
        self.matvec32.load(self.x32)
        if matvec.node_stiffness is not None:
            if self.matvec32.node_stiffness is None:
                self.matvec32.node_stiffness = torch.empty_like(matvec.node_stiffness, dtype=torch.float32)
            self.matvec32.node_stiffness.copy_(matvec.node_stiffness)

    def prepare(self, cg: CGSolver, tol: float, max_iter: int) -> None:
        """A correction's start, as ``CGSolver.start`` from x0 = 0 leaves it: x_32 = 0, r_32 = p_32 =
        r (rounded; r is projected already), r_32.r_32 for its b.b and r.r, the threshold
        max(inner_tol^2 r.r, tol^2 b.b / 4) (no tighter than the float64 tolerance needs) and
        infinite for the objects the float64 solve stopped (they do not iterate: their
        correction stays zero), the statuses (``cg_ops.start_status``: one op for them all)."""
        s, t = cg.state, self.cg32.state
        t.x.zero_()
        t.r.copy_(s.r)
        cg_ops.object_dot(t.r, t.r, self.cg32.plan, t.rhs_sq, t, self.cg32.native)
        t.rr.copy_(t.rhs_sq)
        torch.mul(cg.rhs_sq, 0.25 * tol * tol, out=self.floor32)
        cg_ops.start_status(t, self.inner_tol ** 2, max_iter, self.cg32.native, floor=self.floor32, gate=s.status)
        t.p.copy_(t.r)

    def correct(self, max_iter: int, check_every: int, graph_key=None) -> None:
        """The correction's float32 CG: one op where it serves, else iterations with host looks."""
        if self.whole:
            self.cg32.iterate(self.matvec32, max_iter, max_iter, started=True)
        else:
            self.cg32.finish(self.matvec32, max_iter, check_every, graph_key)

    def absorb(self, cg: CGSolver, matvec, rhs: torch.Tensor) -> None:
        """x += d (zero for the objects that had stopped); the new float64 residual and its r.r;
        for the objects still active, the correction's iterations and failures, else the status of
        the new r.r (``cg_ops.round_end``: one op)."""
        s = cg.state
        s.x.add_(self.cg32.state.x)
        av = cg._apply(matvec, s.x)[0]
        torch.sub(cg._project(rhs), av, out=s.r)
        cg_ops.object_dot(s.r, s.r, cg.plan, s.rr, s, cg.native)
        cg_ops.round_end(s, self.cg32.state, cg.native)

    def round(self, cg: CGSolver, matvec, rhs: torch.Tensor, tol: float, max_iter: int, check_every: int = 8) -> None:
        """One correction of ``cg``'s solve of ``matvec`` x = ``rhs`` (float64)."""
        self.prepare(cg, tol, max_iter)
        self.correct(max_iter, check_every)
        self.absorb(cg, matvec, rhs)

    @staticmethod
    def cap(cg: CGSolver) -> None:
        """Objects still active after the last round: not converged (``CAPPED``)."""
        s = cg.state
        s.status.copy_(torch.where(s.status == ACTIVE, CAPPED, s.status))

    def solve(self, cg: CGSolver, matvec, x: torch.Tensor, rhs: torch.Tensor, x0: Optional[torch.Tensor],
              tol: float, max_iter: int, check_every: int) -> CGResult:
        """The refined solve of ``matvec`` (float64, loaded at ``x``) y = ``rhs [V, d]`` from ``x0``
        (None: zeros), with a host look after each round (the eager steps')."""
        self.load(x, matvec)
        cg.start(matvec, rhs, x0, tol, max_iter)
        for _ in range(MAX_ROUNDS):
            if not cg.any_active():
                break
            self.round(cg, matvec, rhs, tol, max_iter, check_every)
        self.cap(cg)
        return cg.result()


__all__ = ["INNER_TOL", "MAX_ROUNDS", "PRECISIONS", "Refinement", "float32_system"]
