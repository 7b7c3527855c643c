"""Conjugate gradient, batched over packed objects with per-object scalars, resident on the device.

Each object has its own alpha, beta, residual and status: a stiff object that needs many
iterations neither holds back (its neighbours stop updating once converged) nor pollutes (no
scalar is shared) the others. The stopping rule, per object b:

    ||r_b|| <= tol * ||rhs_b||          (the residual ratio, not its square)

tested after every iteration on the device (``cg_ops.cg_update``); an object also stops when its
curvature p.Ap is not positive (an indefinite system, e.g. a compressed ``stvk`` body at a large
step: "breakdown"), when its scalars turn NaN/inf ("non-finite") or at the iteration cap.

An iteration is a fixed sequence of device work (the matvec, then ``cg_alpha``, ``cg_update``,
``cg_direction`` on persistent buffers) with no host synchronisation; the host only looks every
``check_every`` iterations to see whether any object is still active, so the iterates never
depend on it. With a ``graph_key`` on a CUDA device, the ``check_every`` iterations are captured
once in a CUDA graph and replayed: one launch instead of hundreds, no Python per iteration.

Where the matvec has a whole-solve op (``SystemMatvec.solve_in_one_op``: the hooke tensor form,
``ops.system_cg``), the start and every iteration run as that one op instead (on the GPU one
persistent kernel that stops on the device once no object is active): bitwise the same iterates,
and no host check at all.

With a ``preconditioner`` (z = M^-1 r, symmetric positive definite per object), an iteration is
preconditioned CG instead: alpha = r.z / p.Ap, p = z + beta p with beta = r'.z' / r.z, the
stopping rule still on the true residual ||r_b||. It runs through the same ops (the step
length's op reads r.z where it reads r.r, the direction's reads z where it reads r) with r.z
and beta beside them: no host synchronisation either, so its iterations are captured the same
way (where the preconditioner's own ops can be).

A block diagonal preconditioner B (one d x d block a node: block Jacobi) is applied inside
``cg_update`` instead (z = B^-1 r with the update, no launch of its own), and the iteration keeps
r.z where the plain one keeps r.r: the step length, the stopping rule and beta read it, so the
tolerance holds the residual in B^-1's norm, sqrt(r.B^-1 r) <= tol sqrt(b.B^-1 b) (the rows a
penalty makes stiff weigh less: their residual costs the least motion).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from types import SimpleNamespace
from typing import Callable, Dict, List, Optional, Tuple, Union

import torch

from ..ops import cg as cg_ops
from ..ops.cg import ACTIVE, BREAKDOWN, CAPPED, CONVERGED, NONFINITE, STATUS_WORDS, CGState
from ..ops.segments import ChunkPlan, Segments
from .capture import run_captured
from .preconditioner import block_diagonal_product

Matvec = Callable[[torch.Tensor], Union[torch.Tensor, Tuple[torch.Tensor, torch.Tensor]]]


@dataclass
class CGResult:
    """Outcome of a batched CG solve (per-object tensors ``[B]``)."""

    solution: torch.Tensor
    iterations: torch.Tensor
    residual_norm: torch.Tensor
    rhs_norm: torch.Tensor
    converged: torch.Tensor
    breakdown: torch.Tensor
    nonfinite: torch.Tensor

    def status(self) -> List[str]:
        """One word per object: converged, not converged, breakdown, non-finite."""
        out = []
        for conv, brk, bad in zip(self.converged.tolist(), self.breakdown.tolist(), self.nonfinite.tolist()):
            out.append("non-finite" if bad else "breakdown" if brk else "converged" if conv else "not converged")
        return out

    @property
    def relative_residual(self) -> torch.Tensor:
        return self.residual_norm / torch.clamp(self.rhs_norm, min=torch.finfo(self.rhs_norm.dtype).tiny)


def _check_settings(tol, max_iter, check_every):
    if max_iter < 0 or tol < 0 or check_every < 1:
        raise ValueError(f"bad CG settings: max_iter={max_iter}, tol={tol}, check_every={check_every}")


class CGSolver:
    """A batched CG over fixed packed objects, with its buffers (and CUDA graphs) kept across solves.

    Args:
        segments: the objects' node ranges.
        shape: ``(V, d)`` of the unknowns; dtype, device: theirs.
        free: ``[V, 1]`` mask (1 free, 0 constrained) or None. Constrained rows are projected out:
            the solve runs on free nodes and leaves ``x0`` there.
        chunk_nodes: nodes per chunk (one GPU block) of the reductions and updates (None: from the
            node count, ``ChunkPlan.auto_chunk_nodes``).
        cuda_graphs: capture the iterations of solves that pass a ``graph_key`` (CUDA only).
    """

    def __init__(self, segments: Segments, shape, dtype, device, free: Optional[torch.Tensor] = None,
                 chunk_nodes: Optional[int] = None, cuda_graphs: bool = True):
        self.segments = segments.to(device)
        self.plan = ChunkPlan.from_segments(self.segments, chunk_nodes)
        self.state = CGState.empty(self.plan, tuple(shape), dtype, torch.device(device))
        self.rhs_sq = self.state.rhs_sq
        self.free = free
        self.native = cg_ops.native_ops_for(self.state.x)
        # Graphs only over the compiled ops: the pure-torch reference reduces with segment_reduce,
        # which synchronises with the host and cannot be captured (a failed capture would leave
        # torch's CUDA generator expecting a graph).
        self.cuda_graphs = bool(cuda_graphs) and self.state.x.device.type == "cuda" and self.native is not None
        self._graphs: Dict[tuple, object] = {}
        self.graph_replays = 0
        self._pcg = None  # the preconditioned iteration's buffers, made at its first use
        self._block = None  # the block-preconditioned iteration's (_block_buffers)
        self._items = None  # (bodies' node ranges, each object's range of bodies): _coarse_items
        self._pair_items: Optional[torch.Tensor] = None  # each object's range of paired blocks (_load_pair_items)
        self._pair_sums: Optional[torch.Tensor] = None  # r.D r + the pairs' part, before a coarse part
        self._rhs = None  # the right-hand side a captured start reads (preconditioned solves)
        self._paused = None  # a paused solve's (iterations run, pause threshold [B]) (see solve)

    def _project(self, v):
        return v if self.free is None else v * self.free

    def _apply(self, matvec: Matvec, v: torch.Tensor):
        """(A v projected ``[V, d]``, v . Av per node ``[V]``); v is already projected."""
        return self._with_dots(matvec(v), v)

    def _with_dots(self, out, v: torch.Tensor):
        """A product's ``out`` for ``v`` as (A v projected, v . Av per node): a fused product's
        pair as it is, a plain one projected (a new tensor) with its dots."""
        if isinstance(out, tuple):  # a fused matvec: projected, with the per-node dot
            return out
        av = self._project(out)
        return av, (v * av).sum(-1)

    def _iterate(self, matvec: Matvec, max_iter: int, preconditioner=None):
        if _inverse_blocks(preconditioner) is not None:
            return self._block_iterate(matvec, max_iter, preconditioner)
        if preconditioner is not None:
            return self._pcg_iterate(matvec, max_iter, preconditioner)
        s = self.state
        # A matvec that can end in the step length itself (SystemMatvec.matvec_alpha with the
        # compiled ops) saves a launch per iteration; same alpha, bit for bit.
        fused = getattr(matvec, "matvec_alpha", None) if self.native is not None else None
        ap = fused(s.p, self.plan, s) if fused is not None else None
        if ap is None:
            ap = self._step_length(matvec, s)
        cg_ops.cg_update(ap, self.plan, s, max_iter, self.native)
        cg_ops.cg_direction(self.plan, s, self.native)

    def _projects_in_one_op(self, out: torch.Tensor) -> bool:
        """Whether ``cg_alpha_dot`` takes a product ``out``: the compiled ops serve the solver,
        and ``out`` is a plain tensor of the state's shape (no autograd history to write over)
        and the mask, if any, of its dtype."""
        free = self.free
        return (self.native is not None and not out.requires_grad and out.is_contiguous()
                and out.shape == self.state.p.shape and out.dtype == self.state.p.dtype
                and (free is None or (free.dtype == out.dtype and free.shape == (out.shape[0], 1)
                                      and free.is_contiguous())))

    def _step_length(self, matvec: Matvec, s) -> torch.Tensor:
        """Ap ``[V, d]`` projected on the free nodes, and the step length alpha = r.r / p.Ap into
        ``s`` (``s.rr`` read as r.r: the preconditioned iteration's state holds r.z there). A
        product that gives its per-node dots takes ``cg_alpha``; one that does not is projected in
        place and its dots summed in one op (``cg_alpha_dot``: its output is the CG's to change)."""
        out = matvec(s.p)
        if isinstance(out, tuple) or not self._projects_in_one_op(out):
            ap, p_dot_ap = self._with_dots(out, s.p)
            cg_ops.cg_alpha(p_dot_ap, self.plan, s, self.native)
            return ap
        cg_ops.cg_alpha_dot(out, self.free, self.plan, s, self.native)
        return out

    def _pcg_buffers(self):
        """The preconditioned iteration's own per-object buffer ``[B]`` (made at its first use):
        r.z, and ``scaled``, the state as the plain CG ops see it with r.z in place of r.r (their
        step length alpha = r.z / p.Ap is then preconditioned CG's)."""
        if self._pcg is None:
            s = self.state
            rz = torch.zeros_like(s.rr)
            self._pcg = SimpleNamespace(rz=rz, scaled=dataclasses.replace(s, rr=rz))
        return self._pcg

    def _precondition(self, preconditioner) -> torch.Tensor:
        """z = M^-1 r ``[V, d]`` projected on the free nodes."""
        z = preconditioner(self.state.r)
        if self.free is not None:
            z = z.mul_(self.free) if z is not self.state.r else z * self.free
        return z.contiguous()

    def _block_buffers(self):
        """The block-preconditioned iteration's z ``[V, d]`` and the state as ``cg_direction`` takes
        it there (z for r: p = z + beta p), made at their first use. (A corrected preconditioner's
        r.z and the state its step length reads are the preconditioned iteration's:
        :meth:`_pcg_buffers`.)"""
        if self._block is None:
            z = torch.zeros_like(self.state.r)
            self._block = SimpleNamespace(z=z, direction=dataclasses.replace(self.state, r=z))
        return self._block

    def _block_iterate(self, matvec: Matvec, max_iter: int, preconditioner):
        """One iteration preconditioned by a block diagonal B (the preconditioner's
        ``inverse_blocks`` B^-1 ``[V, d, d]``), applied inside the update: the state's r.r is
        r.B^-1 r there. The step length alpha = r.z / p.Ap (the fused product's or
        ``_step_length``), then ``cg_update`` with the blocks (x, r, z = B^-1 r, r.B^-1 r and the
        stopping rule on it, beta = r'.z' / r.z) and p = z + beta p (``cg_direction`` on z): the
        plain iteration's launches. A preconditioner with a coarse part (M^-1 r = B^-1 r + w Z' y,
        y = E^-1 Z'^T r: its ``coarse_terms(r)`` gives Z'^T r and y) adds it without storing the
        corrected z: r.z = r.B^-1 r + w (Z'^T r) . y (``coarse_beta``, a sum over the bodies) and
        p = z + w Z' y + beta p (``cg_direction`` with its ``direction_term``); the stopping rule
        stays on r.B^-1 r. A block Jacobi with paired blocks (its ``paired``,
        ``preconditioner.PairedBlocks``) adds their off-diagonal part to z and its share of r.z in
        one op (``cg_ops.pair_term``) after the update, before the coarse part where there is one."""
        s, b = self.state, self._block_buffers()
        coarse_terms = getattr(preconditioner, "coarse_terms", None)
        paired = getattr(preconditioner, "paired", None)
        step = s if coarse_terms is None and paired is None else self._pcg_buffers().scaled
        fused = getattr(matvec, "matvec_alpha", None) if self.native is not None else None
        ap = fused(s.p, self.plan, step) if fused is not None else None
        if ap is None:
            ap = self._step_length(matvec, step)
        cg_ops.cg_update(ap, self.plan, s, max_iter, self.native, preconditioner.inverse_blocks, b.z)
        if paired is not None:  # z += the paired blocks' part; r.z = r.D r + its part
            rz = self._pcg_buffers().rz
            last = coarse_terms is None
            target = rz if last else self._pair_rz()
            cg_ops.pair_term(s.r, b.z, paired.nodes, paired.blocks, self._pair_items, target, paired.dots, s, last,
                             self.native)
            if last:
                cg_ops.cg_direction(self.plan, b.direction, self.native)
                return
            s = dataclasses.replace(s, rr=target)  # (the coarse part adds to rr + the pairs')
        if coarse_terms is None:
            cg_ops.cg_direction(self.plan, b.direction, self.native)
            return
        restricted, solution = coarse_terms(s.r)
        cg_ops.coarse_beta(restricted, solution, self._coarse_items(preconditioner.body_ptr), preconditioner.weight,
                           self._pcg_buffers().rz, s, self.native)
        cg_ops.cg_direction(self.plan, b.direction, self.native, preconditioner.direction_term(solution))

    def _pair_rz(self) -> torch.Tensor:
        """``[B]``: r.D r plus the paired blocks' part, where a coarse correction adds its own
        after (made at its first use)."""
        if self._pair_sums is None:
            self._pair_sums = torch.zeros_like(self.state.rr)
        return self._pair_sums

    def _load_pair_items(self, paired) -> None:
        """Each object's range of the paired blocks' pairs (``[B + 1]`` int64, in one buffer that a
        captured iteration reads), from their first nodes: the objects are ranges of nodes."""
        ptr = self.segments.ptr.to(device=paired.first.device, dtype=torch.int64)
        items = torch.searchsorted(paired.first, ptr)
        if self._pair_items is None or self._pair_items.shape != items.shape \
                or self._pair_items.device != items.device:
            self._pair_items = items
        else:
            self._pair_items.copy_(items)

    def _coarse_items(self, body_ptr: torch.Tensor) -> torch.Tensor:
        """``[B + 1]`` int64: each object's range of bodies, for the bodies' node ranges ``body_ptr``
        (every object is a run of whole bodies: one body, or a run of coupled ones). Made at the
        first call (the eager run before a capture) and kept in one buffer, written again where
        another ``body_ptr`` comes: a captured iteration reads its storage."""
        if self._items is None or self._items[0] is not body_ptr:
            items = torch.searchsorted(body_ptr, self.segments.ptr.to(body_ptr.device))
            if self._items is not None:  # (the objects are this solver's: the same count)
                items = self._items[1].copy_(items)
            self._items = (body_ptr, items)
        return self._items[1]

    def _pcg_iterate(self, matvec: Matvec, max_iter: int, preconditioner):
        """One preconditioned iteration through the plain CG's ops: the step length from r.z
        (``cg_alpha`` on the state with r.z for r.r), the update of x, r, r.r, statuses and
        counts (``cg_update``: the stopping rule on the true residual), then z = M^-1 r,
        beta = r'.z' / r.z (``pcg_beta``) and p = z + beta p (``cg_direction`` with z for r);
        objects that are not active stay as they are."""
        s, b = self.state, self._pcg_buffers()
        fused = getattr(matvec, "matvec_alpha", None) if self.native is not None else None
        ap = fused(s.p, self.plan, b.scaled) if fused is not None else None
        if ap is None:
            ap = self._step_length(matvec, b.scaled)
        cg_ops.cg_update(ap, self.plan, s, max_iter, self.native)
        z = self._precondition(preconditioner)
        cg_ops.pcg_beta(s.r, z, self.plan, b.rz, s, self.native)
        cg_ops.cg_direction(self.plan, dataclasses.replace(s, r=z), self.native)

    def _in_one_op(self, matvec: Matvec, rhs: Optional[torch.Tensor], tol: float, max_iter: int, count: int,
                   step_end=None, started: bool = False) -> bool:
        """The matvec's whole-solve op (``SystemMatvec.solve_in_one_op``: start when ``rhs`` is
        given, then up to ``count`` iterations, one persistent kernel on the GPU) where it has
        one and the compiled CG ops serve this solver; False (nothing done) otherwise.
        ``step_end``: as :meth:`begin`; ``started``: as :meth:`iterate`."""
        one_op = getattr(matvec, "solve_in_one_op", None) if self.native is not None else None
        return one_op is not None and one_op(self, rhs, tol, max_iter, count, step_end, started)

    def solves_in_one_op(self, matvec: Matvec) -> bool:
        """Whether :meth:`begin` and the iterations run as one op for this matvec."""
        serves = getattr(matvec, "solves_in_one_op", None) if self.native is not None else None
        return serves is not None and serves(self)

    def iterate(self, matvec: Matvec, count: int, max_iter: int, preconditioner=None, started: bool = False):
        """Up to ``count`` iterations from the current state (objects that stopped stay as they
        are); ``preconditioner``: as :meth:`solve`. ``started``: the state is what :meth:`start`
        left, from a guess and with no preconditioner, and no iteration ran since (p = r): a whole
        solve (``count >= max_iter``) may then go on by the GPU's pipelined CG from that iterate
        (the same iterates in exact arithmetic, rounded otherwise; ``ops.system_cg``)."""
        if preconditioner is None and self._in_one_op(matvec, None, 0.0, max_iter, count, started=started):
            return
        for _ in range(count):
            self._iterate(matvec, max_iter, preconditioner)

    def begin(self, matvec: Matvec, rhs: torch.Tensor, tol: float, max_iter: int, count: int, step_end=None):
        """:meth:`start` from x0 = 0 and up to ``count`` iterations: one op where the matvec has a
        whole-solve op (then the device stops iterating once every object has stopped), else the
        start's and the iterations' ops. No host synchronisation either way.

        ``step_end``: a ``solve.StepEnd`` (the end of an implicit Euler step) that a whole solve
        in one op may do in its own kernel; its ``done`` says whether it did (else the caller
        does it after the solve). With ``step_end.rhs`` set, ``rhs`` is that op's to compute: only
        that op runs, or nothing (``done`` False)."""
        _check_settings(tol, max_iter, 1)
        if self._in_one_op(matvec, rhs, self._effective_tol(tol, rhs.dtype), max_iter, count, step_end):
            return
        if step_end is not None and step_end.rhs is not None:
            return
        self.start(matvec, rhs, None, tol, max_iter)
        for _ in range(count):
            self._iterate(matvec, max_iter)

    @staticmethod
    def _effective_tol(tol: float, dtype) -> float:
        # A tolerance below the dtype's epsilon means "to roundoff": iterating past it only
        # underflows p.Ap to 0, which would read as a breakdown.
        return max(float(tol), torch.finfo(dtype).eps)

    def run_iterations(self, matvec: Matvec, count: int, max_iter: int, graph_key, preconditioner=None):
        """:meth:`iterate` ``count`` times, through a CUDA graph kept per (``graph_key``, count,
        max_iter) where the solver captures (``graph_key`` None: eagerly)."""

        def iterations():
            self.iterate(matvec, count, max_iter, preconditioner)

        if graph_key is None or not self.cuda_graphs:
            iterations()
        elif run_captured(self._graphs, (graph_key, count, max_iter), iterations):
            self.graph_replays += 1

    def start(self, matvec: Matvec, rhs: torch.Tensor, x0: Optional[torch.Tensor] = None, tol: float = 1e-6,
              max_iter: int = 200, preconditioner=None):
        """Set up a solve (residual, norms, per-object status) on the device, with no host
        synchronisation: it can be part of a captured CUDA graph. Arguments as :meth:`solve`."""
        _check_settings(tol, max_iter, 1)
        s = self.state
        b = self._project(rhs)
        if x0 is None:
            s.x.zero_()
            s.r.copy_(b)
        else:
            s.x.copy_(x0)
            torch.sub(b, self._apply(matvec, self._project(x0))[0], out=s.r)
        inverse_blocks = _inverse_blocks(preconditioner)
        if inverse_blocks is not None:  # the norms are B^-1's: b.B^-1 b, r.z with z = B^-1 r
            z = self._block_buffers().z
            z.copy_(block_diagonal_product(inverse_blocks, s.r))
            cg_ops.object_dot(s.r, z, self.plan, s.rr, s, self.native)
            if x0 is None:  # r = b
                self.rhs_sq.copy_(s.rr)
            else:
                cg_ops.object_dot(b, block_diagonal_product(inverse_blocks, b), self.plan, self.rhs_sq, s, self.native)
        else:
            cg_ops.object_dot(b, b, self.plan, self.rhs_sq, s, self.native)
            if x0 is None:  # r = b
                s.rr.copy_(self.rhs_sq)
            else:
                cg_ops.object_dot(s.r, s.r, self.plan, s.rr, s, self.native)
        tol = self._effective_tol(tol, rhs.dtype)
        cg_ops.start_status(s, tol * tol, max_iter, self.native)  # threshold, statuses, zero counts
        if preconditioner is None:
            s.p.copy_(s.r)
        elif inverse_blocks is not None:
            correct = getattr(preconditioner, "correct", None)
            paired = getattr(preconditioner, "paired", None)
            if paired is not None:  # z += the paired blocks' part (its r.z: the dot below)
                self._load_pair_items(paired)
                cg_ops.pair_term(s.r, self._block.z, paired.nodes, paired.blocks, self._pair_items,
                                 self._pcg_buffers().rz, paired.dots, s, False, self.native)
            if correct is not None:  # z = B^-1 r + C r
                correct(s.r, self._block.z)
            if correct is not None or paired is not None:  # r.z for the step length
                cg_ops.object_dot(s.r, self._block.z, self.plan, self._pcg_buffers().rz, s, self.native)
            s.p.copy_(self._block.z)
        else:
            z = self._precondition(preconditioner)
            cg_ops.object_dot(s.r, z, self.plan, self._pcg_buffers().rz, s, self.native)
            s.p.copy_(z)

    def any_active(self) -> bool:
        """Whether some object is still iterating (a host synchronisation)."""
        return bool((self.state.status == ACTIVE).any())

    def _past_pause(self, pause_threshold: torch.Tensor) -> bool:
        """Whether a solve pausing at r.r <= ``pause_threshold [B]`` goes on (some object still
        iterates above it); where it stops with objects still iterating, it is paused (one host
        synchronisation for both)."""
        active = self.state.status == ACTIVE
        above, left = torch.stack([(active & (self.state.rr > pause_threshold)).any(), active.any()]).tolist()
        if not above and left:
            self._paused = (None, pause_threshold)
        return bool(above)

    def result(self) -> CGResult:
        """The outcome of the last solve (copies: the buffers are reused). While the solve is
        paused (:meth:`solve`'s ``pause_tol``), an object counts as converged once its residual is
        within the pause's tolerance."""
        s = self.state
        status = s.status
        converged = status == CONVERGED
        if self._paused is not None:
            converged = converged | ((status == ACTIVE) & (s.rr <= self._paused[1]))
        return CGResult(s.x.clone(), s.iterations.long(), torch.sqrt(torch.clamp(s.rr, min=0)),
                        torch.sqrt(self.rhs_sq), converged, status == BREAKDOWN, status == NONFINITE)

    @property
    def paused(self) -> bool:
        """Whether the last solve paused at its ``pause_tol`` (:meth:`resume` goes on)."""
        return self._paused is not None

    def solve(self, matvec: Matvec, rhs: torch.Tensor, x0: Optional[torch.Tensor] = None, tol: float = 1e-6,
              max_iter: int = 200, check_every: int = 8, graph_key=None, done: int = 0,
              preconditioner=None, pause_tol: Optional[float] = None) -> CGResult:
        """Solve A x = rhs for every object at once.

        Args:
            matvec: p ``[V, d]`` -> A p ``[V, d]`` (A symmetric positive definite per object), or a
                fused matvec returning (A p projected on the free nodes, p . Ap per node ``[V]``).
            rhs: ``[V, d]``; x0: initial guess ``[V, d]`` (zeros by default).
            tol: relative residual tolerance (>= 0; below the dtype's epsilon it counts as epsilon):
                ``tol = 0`` runs ``max_iter`` iterations unless the residual reaches roundoff first.
            max_iter: iteration cap (>= 0); check_every: host check of "any object active" every k
                iterations (>= 1).
            graph_key: hashable; not None promises that ``matvec`` reads only tensors whose storage
                stays the same for every solve with this key (its inputs are updated in place), so its
                iterations may be captured once in a CUDA graph and replayed.
            done: iterations already run since a :meth:`start` made by the caller (then ``rhs`` and
                ``x0`` are ignored and the solve goes on from the current state).
            preconditioner: r ``[V, d]`` -> M^-1 r ``[V, d]`` (a symmetric positive definite
                operator acting on each object alone), or None (plain CG). Its ops are in the
                captured iterations where ``graph_key`` is given: it must then also read only
                tensors whose storage stays. One with ``inverse_blocks`` (B^-1 ``[V, d, d]``, a
                block diagonal: ``preconditioner.BlockJacobi``) is applied inside the update
                instead, and ``tol`` then holds the residual in B^-1's norm (see the module).
            pause_tol: a relative residual above ``tol`` at which the solve pauses (None: none):
                once no object iterates with a residual above it (looked at every
                ``check_every`` iterations), the solve returns with the objects still short of
                ``tol`` counted converged, and :meth:`resume` goes on from there to ``tol``. The
                iterations are the same either way: a paused and resumed solve is the solve to
                ``tol``, bit for bit, whatever ran on the device in between (on other buffers).
        """
        _check_settings(tol, max_iter, check_every)
        self._paused = None
        pausing = pause_tol is not None and pause_tol > tol
        if done == 0:
            # the whole solve in one op, the device deciding when to stop
            if preconditioner is None and not pausing and self.solves_in_one_op(matvec):
                if x0 is None:
                    self.begin(matvec, rhs, tol, max_iter, max_iter)
                else:  # the start from the guess, then the rest in one op (the pipelined CG's on the GPU)
                    self.start(matvec, rhs, x0, tol, max_iter)
                    self.iterate(matvec, max_iter, max_iter, started=True)
                done = max_iter
            elif x0 is None and preconditioner is not None and graph_key is not None and self.cuda_graphs:
                # the start applies the preconditioner once: captured too, over a kept copy of rhs
                if self._rhs is None or self._rhs.shape != rhs.shape or self._rhs.dtype != rhs.dtype:
                    self._rhs = torch.empty_like(rhs)
                self._rhs.copy_(rhs)
                run_captured(self._graphs, (graph_key, "start", float(tol), max_iter),
                             lambda: self.start(matvec, self._rhs, None, tol, max_iter, preconditioner))
            else:
                self.start(matvec, rhs, x0, tol, max_iter, preconditioner)
        pause_threshold = self.rhs_sq * self._effective_tol(pause_tol, rhs.dtype) ** 2 if pausing else None
        done = self.finish(matvec, max_iter, check_every, graph_key, done, preconditioner, pause_threshold)
        if self._paused is not None:
            self._paused = (done, pause_threshold)
        return self.result()

    def resume(self, matvec: Matvec, max_iter: int = 200, check_every: int = 8, graph_key=None,
               preconditioner=None) -> CGResult:
        """Go on with a paused solve (:meth:`solve`'s ``pause_tol``) to its ``tol``; the arguments
        must be the paused solve's (its matvec's inputs unchanged). A solve that is not paused
        is returned as it stands."""
        if self._paused is not None:
            done, self._paused = self._paused[0], None
            self.finish(matvec, max_iter, check_every, graph_key, done, preconditioner)
        return self.result()

    def run_ahead(self, matvec: Matvec, max_iter: int = 200, check_every: int = 8, graph_key=None,
                  preconditioner=None, stretches: int = 1) -> None:
        """Launch up to ``stretches`` stretches of a paused solve's iterations (``check_every``
        each) without reading anything back, so that the device has them to run while the host
        does other work (a contact check); :meth:`resume` then goes on after them. The arguments
        must be the paused solve's. Bit for bit the same solve: a paused solve still has an
        object iterating (:meth:`_past_pause`), so resume's first stretch would run anyway, and a
        stretch after every object stopped leaves the state as it is (it only costs its time).
        Nothing where the solve is not paused."""
        if self._paused is None:
            return
        done, pause_threshold = self._paused
        for _ in range(stretches):
            if done >= max_iter:
                break
            count = min(check_every, max_iter - done)
            self.run_iterations(matvec, count, max_iter, graph_key, preconditioner)
            done += count
        self._paused = (done, pause_threshold)

    def finish(self, matvec: Matvec, max_iter: int, check_every: int, graph_key=None, done: int = 0,
               preconditioner=None, pause_threshold: Optional[torch.Tensor] = None) -> int:
        """Iterate from the current state until no object is active (or, with ``pause_threshold
        [B]``, none with r.r above it) or ``max_iter`` iterations have run (``done`` of them
        already), looking at the host every ``check_every``; returns the iterations run."""
        while done < max_iter and (self.any_active() if pause_threshold is None else self._past_pause(pause_threshold)):
            count = min(check_every, max_iter - done)
            self.run_iterations(matvec, count, max_iter, graph_key, preconditioner)
            done += count
        return done


def _inverse_blocks(preconditioner) -> Optional[torch.Tensor]:
    """A block diagonal preconditioner's B^-1 ``[V, d, d]`` (its ``inverse_blocks``: the CG applies
    it inside its update), or None (none, or one the CG calls)."""
    return getattr(preconditioner, "inverse_blocks", None)


def batched_cg(matvec: Matvec, rhs: torch.Tensor, segments: Segments, free: Optional[torch.Tensor] = None,
               x0: Optional[torch.Tensor] = None, tol: float = 1e-6, max_iter: int = 200,
               check_every: int = 8, preconditioner=None) -> CGResult:
    """Solve A x = rhs for every object at once (a one-off :class:`CGSolver`; see its ``solve``).

    Args:
        matvec: p ``[V, d]`` -> A p ``[V, d]``, or (A p projected, p . Ap per node ``[V]``).
        rhs: ``[V, d]``; segments: the objects' node ranges.
        free: ``[V, 1]`` mask (1 free, 0 constrained) or None; x0: initial guess ``[V, d]``.
        tol, max_iter, check_every, preconditioner: as :meth:`CGSolver.solve`.
    """
    _check_settings(tol, max_iter, check_every)
    solver = CGSolver(segments, rhs.shape, rhs.dtype, rhs.device, free, cuda_graphs=False)
    return solver.solve(matvec, rhs, x0, tol, max_iter, check_every, preconditioner=preconditioner)


__all__ = ["CGResult", "CGSolver", "batched_cg", "STATUS_WORDS", "ACTIVE", "CONVERGED", "BREAKDOWN", "NONFINITE",
           "CAPPED"]
