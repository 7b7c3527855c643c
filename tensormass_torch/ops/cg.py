"""The three in-place steps of one batched CG iteration, after the matvec:

    cg_alpha(p_dot_ap [V], plan, state)      p.Ap per object; alpha = rr / p.Ap, or the object
                                            stops (breakdown: p.Ap <= 0; non-finite)
    cg_update(ap [V, d], plan, state, ...)   x += alpha p; r -= alpha Ap; rr_new = r.r per object;
                                            converged / non-finite / iteration cap; beta
                                            (with a block diagonal B^-1: also z = B^-1 r, and
                                            r.z in place of r.r)
    cg_direction(plan, state)                p = r + beta p (with a coarse term: p = r +
                                            weight Z' c + beta p, the rigid correction's part)

Each runs the compiled op ``torch.ops.tensormass.cg_*`` (the cg family, ``csrc/cg/``: one GPU
block per chunk of a :class:`ChunkPlan`, deterministic sums, no host synchronisation: capturable in
a CUDA graph) when the extension serves the device, else the pure-torch reference below, which is
the tests' oracle. Objects that are not active are left untouched by every step. ``cg_alpha_dot``
is the first step for a product that does not give its per-node dots: Ap projected on the free
nodes in place and p.Ap summed in the same pass. The family also
has ``cg_dot`` (per-object dot products), ``cg_dot_beta`` (preconditioned CG's r.z and beta),
``cg_coarse_beta`` (the same where a coarse correction adds to block Jacobi: r.z from cg_update's
r.B^-1 r and the coarse vectors, no pass over the nodes), ``cg_pair_term`` (paired blocks' part of
z and of r.z, a pair a thread), ``euler_update`` (the end of an implicit Euler step after its
solve), and two ops on the per-object scalars alone, a thread an object, each in place of a dozen
tensor ops on ``[B]`` tensors that cost a launch each: ``cg_start_status`` (a start's threshold,
status and zeroed counts once its r.r is known) and ``cg_round_end`` (the end of an iterative
refinement's round, ``solver.refine``). The ops write into their
arguments and return nothing (fake kernels: none).
"""
from __future__ import annotations

from dataclasses import dataclass
from types import SimpleNamespace
from typing import Optional

import torch

from .. import _backend
from . import library
from .library import OpDef
from .multigrid import rigid_motion_reference
from .segments import ChunkPlan, Segments

ACTIVE, CONVERGED, BREAKDOWN, NONFINITE, CAPPED = 0, 1, 2, 3, 4
STATUS_WORDS = ("active", "converged", "breakdown", "non-finite", "not converged")

_NATIVE = {}


@dataclass
class CGState:
    """The iterates and per-object scalars of a batched CG, updated in place.

    Attributes:
        x, r, p: solution, residual, direction ``[V, d]``.
        rr, alpha, beta, threshold, rhs_sq: per object ``[B]`` (r.r, step, direction coefficient,
            tol^2 b.b, b.b).
        status, iterations: ``[B]`` int32 (``ACTIVE`` ... ``CAPPED``; iterations done).
        scratch: chunk sums ``[K]`` float64; counter: ``[B]`` int32, zero between calls (GPU only).
        rr_swap ``[B]``, work ``[3B + 2]`` int32, sums ``[2K]`` float64: the buffers of a whole solve
            in one op (``native.system_cg``: the persistent kernel's other parity of the scalars,
            statuses after the step length, active counts, chunk sums).
    """

    x: torch.Tensor
    r: torch.Tensor
    p: torch.Tensor
    rr: torch.Tensor
    alpha: torch.Tensor
    beta: torch.Tensor
    threshold: torch.Tensor
    status: torch.Tensor
    iterations: torch.Tensor
    scratch: torch.Tensor
    counter: torch.Tensor
    rhs_sq: torch.Tensor
    rr_swap: torch.Tensor
    work: torch.Tensor
    sums: torch.Tensor

    #: the state as the whole-solve ops take it (their ``cg`` list: csrc/solve/schema.cpp)
    PACKED = ("x", "r", "p", "threshold", "rhs_sq", "rr", "alpha", "beta", "status", "iterations")

    def packed(self):
        """``[x, r, p, threshold, rhs_sq, rr, alpha, beta, status, iterations]``: the solve ops' ``cg``."""
        return [getattr(self, name) for name in self.PACKED]

    @classmethod
    def empty(cls, plan: ChunkPlan, shape, dtype, device) -> "CGState":
        b = plan.segments.num_objects
        vec = lambda: torch.zeros(shape, dtype=dtype, device=device)  # noqa: E731
        obj = lambda: torch.zeros(b, dtype=dtype, device=device)  # noqa: E731
        ints = lambda: torch.zeros(b, dtype=torch.int32, device=device)  # noqa: E731
        k = plan.num_chunks
        return cls(vec(), vec(), vec(), obj(), obj(), obj(), obj(), ints(), ints(),
                   torch.zeros(k, dtype=torch.float64, device=device), ints(), obj(), obj(),
                   torch.zeros(3 * b + 2, dtype=torch.int32, device=device),
                   torch.zeros(2 * k, dtype=torch.float64, device=device))


@dataclass(frozen=True)
class CoarseTerm:
    """A coarse correction's part of the CG's direction (:func:`cg_direction`): weight Z' c ``[V, 3]``
    with Z'_i = N_i [I | -[a_i]x] formed at each node (``common/rigid_modes.h``; the rigid
    correction's, ``solver.rigid_modes``)."""

    node_inverse: torch.Tensor  # N: [V] (n_i I) or [V, 3, 3]
    arm: torch.Tensor  # a [V, 3]
    node_body: torch.Tensor  # [V] int32
    coarse: torch.Tensor  # c [6 B]: each body's t and w
    weight: float

    def tensors(self) -> tuple:
        """(node_inverse, arm, node_body, coarse): the ops' arguments before ``weight``."""
        return self.node_inverse, self.arm, self.node_body, self.coarse

    def motion(self) -> torch.Tensor:
        """weight Z' c ``[V, 3]`` in tensor ops (the reference's)."""
        return rigid_motion_reference(*self.tensors(), self.weight)


def _native_ops(device: torch.device):
    """``torch.ops.tensormass`` when the extension has the CG ops for this device, else None."""
    if not _backend.use_extension(device):
        return None
    key = device.type
    if key not in _NATIVE:
        # use_extension said the extension is built for this device type: its CG ops come with it
        ok = library.ensure_registered() and hasattr(torch.ops.tensormass, "cg_dot")
        _NATIVE[key] = torch.ops.tensormass if ok else None
    return _NATIVE[key]


def _object_sums(values: torch.Tensor, plan: ChunkPlan) -> torch.Tensor:
    """Per-object sums in float64 of per-node values ``[V]`` or ``[V, d]`` -> ``[B]``."""
    return plan.segments.sum(values.to(torch.float64))


# ---------------------------------------------------------------- pure-torch reference


def _ref_alpha(p_dot_ap, plan: ChunkPlan, s: CGState):
    active = s.status == ACTIVE
    p_ap = _object_sums(p_dot_ap, plan).to(s.rr.dtype)
    ok = p_ap > 0
    stopped = active & ~ok
    s.status.copy_(torch.where(stopped, torch.where(torch.isfinite(p_ap), BREAKDOWN, NONFINITE).to(torch.int32),
                               s.status))
    step = torch.where(ok, s.rr / torch.where(ok, p_ap, torch.ones_like(p_ap)), torch.zeros_like(p_ap))
    s.alpha.copy_(torch.where(active, step, s.alpha))


def _ref_update(ap, plan: ChunkPlan, s: CGState, max_iter: int, inverse_blocks=None, z=None):
    active = s.status == ACTIVE
    node_active = plan.segments.spread(active.to(s.x.dtype)) > 0
    a = plan.segments.spread(s.alpha)
    s.x.copy_(torch.where(node_active, s.x + a * s.p, s.x))
    s.r.copy_(torch.where(node_active, s.r - a * ap, s.r))
    if inverse_blocks is None:
        rr_new = _object_sums(s.r * s.r, plan).to(s.rr.dtype)
    else:  # z = B^-1 r on the active objects' nodes; rr is r.z
        z.copy_(torch.where(node_active, (inverse_blocks @ s.r[..., None])[..., 0], z))
        rr_new = _object_sums(s.r * z, plan).to(s.rr.dtype)
    iterations = s.iterations + active.to(torch.int32)
    finite = torch.isfinite(rr_new)
    converged = finite & (rr_new <= s.threshold)
    capped = finite & ~converged & (iterations >= max_iter)
    status = torch.where(~finite, NONFINITE, torch.where(converged, CONVERGED, torch.where(capped, CAPPED, ACTIVE)))
    going = finite & ~converged & ~capped
    beta = torch.where(going, rr_new / torch.where(going, s.rr, torch.ones_like(s.rr)), torch.zeros_like(rr_new))
    s.beta.copy_(torch.where(active, beta, s.beta))
    s.rr.copy_(torch.where(active & finite, rr_new, s.rr))
    s.status.copy_(torch.where(active, status.to(torch.int32), s.status))
    s.iterations.copy_(iterations)


def _ref_direction(plan: ChunkPlan, s: CGState, coarse: Optional[CoarseTerm] = None):
    node_active = plan.segments.spread((s.status == ACTIVE).to(s.p.dtype)) > 0
    r = s.r if coarse is None else s.r + coarse.motion()
    s.p.copy_(torch.where(node_active, r + plan.segments.spread(s.beta) * s.p, s.p))


# ---------------------------------------------------------------- the steps


def cg_alpha(p_dot_ap: torch.Tensor, plan: ChunkPlan, s: CGState, native=None):
    """Step 1 after the matvec: ``p_dot_ap [V]`` (p . Ap per node) -> ``s.alpha``, ``s.status``."""
    if native is None:
        return _ref_alpha(p_dot_ap, plan, s)
    native.cg_alpha(p_dot_ap.contiguous(), *plan.tensors(), s.rr, s.status, s.alpha, s.scratch, s.counter)


def cg_alpha_dot(ap: torch.Tensor, free, plan: ChunkPlan, s: CGState, native=None):
    """Step 1 for a product without its dots: ``ap [V, d]`` projected in place on the nodes of the
    active objects (times ``free [V, 1]``, or None: every node free), then p.Ap per object ->
    ``s.alpha``, ``s.status`` as :func:`cg_alpha`."""
    if native is None:
        return _ref_cg_alpha_dot(s.p, ap, free, *plan.tensors(), s.rr, s.status, s.alpha, None, None)
    native.cg_alpha_dot(s.p, ap, free, *plan.tensors(), s.rr, s.status, s.alpha, s.scratch, s.counter)


def cg_update(ap: torch.Tensor, plan: ChunkPlan, s: CGState, max_iter: int, native=None,
              inverse_blocks: Optional[torch.Tensor] = None, z: Optional[torch.Tensor] = None):
    """Step 2: ``ap [V, d]`` -> ``s.x``, ``s.r``, ``s.rr``, ``s.beta``, ``s.status``, ``s.iterations``.
    With ``inverse_blocks [V, d, d]`` (a block diagonal preconditioner's B^-1) and ``z [V, d]``: also
    z = B^-1 r, and ``s.rr`` is r.z (block-preconditioned CG's; its direction is then p = z + beta p)."""
    if native is None:
        return _ref_update(ap, plan, s, max_iter, inverse_blocks, z)
    native.cg_update(s.x, s.r, s.p, ap.contiguous(), s.alpha, *plan.tensors(), s.threshold, int(max_iter), s.rr,
                     s.status, s.beta, s.iterations, s.scratch, s.counter, inverse_blocks, z)


def cg_direction(plan: ChunkPlan, s: CGState, native=None, coarse: Optional[CoarseTerm] = None):
    """Step 3: ``s.p = s.r + beta s.p`` on active objects; with a ``coarse`` term (``[V, 3]``
    unknowns), ``s.p = s.r + weight Z' c + beta s.p`` (s.r: block Jacobi's z; the preconditioned z
    is then never stored)."""
    if native is None:
        return _ref_direction(plan, s, coarse)
    if coarse is None:
        native.cg_direction(s.p, s.r, s.beta, s.status, *plan.tensors())
    else:
        native.cg_direction(s.p, s.r, s.beta, s.status, *plan.tensors(), *coarse.tensors(), float(coarse.weight))


def object_dot(a: torch.Tensor, b: torch.Tensor, plan: ChunkPlan, out: torch.Tensor, s: CGState, native=None):
    """Per-object dot products of ``[V]`` or ``[V, d]`` fields into ``out [B]`` (in place; float64
    sums in chunk order, no host synchronisation), using the state's scratch buffers."""
    if native is None:
        out.copy_(_object_sums(a * b, plan))
        return
    native.cg_dot(a.contiguous(), b.contiguous(), *plan.tensors(), out, s.scratch, s.counter)


def _ref_pcg_beta(rz_new: torch.Tensor, status: torch.Tensor, rz: torch.Tensor, beta: torch.Tensor):
    going = status == ACTIVE
    beta.copy_(torch.where(going, rz_new / torch.where(going, rz, torch.ones_like(rz)), beta))
    rz.copy_(torch.where(going, rz_new, rz))


def pcg_beta(r: torch.Tensor, z: torch.Tensor, plan: ChunkPlan, rz: torch.Tensor, s: CGState, native=None):
    """Preconditioned CG's direction coefficient after z = M^-1 r (``[V, d]`` each): per active
    object rz_new = r . z, ``s.beta = rz_new / rz`` and ``rz = rz_new`` (``[B]``, in place); objects
    that are not active are left as they are."""
    if native is None:
        return _ref_pcg_beta(_object_sums(r * z, plan).to(rz.dtype), s.status, rz, s.beta)
    native.cg_dot_beta(r.contiguous(), z.contiguous(), *plan.tensors(), s.status, rz, s.beta, s.scratch, s.counter)


def _ref_statuses(rr: torch.Tensor, threshold: torch.Tensor, max_iter: int) -> torch.Tensor:
    """``[B]`` int32 statuses of a start from r.r ``rr`` (common/cg.h: cg_start_status): non-finite,
    converged (rr <= threshold), capped where ``max_iter`` is 0, else active."""
    return torch.where(~torch.isfinite(rr), NONFINITE,
                       torch.where(rr <= threshold, CONVERGED, CAPPED if max_iter == 0 else ACTIVE)).to(torch.int32)


def _ref_start_status(rr, rhs_sq, tol_sq, max_iter, threshold, status, iterations, alpha, beta, floor=None,
                      gate=None):
    """The op's reference: see :func:`start_status`."""
    limit = rhs_sq * tol_sq
    if floor is not None:
        limit = torch.maximum(limit, floor)
    if gate is not None:
        limit = torch.where(gate != ACTIVE, torch.inf, limit)
    threshold.copy_(limit)
    status.copy_(_ref_statuses(rr, threshold, max_iter))
    iterations.zero_()
    alpha.zero_()
    beta.zero_()


def start_status(s: CGState, tol_sq: float, max_iter: int, native=None, floor: Optional[torch.Tensor] = None,
                 gate: Optional[torch.Tensor] = None):
    """A solve's start once ``s.rr`` (r.r of its first residual) and ``s.rhs_sq`` (b.b) are known:
    ``s.threshold = tol_sq * rhs_sq``, raised to ``floor [B]`` where given and infinite where
    ``gate [B]`` int32 (another solve's statuses) is not active; each object's status against it
    (non-finite, converged, capped where ``max_iter`` is 0, else active: an object the gate holds
    starts converged and never iterates, also for a later start from the threshold, as the
    pipelined solve's from an iterate); ``s.iterations``, ``s.alpha``, ``s.beta`` zero. One op (a
    thread an object), in place; every object."""
    args = (s.rr, s.rhs_sq, float(tol_sq), int(max_iter), s.threshold, s.status, s.iterations, s.alpha, s.beta,
            floor, gate)
    if native is None:
        return _ref_start_status(*args)
    native.cg_start_status(*args)


def _ref_round_end(rr, threshold, round_status, round_iterations, status, iterations):
    """The op's reference: see :func:`round_end`."""
    active = status == ACTIVE
    iterations.add_(torch.where(active, round_iterations, 0))
    failed = (round_status == BREAKDOWN) | (round_status == NONFINITE)
    ended = torch.where(failed, round_status, _ref_statuses(rr, threshold, 1))
    status.copy_(torch.where(active, ended.to(torch.int32), status))


def round_end(s: CGState, round_state: CGState, native=None):
    """The end of an iterative refinement's round (``solver.refine``) for the solve ``s``, its
    new r.r in ``s.rr``, corrected by the solve ``round_state``: each object still active in ``s``
    adds the round's iterations and takes its failure (breakdown, non-finite), else the status of
    its new r.r against ``s.threshold`` (non-finite, converged or still active). One op (a thread an
    object), in place."""
    args = (s.rr, s.threshold, round_state.status, round_state.iterations, s.status, s.iterations)
    if native is None:
        return _ref_round_end(*args)
    native.cg_round_end(*args)


def _range_sums(per_item: torch.Tensor, item_ptr: torch.Tensor) -> torch.Tensor:
    """Each object's sum of ``per_item [N]`` over its items ``item_ptr[b] .. item_ptr[b + 1] - 1``."""
    running = torch.cat([per_item.new_zeros(1), torch.cumsum(per_item, 0)])
    return running[item_ptr[1:]] - running[item_ptr[:-1]]


def _ref_coarse_beta(rr, u, v, item_ptr, weight, status, rz, beta):
    sums = _range_sums((u.to(torch.float64) * v.to(torch.float64)).sum(-1), item_ptr)
    _ref_pcg_beta((rr.to(torch.float64) + weight * sums).to(rz.dtype), status, rz, beta)


def coarse_beta(u: torch.Tensor, v: torch.Tensor, item_ptr: torch.Tensor, weight: float, rz: torch.Tensor,
                s: CGState, native=None):
    """Preconditioned CG's direction coefficient where z = B^-1 r + weight Z' v, v = E^-1 u the coarse
    solution of u = Z'^T r (``[N, k]`` each, an item a body): per active object rz_new = r.B^-1 r
    (``s.rr``, cg_update's) + weight * the sum of u . v over its items ``item_ptr[b] ..
    item_ptr[b + 1] - 1`` (``[B + 1]`` int64), ``s.beta = rz_new / rz``, ``rz = rz_new`` (``[B]``, in
    place): r . Z' v = (Z'^T r) . v, so no pass over the nodes."""
    if native is None:
        return _ref_coarse_beta(s.rr, u, v, item_ptr, weight, s.status, rz, s.beta)
    native.cg_coarse_beta(s.rr, u, v, item_ptr, float(weight), s.status, rz, s.beta)


def _ref_pair_term(r, z, nodes, blocks, item_ptr, rr, status, rz, beta, dots, step):
    counts = item_ptr[1:] - item_ptr[:-1]
    pair_object = torch.repeat_interleave(torch.arange(rr.shape[0], device=rr.device), counts)  # [item_ptr[B]]
    count = pair_object.shape[0]
    going = (status == ACTIVE)[pair_object]
    i, j = nodes[:count, 0], nodes[:count, 1]
    o = blocks[:count] * going[:, None, None].to(blocks.dtype)  # (an object that is not active: nothing)
    at_i = (o * r[j][:, None, :]).sum(-1)  # O r_j
    at_j = (o.transpose(1, 2) * r[i][:, None, :]).sum(-1)  # O^T r_i
    pair_dots = ((r[i].double() * at_i.double()).sum(-1) + (r[j].double() * at_j.double()).sum(-1))
    dots[:count].copy_(torch.where(going, pair_dots, dots[:count]))
    z.index_add_(0, torch.cat([i, j]), torch.cat([at_i, at_j]))
    rz_new = (rr.double() + _range_sums(pair_dots, item_ptr)).to(rz.dtype)
    if step:
        _ref_pcg_beta(rz_new, status, rz, beta)
    else:
        rz.copy_(torch.where(status == ACTIVE, rz_new, rz))


def pair_term(r: torch.Tensor, z: torch.Tensor, nodes: torch.Tensor, blocks: torch.Tensor, item_ptr: torch.Tensor,
              rz: torch.Tensor, dots: torch.Tensor, s: CGState, step: bool, native=None,
              rr: Optional[torch.Tensor] = None):
    """Paired blocks beside block Jacobi (``solver.preconditioner.BlockJacobi`` with pairs): for
    each active object's pairs ``item_ptr[b] .. item_ptr[b + 1] - 1`` (``[B + 1]`` int64), nodes
    (i, j) = ``nodes[k]`` (``[K, 2]`` int64, no node in two pairs) and O = ``blocks[k]`` (``[K, 3,
    3]``, the block (i, j) of the pair's inverse), z_i += O r_j and z_j += O^T r_i in place (``r``,
    ``z`` ``[V, 3]``; z holds B^-1 r), and rz_new = ``rr`` (default ``s.rr``, cg_update's r.B^-1 r)
    + the pairs' part of r.z. With ``step``, ``s.beta = rz_new / rz`` and ``rz = rz_new``; without,
    ``rz = rz_new`` only (a coarse correction's ``coarse_beta`` then takes it for its rr). Objects
    that are not active are left as they are. ``dots [K]`` float64: scratch, each pair's part of
    r.z (the GPU sums them per object in a second pass)."""
    rr = s.rr if rr is None else rr
    if native is None:
        return _ref_pair_term(r, z, nodes, blocks, item_ptr, rr, s.status, rz, s.beta, dots, step)
    native.cg_pair_term(r, z, nodes, blocks, item_ptr, rr, s.status, rz, s.beta, dots, bool(step))


def native_ops_for(x: torch.Tensor):
    """The compiled CG ops for ``x``'s device and dtype, or None (pure-torch reference)."""
    if x.dtype not in (torch.float32, torch.float64):
        return None
    return _native_ops(x.device)


# ---------------------------------------------------------------- the ops' references (op signatures)


def _op_state(**fields):
    return SimpleNamespace(**fields)


def _ref_cg_alpha(p_dot_ap, chunk_start, chunk_object, object_chunk, rr, status, alpha, scratch, counter):
    _ref_alpha(p_dot_ap, ChunkPlan.from_tensors(chunk_start, chunk_object, object_chunk),
               _op_state(rr=rr, status=status, alpha=alpha))


def _ref_cg_alpha_dot(p, ap, free, chunk_start, chunk_object, object_chunk, rr, status, alpha, scratch, counter):
    plan = ChunkPlan.from_tensors(chunk_start, chunk_object, object_chunk)
    if free is not None:  # (on the active objects' nodes: the others are left as they are)
        active = plan.segments.spread((status == ACTIVE).to(ap.dtype)).reshape(-1, *[1] * (ap.dim() - 1)) > 0
        ap.copy_(torch.where(active, ap * free.reshape(-1, *[1] * (ap.dim() - 1)), ap))
    dots = p * ap if ap.dim() == 1 else (p * ap).sum(-1)
    _ref_alpha(dots, plan, _op_state(rr=rr, status=status, alpha=alpha))


def _ref_cg_update(x, r, p, ap, alpha, chunk_start, chunk_object, object_chunk, threshold, max_iter, rr, status,
                   beta, iterations, scratch, counter, inverse_blocks=None, z=None):
    s = _op_state(x=x, r=r, p=p, alpha=alpha, threshold=threshold, rr=rr, status=status, beta=beta,
                  iterations=iterations)
    _ref_update(ap, ChunkPlan.from_tensors(chunk_start, chunk_object, object_chunk), s, max_iter, inverse_blocks, z)


def _ref_cg_direction(p, r, beta, status, chunk_start, chunk_object, object_chunk, node_inverse=None, arm=None,
                      node_body=None, coarse=None, weight=1.0):
    term = None if coarse is None else CoarseTerm(node_inverse, arm, node_body, coarse, weight)
    _ref_direction(ChunkPlan.from_tensors(chunk_start, chunk_object, object_chunk),
                   _op_state(p=p, r=r, beta=beta, status=status), term)


def _ref_cg_dot(a, b, chunk_start, chunk_object, object_chunk, out, scratch, counter):
    out.copy_(_object_sums(a * b, ChunkPlan.from_tensors(chunk_start, chunk_object, object_chunk)))


def _ref_cg_dot_beta(r, z, chunk_start, chunk_object, object_chunk, status, rz, beta, scratch, counter):
    plan = ChunkPlan.from_tensors(chunk_start, chunk_object, object_chunk)
    _ref_pcg_beta(_object_sums(r * z, plan).to(rz.dtype), status, rz, beta)


def _ref_euler_update(x, v, dv, dv_imposed, h, x_new, v_new, chunk_start, chunk_object, object_chunk, status,
                      iterations, rr, rhs_sq, norms, summary, scratch, counter, ring=None, ring_pos=None,
                      carry=False, h_old=0.0):
    """v_new = v + dv (+ dv_imposed), x_new = x + h v_new (``h_old`` not 0: x + h_old v + (h - h_old)
    v_new, the trapezoidal rule's) (``carry``: also into x, v); per object
    |v_new|^2 into norms ``[B]`` and the columns (status, iterations, rr, rhs_sq, norm) into
    summary ``[5, B]`` float64 and, with a ring ``[R, 5, B]``, its row ring_pos[0] (if in range),
    ring_pos then advanced by one."""
    plan = ChunkPlan.from_tensors(chunk_start, chunk_object, object_chunk)
    vn = v + dv if dv_imposed is None else v + dv + dv_imposed
    xn = x + h * vn if h_old == 0 else x + h_old * v + (h - h_old) * vn
    x_new.copy_(xn)
    v_new.copy_(vn)
    if carry:
        x.copy_(xn)
        v.copy_(vn)
    norms.copy_(_object_sums(vn * vn, plan).to(norms.dtype))
    columns = torch.stack([status.double(), iterations.double(), rr.double(), rhs_sq.double(), norms.double()])
    summary.copy_(columns)
    if ring_pos is not None:
        pos = int(ring_pos[0])
        if ring is not None and 0 <= pos < ring.shape[0]:
            ring[pos].copy_(columns)
        ring_pos.add_(1)


def _example(name):
    def example(device, dtype):
        segments = Segments.from_lengths([3, 2], device=device)
        plan = ChunkPlan.from_segments(segments, 2)
        tensors = plan.tensors()
        gen = torch.Generator().manual_seed(3)
        s = CGState.empty(plan, (5, 3), dtype, device)
        for t in (s.x, s.r, s.p):
            t.copy_(torch.randn(t.shape, generator=gen))
        s.rr.fill_(2.0)
        s.alpha.fill_(0.5)
        s.beta.fill_(0.25)
        s.threshold.fill_(1e-12)
        s.rhs_sq.fill_(4.0)
        field = torch.randn((5, 3), generator=gen).to(device=device, dtype=dtype)
        per_node = (field * field).sum(-1) + 0.1
        if name == "cg_alpha":
            return (per_node, *tensors, s.rr, s.status, s.alpha, s.scratch, s.counter), {}
        if name == "cg_alpha_dot":
            s.status[1] = CONVERGED  # skipped: its ap stays as it is
            free = torch.tensor([[1.0], [0.0], [1.0], [1.0], [0.0]], dtype=dtype, device=device)
            return (s.p, field, free, *tensors, s.rr, s.status, s.alpha, s.scratch, s.counter), {}
        if name == "cg_update":  # preconditioned by blocks; object 1 skipped (its z stays)
            s.status[1] = CONVERGED
            half = torch.randn((5, 3, 3), generator=gen).to(device=device, dtype=dtype)
            inverse = half @ half.transpose(-1, -2) + torch.eye(3, dtype=dtype, device=device)
            z = torch.randn((5, 3), generator=gen).to(device=device, dtype=dtype)
            return (s.x, s.r, s.p, field, s.alpha, *tensors, s.threshold, 10, s.rr, s.status, s.beta, s.iterations,
                    s.scratch, s.counter, inverse, z), {}
        if name == "cg_direction":  # with a coarse term (two bodies); object 1 skipped
            s.status[1] = CONVERGED
            node_inverse = torch.tensor([1.0, 0.0, 1.0, 1.0, 1.0], dtype=dtype, device=device)
            node_body = torch.tensor([0, 0, 0, 1, 1], dtype=torch.int32, device=device)
            coarse = torch.randn(12, generator=gen).to(device=device, dtype=dtype)
            return (s.p, s.r, s.beta, s.status, *tensors, node_inverse, field, node_body, coarse, 0.5), {}
        if name == "cg_coarse_beta":  # object 0 two items, object 1 one (skipped)
            s.status[1] = CONVERGED
            u, v = (torch.randn((3, 6), generator=gen).to(device=device, dtype=dtype) for _ in range(2))
            item_ptr = torch.tensor([0, 2, 3], dtype=torch.int64, device=device)
            return (s.rr, u, v, item_ptr, 0.5, s.status, s.alpha, s.beta), {}
        if name == "cg_pair_term":  # a pair an object (object 1's skipped), then padding (not read)
            s.status[1] = CONVERGED
            nodes = torch.tensor([[0, 2], [3, 4], [-1, -1]], dtype=torch.int64, device=device)
            blocks = torch.randn((3, 3, 3), generator=gen).to(device=device, dtype=dtype)
            item_ptr = torch.tensor([0, 1, 2], dtype=torch.int64, device=device)
            z = torch.randn((5, 3), generator=gen).to(device=device, dtype=dtype)
            dots = torch.zeros(3, dtype=torch.float64, device=device)
            return (s.r, z, nodes, blocks, item_ptr, s.rr, s.status, s.alpha, s.beta, dots, True), {}
        if name == "cg_dot":
            return (field, s.p, *tensors, s.rr, s.scratch, s.counter), {}
        if name == "cg_start_status":  # object 0 converged by the floor, object 1 held by the gate
            floor = torch.tensor([3.0, 0.5], dtype=dtype, device=device)
            gate = torch.tensor([ACTIVE, CONVERGED], dtype=torch.int32, device=device)
            return (s.rr, s.rhs_sq, 0.01, 10, s.threshold, s.status, s.iterations, s.alpha, s.beta, floor, gate), {}
        if name == "cg_round_end":  # object 0 takes its new r.r's status, object 1 its round's failure
            s.status.zero_()
            s.iterations.fill_(3)
            round_status = torch.tensor([CONVERGED, BREAKDOWN], dtype=torch.int32, device=device)
            round_iterations = torch.tensor([4, 5], dtype=torch.int32, device=device)
            s.threshold.copy_(torch.tensor([3.0, 3.0]))
            return (s.rr, s.threshold, round_status, round_iterations, s.status, s.iterations), {}
        if name == "cg_dot_beta":
            s.status[1] = CONVERGED  # skipped
            return (field, s.p, *tensors, s.status, s.rr, s.beta, s.scratch, s.counter), {}
        b = segments.num_objects
        ring = torch.zeros((2, 5, b), dtype=torch.float64, device=device)
        ring_pos = torch.zeros(1, dtype=torch.int64, device=device)
        summary = torch.zeros((5, b), dtype=torch.float64, device=device)
        counter = torch.zeros(b + 1, dtype=torch.int32, device=device)
        return (s.x, s.r, field, None, 0.01, s.beta.new_zeros((5, 3)), s.beta.new_zeros((5, 3)), *tensors, s.status,
                s.iterations, s.rr, s.rhs_sq, s.alpha, summary, s.scratch, counter, ring, ring_pos, True, 0.004), {}

    return example


_REFERENCES = {"cg_alpha": _ref_cg_alpha, "cg_alpha_dot": _ref_cg_alpha_dot, "cg_update": _ref_cg_update,
               "cg_direction": _ref_cg_direction, "cg_dot": _ref_cg_dot, "cg_dot_beta": _ref_cg_dot_beta,
               "cg_coarse_beta": _ref_coarse_beta, "cg_pair_term": _ref_pair_term,
               "cg_start_status": _ref_start_status, "cg_round_end": _ref_round_end,
               "euler_update": _ref_euler_update}
OPS = tuple(OpDef(name, ref, None, differentiable=False, mutates=True, example=_example(name),
                  scratch=("scratch", "counter")) for name, ref in _REFERENCES.items())
library.define(OPS, lambda: library.register(OPS))
