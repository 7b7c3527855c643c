"""Conjugate gradient, batched over packed objects with per-object scalars.

Each object has its own alpha, beta, residual and convergence flag: a stiff object that needs
many iterations neither holds back (its neighbours stop updating once converged) nor pollutes
(no scalar is shared) the others. The stopping rule, per object b:

    ||r_b|| <= tol * ||rhs_b||          (the residual ratio, not its square)

tested after every iteration on the device; the host only looks every ``check_every``
iterations to see whether all objects are done, so the iterates never depend on it.
An object whose curvature p.Ap is not positive (an indefinite system, e.g. a compressed
``stvk`` body at a large step) or whose scalars turn NaN/inf is stopped and flagged.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, List, Optional

import torch

from .segments import Segments


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


def batched_cg(matvec: Callable[[torch.Tensor], torch.Tensor], rhs: torch.Tensor, segments: Segments,
               free: Optional[torch.Tensor] = None, x0: Optional[torch.Tensor] = None, tol: float = 1e-6,
               max_iter: int = 200, check_every: int = 8) -> CGResult:
    """Solve A x = rhs for every object at once.

    Args:
        matvec: p ``[V, d]`` -> A p ``[V, d]`` (A symmetric positive definite per object).
        rhs: ``[V, d]``.
        segments: the objects' node ranges.
        free: ``[V, 1]`` mask (1 free, 0 constrained) or None. Constrained rows are projected out:
            the solve runs on free nodes and leaves ``x0`` there.
        x0: initial guess ``[V, d]`` (zeros by default).
        tol: relative residual tolerance (>= 0); ``tol = 0`` runs exactly ``max_iter`` iterations.
        max_iter: iteration cap (>= 0).
        check_every: host check of "all objects done" every k iterations (>= 1).
    """
    if max_iter < 0 or tol < 0 or check_every < 1:
        raise ValueError(f"bad CG settings: max_iter={max_iter}, tol={tol}, check_every={check_every}")

    def project(v):
        return v if free is None else v * free

    def apply(v):
        return project(matvec(project(v)))

    x = torch.zeros_like(rhs) if x0 is None else x0.clone()
    b = project(rhs)
    r = b - apply(x) if x0 is not None else b.clone()
    rhs_sq = segments.dot(b, b)
    rr = segments.dot(r, r)
    threshold = (tol * tol) * rhs_sq
    nonfinite = ~torch.isfinite(rr)
    converged = (rr <= threshold) & ~nonfinite
    breakdown = torch.zeros_like(converged)
    active = ~converged & ~nonfinite
    iterations = torch.zeros_like(segments.lengths)
    p = r.clone()
    for k in range(max_iter):
        if k % check_every == 0 and not bool(active.any()):
            break
        ap = apply(p)
        p_ap = segments.dot(p, ap)
        newly_broken = active & ~(p_ap > 0)  # also catches NaN curvature
        breakdown |= newly_broken & torch.isfinite(p_ap)
        nonfinite |= newly_broken & ~torch.isfinite(p_ap)
        active &= ~newly_broken
        alpha = torch.where(active, rr / torch.where(active, p_ap, torch.ones_like(p_ap)), torch.zeros_like(rr))
        x = x + segments.spread(alpha) * p
        r = r - segments.spread(alpha) * ap
        rr_new = segments.dot(r, r)
        iterations = iterations + active.long()
        bad = active & ~torch.isfinite(rr_new)
        nonfinite |= bad
        active &= ~bad
        done = active & (rr_new <= threshold)
        converged |= done
        active &= ~done
        beta = torch.where(active, rr_new / torch.where(active, rr, torch.ones_like(rr)), torch.zeros_like(rr))
        p = r + segments.spread(beta) * p
        rr = torch.where(active | done, rr_new, rr)
    return CGResult(x, iterations, torch.sqrt(torch.clamp(rr, min=0)), torch.sqrt(rhs_sq), converged,
                    breakdown, nonfinite)
