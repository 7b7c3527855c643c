"""Initial guesses of a step's CG from the solutions of the steps before.

``warm_start="project"`` (:class:`SolutionSpace`) keeps the last few steps' solutions as a basis
W = [w_1 .. w_k] that is orthonormal in the step matrix's energy inner product (w_i . A w_j =
delta_ij, per object), and starts each solve from the Galerkin projection of the unknown
solution x* = A^-1 b on span W:

    x0 = sum_i w_i (w_i . A x*) = sum_i w_i (w_i . b)

which needs only b, never A^-1. Of all the guesses in span W it is the one nearest x* in the energy
norm (||x* - x0||_A <= ||x*||_A: never worse than zero) while A is the matrix the basis was
made with, as for hooke without contact, whose step matrix c_M M + c_K K is the same at every
step. After the solve the new solution x joins the basis: its part A-orthogonal to W (classical
Gram-Schmidt twice, the coefficients w_i . A y from the product A y), normalised, written over
the vector that counted least in this step's guess (the smallest share of the objects'
projections; an unused row first). Dropping a vector of an orthonormal set
leaves it orthonormal; dropping the oldest instead threw away the first steps' solutions, which
carry the static deflection that every later solution shares (on a 4,800-tet beam the guess's
residual went from 1e-6 to 0.6 of the right-hand side when the basis first filled). Two
products a step, beside a handful of [k, V, d] vector operations.

The basis is kept in float64 whatever the solve's dtype: what a new solution adds to the span
is as small as 1e-4-1e-6 of it, and its Gram-Schmidt in float32 (roundoff 1e-7 relative to the
solution) left it far from orthogonal; the guess is rounded to the solve's dtype at the end.

Why it pays: a backward Euler step damps each vibration mode by 1 / (1 + (omega h)^2), so after a
few steps the motion is carried by the few modes with omega h below about one, and the steps'
solutions lie close to a space of small dimension; the projection removes those modes from the
solve and leaves CG (or the multigrid cycle) the rest (docs/preconditioners.md, "Warm starts").
Where the matrix changes from step to step (stvk, corotational, contact penalties) the basis is
no longer A-orthonormal for the new A: the guess is then an approximation whose quality follows
the change, and the stopping rule (the true residual against the right-hand side) is the same
whatever the guess, so the step means the same.

Every operation is a tensor op of fixed shape on the solve's device, with no host
synchronisation (the captured step graphs run them), and the per-object sums reduce in a fixed
order (one object: matrix-vector products, one pass over the basis each; several: a cumulative
sum), so results are reproducible.
"""
from __future__ import annotations

from typing import Callable, Optional

import torch

from ..ops.segments import Segments

#: vectors a :class:`SolutionSpace` keeps (the newest replaces the oldest)
PROJECTION_VECTORS = 32

#: warm-start modes (``StepOptions.warm_start``): none, 2 dv_1 - dv_2 of the two steps before
#: (the simulator's), and the projection on the last steps' solutions (:class:`SolutionSpace`)
WARM_STARTS = ("none", "extrapolate", "project")


def warm_start_mode(value) -> str:
    """``StepOptions.warm_start`` as one of :data:`WARM_STARTS` (``False`` -> ``"none"``, ``True``
    -> ``"extrapolate"``); raises ValueError naming the value otherwise."""
    if value is False:
        return "none"
    if value is True:
        return "extrapolate"
    if isinstance(value, str) and value in WARM_STARTS:
        return value
    raise ValueError(f"warm_start must be True, False or one of {', '.join(map(repr, WARM_STARTS))}, got {value!r}")


class SolutionSpace:
    """The last ``capacity`` solutions of a step's system, A-orthonormal per object, and the
    projected guesses they give (module docstring).

    Args:
        like: a solution's shape, dtype and device ``[V, d]``.
        segments: the objects' node ranges (the inner products are per object: each object's
            guess is its own projection, whatever the others do).
        capacity: vectors kept (:data:`PROJECTION_VECTORS`).
    """

    def __init__(self, like: torch.Tensor, segments: Segments, capacity: int = PROJECTION_VECTORS):
        if int(capacity) < 1:
            raise ValueError(f"capacity must be >= 1, got {capacity}")
        self.capacity = int(capacity)
        #: the basis W ``[k, V, d]``, float64 (rows of zeros: unused)
        self.basis = torch.zeros((self.capacity,) + tuple(like.shape), dtype=torch.float64, device=like.device)
        #: each row's share of the last guess ``[k]`` (the least is replaced; only the order is
        #: read): its squared coefficient for one object, the sum of its fractions of each
        #: object's guess for several
        self.share = torch.zeros(self.capacity, dtype=torch.float64, device=like.device)
        #: 1 for the rows that hold a vector of the current matrix, 0 for the others ``[k]``: a
        #: change of the matrix (:meth:`watch`) sets them all to 0 on the device, without a pass
        #: over the basis; invalid rows take no part in a guess or a Gram-Schmidt and go first
        self.valid = torch.zeros(self.capacity, dtype=torch.float64, device=like.device)
        self._node_stiffness = None  # the node stiffness the valid rows were made with (a copy)
        self._kept = None  # [basis, share, valid, node stiffness or None] as keep() found them
        self.dtype = like.dtype
        segments = segments.to(like.device)
        self._node_object = segments.node_object
        ptr = segments.ptr
        self._objects = segments.num_objects
        self._last = ptr[1:] - 1  # each object's last node (cumulative sums: its sum less the one before)
        self._before = ptr[:-1] - 1  # the node before its first (-1 for the first object)
        # the smallest A-norm a new direction keeps, relative to its solution's: below it the
        # solution is already in the span to within roundoff, and its remainder is noise
        # (float64 arithmetic; the solution's own accuracy, 1e-6 in float32, is far above it)
        self._keep_sq = 1e-16

    def keep(self) -> None:
        """Copy the space as it is now, for :meth:`rewind` (a copy as large as the space, made at
        the first call and kept)."""
        now = (self.basis, self.share, self.valid)
        if self._kept is None:
            self._kept = [t.clone() for t in now] + [None]
        else:
            for kept, tensor in zip(self._kept, now):
                kept.copy_(tensor)
        stiffness = self._node_stiffness
        if stiffness is None:
            self._kept[3] = None
        elif self._kept[3] is None or self._kept[3].shape != stiffness.shape:
            self._kept[3] = stiffness.clone()
        else:
            self._kept[3].copy_(stiffness)

    def rewind(self) -> None:
        """The space as the last :meth:`keep` found it, in place (graphs captured over its tensors
        stay valid), so that steps run again from there make the same guesses. Where it then had
        no node stiffness and has one now, the copy of it is filled with NaN: the next
        :meth:`watch` finds it changed and invalidates every row, as it does from none."""
        if self._kept is None:
            raise ValueError("SolutionSpace.rewind: keep() was never called")
        for kept, tensor in zip(self._kept, (self.basis, self.share, self.valid)):
            tensor.copy_(kept)
        kept = self._kept[3]
        if kept is None:
            if self._node_stiffness is not None:
                self._node_stiffness.fill_(float("nan"))
        elif self._node_stiffness is not None and self._node_stiffness.shape == kept.shape:
            self._node_stiffness.copy_(kept)
        else:
            self._node_stiffness = kept.clone()

    def reset(self) -> None:
        """Forget every solution (in place: captured graphs keep their addresses)."""
        self.basis.zero_()
        self.share.zero_()
        self.valid.zero_()
        self._node_stiffness = None

    def _object_sums(self, per_node: torch.Tensor) -> torch.Tensor:
        """Per-object sums ``[..., B]`` of per-node values ``[..., V]`` (float64), in a fixed order."""
        if self._objects == 1:
            return per_node.sum(-1, keepdim=True)
        running = per_node.cumsum(-1)
        before = torch.where(self._before >= 0, running[..., self._before.clamp(min=0)], 0.0)
        return running[..., self._last] - before

    def _spread(self, per_object: torch.Tensor) -> torch.Tensor:
        """Per-object values ``[k, B]`` -> per node ``[k, V, 1]`` (one object: ``[k, 1, 1]``, which
        broadcasts as that, with no gather)."""
        if self._objects == 1:
            return per_object.unsqueeze(-1)
        return per_object[:, self._node_object].unsqueeze(-1)

    def _dot(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        """Per-object a . b ``[B]`` of two fields ``[V, d]`` (float64): one dot product for one
        object."""
        if self._objects == 1:
            return torch.dot(a.reshape(-1), b.reshape(-1)).reshape(1)
        return self._object_sums((a * b).sum(-1))

    def _coefficients(self, field: torch.Tensor) -> torch.Tensor:
        """w_i . field per object ``[k, B]`` for the basis rows w_i, ``field [V, d]`` (float64). One
        object: one matrix-vector product (a pass over the basis); several: per-node products
        summed per object."""
        if self._objects == 1:
            return torch.mv(self.basis.view(self.capacity, -1), field.reshape(-1)).unsqueeze(1)
        return self._object_sums((self.basis * field).sum(-1))

    def _combination(self, coefficients: torch.Tensor) -> torch.Tensor:
        """sum_i w_i c_i ``[V, d]`` (float64) for per-object coefficients ``[k, B]``: one
        matrix-vector product for one object (a pass over the basis)."""
        if self._objects == 1:
            return torch.mv(self.basis.view(self.capacity, -1).T, coefficients[:, 0]).view(self.basis.shape[1:])
        return (self.basis * self._spread(coefficients)).sum(0)

    def guess(self, rhs: torch.Tensor) -> torch.Tensor:
        """The projected guess ``[V, d]`` (the solve's dtype) of the solution of A x = ``rhs [V, d]``
        (the right-hand side on the free nodes): sum_i w_i (w_i . rhs) per object; zeros while
        the space is empty. Notes each row's share of it (what :meth:`add` replaces)."""
        coefficients = self._coefficients(rhs.to(torch.float64)) * self.valid[:, None]
        energy = coefficients.square()
        if self._objects == 1:  # (the fractions' order is the coefficients')
            share = energy[:, 0]
        else:
            share = (energy / energy.sum(0).clamp(min=torch.finfo(torch.float64).tiny)).sum(1)
        self.share.copy_(torch.where(self.valid > 0, share, -1.0))
        return self._combination(coefficients).to(self.dtype)

    def add(self, solution: torch.Tensor, product: Callable[[torch.Tensor], torch.Tensor],
            image: Optional[torch.Tensor] = None) -> None:
        """Join ``solution [V, d]`` (a solve's x) to the space; ``product``: p ``[V, d]`` -> A p
        ``[V, d]`` (the solve's dtype) with the matrix the guesses are for. Its part
        A-orthogonal to the basis, normalised, is written over the row the last guess used
        least; an object whose solution already lies in the span (to within roundoff) writes
        zeros there.

        Gram-Schmidt twice (classical), each pass's coefficients w_i . A y from the product of
        y: the first pass's y is the solution, the second's what the first left, whose own
        product then also gives its norm (w . A w1 = w . A w to roundoff, w being A-orthogonal
        to the basis). Two products, and no images A W kept: half the memory of keeping them.
        ``image``: A ``solution`` ``[V, d]`` where the caller has it exactly (a refined solve's
        b - r, its residual being the true one: one product fewer), else None."""
        direction = solution.to(torch.float64)
        image = (product(solution) if image is None else image).to(torch.float64)
        whole_sq = self._dot(direction, image)
        for first in (True, False):
            along = self._coefficients(image) * self.valid[:, None]  # w_i . A y
            direction = direction - self._combination(along)
            if first:
                image = product(direction.to(self.dtype)).to(torch.float64)
        norm_sq = self._dot(direction, image)
        # kept above keep_sq of the solution's (and above 0): a NaN fails the test, and an
        # infinite norm has the scale rsqrt(inf) = 0
        least = (whole_sq * self._keep_sq).clamp_(min=torch.finfo(torch.float64).tiny)
        scale = torch.where(norm_sq > least, norm_sq.rsqrt(), 0.0)
        scale = self._spread(scale[None])[0]
        slot = torch.argmin(self.share).reshape(1)  # (the first of equals: an unused row first)
        # (a zero scale writes zeros, also over a non-finite solution's NaN)
        self.basis.index_copy_(0, slot, torch.where(scale != 0, direction * scale, 0.0)[None])
        self.share.index_fill_(0, slot, float("inf"))  # (kept until the next guess notes the shares)
        self.valid.index_fill_(0, slot, 1.0)

    def watch(self, node_stiffness: Optional[torch.Tensor], changing: bool = False) -> None:
        """Invalidate every row (on the device: no host synchronisation) where the step's node
        stiffness ``[V, d, d]`` (the planes' and tools' penalties; None: none) is not the one the
        rows were made with, or where ``changing`` (a part of the matrix that changes at every
        step, as body contact pairs). Call it before :meth:`guess`.

        A penalty that starts or stops acting changes the matrix by a large, local amount: the
        basis is then far from A-orthonormal, and its projection was measured to cost iterations
        (SOFA's beam landing on its floor: 125-131 iterations a step where the cold start took
        84-116, float64). Emptied there, it fills again while the same nodes touch."""
        if changing or node_stiffness is None:
            if changing or self._node_stiffness is not None:
                self.valid.zero_()
            self._node_stiffness = None
            return
        if self._node_stiffness is None or self._node_stiffness.shape != node_stiffness.shape:
            self.valid.zero_()
            self._node_stiffness = node_stiffness.detach().clone()
            return
        self.valid.mul_(torch.eq(node_stiffness, self._node_stiffness).all())
        self._node_stiffness.copy_(node_stiffness)


__all__ = ["SolutionSpace", "PROJECTION_VECTORS", "WARM_STARTS", "warm_start_mode"]
