"""Jacobi preconditioning of the step's CG, written as a symmetric diagonal scaling.

CG on A x = b preconditioned by D = diag(A) makes the same iterates x as plain CG on

    (S A S) y = S b,    x = S y,    S = D^(-1/2)

so the CG and its ops (``ops.cg``, the captured iterations) stay as they are: the solver is
handed the product p -> S A (S p), the right-hand side S b and the initial guess S^(-1) x0, and
its solution is scaled back. Its residual is then S r, the residual with each row divided by the
square root of its diagonal: the tolerance holds that scaled residual relative to S b. (The rows
scaled down most are the stiff ones, contact and floor, where a residual costs the least motion.)

What it is for: a penalty (a body's contact pairs, the floor, a tool) adds k dt^2 to the diagonal
of the nodes it acts on, tens of times the elastic diagonal at the stiffnesses the scenes use, so
unpreconditioned CG spends its iterations on those few rows; dividing by the diagonal brings
them back to the others' scale. On an elastic body alone the diagonal varies little and Jacobi
saves little: :data:`PRECONDITIONERS`' ``"auto"`` uses it only where body contact pairs join a
solve (there under the rigid bodies' coarse correction, ``solver.rigid_modes``, on 3-D bodies).

The diagonal is the system's own, c_M m + c_K (K_rest + node stiffness) + the pairs' part, with
K_rest the elastic stiffness's diagonal at rest (``TensorMass.stiffness_diagonal``: exact for
hooke, near the tangent's for stvk and corotational, which is all a preconditioner needs).

Block Jacobi (``"jacobi"`` in 3-D and 2-D alike) divides by each node's whole d x d diagonal
block B instead. With B = L L^T (Cholesky), S = L^-T per node and CG runs on

    (S^T A S) y = S^T b,    x = S y,

whose matrix is similar to B^-1 A, as B^(-1/2) A B^(-1/2) is: the same iterates x in exact
arithmetic as the symmetric scaling. The factor is written out in tensor ops (a d x d Cholesky
and its triangular inverse, elementwise over the nodes): no solver library, whose batched
routines limit the batch and check their results on the host (docs/solver-defaults.md). A
penalty k n n^T along a tilted normal, a membrane's in-plane stiffness, a node of a thin body
couple a node's axes; the block takes them in where the diagonal cannot.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Optional

import torch

from ..errors import SceneError, SolverError
from ..mesh.topology import add_at
from ..ops import library
from ..ops.multigrid import BsrMatrix, block_cholesky_scaling, block_scaling, bsr_gemv
from .capture import run_captured

#: Choices of ``StepOptions.preconditioner``: ``"none"`` (plain CG), ``"jacobi"`` (every solve
#: through a TensorMass's product, never the whole-solve op or the captured steps, which have no
#: preconditioner), ``"auto"`` (for the solves body contact pairs join, block Jacobi under the
#: rigid bodies' coarse correction on 3-D bodies, block Jacobi alone on 2-D ones; none elsewhere),
#: ``"rigid"`` (block Jacobi and the rigid bodies' coarse correction: ``solver.rigid_modes``),
#: ``"multigrid"`` (preconditioned CG with a smoothed-aggregation V-cycle: ``solver.multigrid``),
#: ``"cholesky"`` (with the rest matrix's sparse Cholesky factor: ``solver.direct``).
PRECONDITIONERS = ("auto", "none", "jacobi", "rigid", "multigrid", "cholesky")


class JacobiScaling:
    """S = D^(-1/2) ``[V, d]`` (Jacobi) or S = L^-T ``[V, d, d]`` (d x d block Jacobi: each node's
    diagonal block B = L L^T) and S^-1, in buffers whose storage stays from solve to solve (a CUDA
    graph captured over the scaled product replays with each step's). The solve is CG on
    S^T A S y = S^T b, x = S y (see the module)."""

    def __init__(self):
        self.scale: Optional[torch.Tensor] = None
        self.inverse: Optional[torch.Tensor] = None
        # block Jacobi: S, S^T and S^-1 as block-diagonal BSR matrices (one d x d block a row) on
        # the buffers above and S^T's own, for the BSR product op (ops.multigrid)
        self._blocks: Optional[tuple] = None

    def load(self, diagonal: torch.Tensor) -> "JacobiScaling":
        """Take the system's diagonal ``[V, d]`` or diagonal blocks ``[V, d, d]``; rows (blocks)
        that are not positive (definite) (a node with no mass and no element left, whose row CG
        never moves) are left unscaled."""
        if diagonal.dim() == 3:  # S, S^T and S^-1 written into the buffers in one op
            if self.scale is None or self.scale.shape != diagonal.shape or self.scale.dtype != diagonal.dtype \
                    or self.scale.device != diagonal.device:
                self.scale, self.inverse = torch.empty_like(diagonal), torch.empty_like(diagonal)
                self._blocks = _block_diagonal(self.scale, self.inverse)
            block_scaling(diagonal, self.scale, self._blocks[1].values, self.inverse)
            return self
        positive = diagonal > 0
        safe = diagonal.clamp(min=torch.finfo(diagonal.dtype).tiny)
        scale = torch.where(positive, torch.rsqrt(safe), torch.ones_like(diagonal))
        inverse = torch.where(positive, torch.sqrt(safe), torch.ones_like(diagonal))
        if self.scale is None or self.scale.shape != scale.shape or self.scale.dtype != scale.dtype \
                or self.scale.device != scale.device:
            self.scale, self.inverse, self._blocks = scale, inverse, None
        else:
            self.scale.copy_(scale)
            self.inverse.copy_(inverse)
        return self

    @property
    def key(self) -> tuple:
        """What a graph captured over :meth:`product` depends on: the buffer's storage."""
        return ("jacobi", self.scale.data_ptr())

    # The blocks' products are one launch of the BSR product op each (ops.multigrid: a block row a
    # node, each block read once, no [V, d, d] temporaries), where the extension serves the
    # device; its reference otherwise. Two of them run in every CG iteration.
    def apply(self, v: torch.Tensor) -> torch.Tensor:
        """S v ``[V, d]``."""
        if self._blocks is not None:
            return _block_product(self._blocks[0], v)
        return v * self.scale

    def apply_transpose(self, v: torch.Tensor) -> torch.Tensor:
        """S^T v ``[V, d]``."""
        if self._blocks is not None:
            return _block_product(self._blocks[1], v)
        return v * self.scale

    def unapply(self, v: torch.Tensor) -> torch.Tensor:
        """S^-1 v ``[V, d]``."""
        if self._blocks is not None:
            return _block_product(self._blocks[2], v)
        return v * self.inverse

    def product(self, matvec):
        """p -> S^T A (S p) ``[V, d]`` for the product ``matvec`` (A p, or a fused product's
        (A p, p . Ap) whose dots are dropped: the CG takes its own on the scaled vectors)."""

        def scaled(p: torch.Tensor) -> torch.Tensor:
            out = matvec(self.apply(p))
            return self.apply_transpose(out[0] if isinstance(out, tuple) else out)

        return scaled


@dataclass
class PairTerms:
    """A solve's contact pairs as block Jacobi's pairing reads them: ``nodes [P, 4]`` (vertex,
    triangle) and ``coefficients [P, 4]`` (1, -w_a, -w_b, -w_c; rows of zeros are padding),
    ``matrices()`` -> ``[P, 3, 3]`` each pair's M (its part of the step's matrix is J^T M J), and
    ``key``: the storage of what it reads where that stays from load to load (a
    ``PairStiffness``'s buffers), else None."""

    nodes: torch.Tensor
    coefficients: torch.Tensor
    matrices: Callable[[], torch.Tensor]
    key: Optional[tuple] = None


def _capacity(count: int) -> int:
    """A power of two, at least ``count`` and 1."""
    return max(1, 1 << (max(count, 1) - 1).bit_length())


class BlockJacobi:
    """Block Jacobi as preconditioned CG's M = B, each node's d x d diagonal block, for the CG to
    apply inside its update (``CGSolver``: ``inverse_blocks`` B^-1 ``[V, d, d]``, in a buffer whose
    storage stays from load to load, so that graphs captured over the iterations replay with each
    solve's blocks). The same iterates in exact arithmetic as the scaled system of
    :class:`JacobiScaling` (x = S y), and the same tolerance (on sqrt(r.B^-1 r) = |S^T r|), without
    its two block products an iteration: z = B^-1 r is computed in the update's pass.

    With body contact pairs (and ``StepOptions.paired_blocks``, the default), B also takes the
    block A_ij between two nodes i, j of different bodies that a pair couples most
    (:func:`paired_nodes`): their 6 x 6 block is inverted whole, its diagonal blocks D_i, D_j go
    into ``inverse_blocks`` and its off-diagonal block O into :attr:`paired` (a
    :class:`PairedBlocks`, which the CG adds to z: ``ops.cg.pair_term``). A contact's stiffness k
    dt^2 is tens of times a node's elastic diagonal, so Jacobi leaves the pair's two nodes moving
    together as one of the solve's slowest modes; the merged block takes that mode in. The
    stopping rule is then on r . D r (D: ``inverse_blocks``)."""

    def __init__(self):
        self.inverse_blocks: Optional[torch.Tensor] = None
        self._factors: Optional[tuple] = None  # block_scaling's outputs (S, S^T, S^-1)
        self.paired: Optional[PairedBlocks] = None  # the loaded pairs (None: none this load)
        self._pairs: Optional[PairedBlocks] = None  # their buffers, kept from load to load
        self._blocks: Optional[torch.Tensor] = None  # the blocks a captured load reads
        self._graphs: dict = {}  # captured paired loads (CUDA), by the buffers they read

    def load(self, blocks: torch.Tensor, pairs: Optional[PairTerms] = None, node_object: Optional[torch.Tensor] = None,
             free: Optional[torch.Tensor] = None, capture: bool = False) -> "BlockJacobi":
        """Take the system's diagonal blocks ``[V, d, d]``; a block that is not positive definite
        (a node with no mass and no element left, whose row CG never moves) gives the identity.
        B^-1 = L^-T L^-1 = S S^T from the blocks' Cholesky factor (``block_scaling``). ``pairs``
        (the solve's contact pairs as :class:`PairTerms`, or None) with the nodes' bodies
        ``node_object [V]`` and the free-node mask ``free [V, 1]`` (or None): the nodes
        :func:`paired_nodes` pairs are merged into 6 x 6 blocks (3-D). ``capture``: on a CUDA
        device, with ``pairs`` on buffers that keep their storage (a ``PairStiffness``'s), the load
        runs as a CUDA graph captured once for those buffers (``solver.capture.run_captured``):
        its hundred small launches are then one."""
        if self.inverse_blocks is None or self.inverse_blocks.shape != blocks.shape \
                or self.inverse_blocks.dtype != blocks.dtype or self.inverse_blocks.device != blocks.device:
            self.inverse_blocks = torch.empty_like(blocks)
            self._factors = tuple(torch.empty_like(blocks) for _ in range(3))
            self._pairs, self._blocks, self._graphs = None, None, {}
        paired = pairs is not None and pairs.nodes.shape[0] > 0 and blocks.shape[-1] == 3
        if paired and self._pairs is None:
            self._pairs = PairedBlocks()
        self.paired = self._pairs if paired else None
        if not (paired and capture and blocks.is_cuda and pairs.key is not None):
            self._load(blocks, pairs if paired else None, node_object, free)
            return self
        if self._blocks is None:
            self._blocks = torch.empty_like(blocks)
        self._blocks.copy_(blocks)
        self._pairs.reserve(pairs.nodes.shape[0], blocks.shape[0], blocks.dtype, blocks.device)
        key = (pairs.key, self._pairs.key, None if free is None else free.data_ptr(), node_object.data_ptr())
        run_captured(self._graphs, key, lambda: self._load(self._blocks, pairs, node_object, free))
        return self

    def _load(self, blocks: torch.Tensor, pairs: Optional[PairTerms], node_object, free) -> None:
        """The load's device work (see :meth:`load`), on the buffers."""
        scale, scale_t, inverse = self._factors
        block_scaling(blocks, scale, scale_t, inverse)
        # S S^T elementwise: a batched matmul of 3 x 3 blocks goes to a GEMM kernel that took
        # 1.4 ms on the pile's 726,000 nodes (H200), against two elementwise launches
        torch.sum(scale[:, :, None, :] * scale[:, None, :, :], -1, out=self.inverse_blocks)
        if pairs is not None:
            self._pairs.load(blocks, self.inverse_blocks, pairs, node_object, free)

    @property
    def key(self) -> tuple:
        """What a graph captured over the iterations depends on: the buffers' storage."""
        return ("block_jacobi", self.inverse_blocks.data_ptr()) + (() if self.paired is None else self.paired.key)

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        """z = M^-1 r ``[V, d]`` (for callers that apply it themselves): B^-1 r, and the paired
        blocks' part where there is one."""
        z = block_diagonal_product(self.inverse_blocks, r)
        return z if self.paired is None else self.paired.add_to(r, z)


class PairedBlocks:
    """The node pairs of a :class:`BlockJacobi` merged into 6 x 6 blocks, in buffers of a fixed
    capacity (a power of two, at least the pairs' count) whose storage stays while the capacity
    does: ``nodes [C, 2]`` int64 (i < j, in order of i; -1 past the pairs), ``blocks [C, 3, 3]``
    (O = the block (i, j) of the merged block's inverse) and ``first [C]`` (i, or the node count
    past the pairs: each CG object's pairs are then a range, ``CGSolver`` finds it by a search)."""

    def __init__(self):
        self.nodes: Optional[torch.Tensor] = None
        self.blocks: Optional[torch.Tensor] = None
        self.first: Optional[torch.Tensor] = None
        self.dots: Optional[torch.Tensor] = None

    def reserve(self, pairs: int, num_nodes: int, dtype, device) -> None:
        """Buffers for the merged pairs of ``pairs`` contact pairs over ``num_nodes`` nodes (kept
        where they fit already)."""
        capacity = _capacity(min(pairs, num_nodes // 2))
        if self.nodes is None or self.nodes.shape[0] != capacity or self.blocks.dtype != dtype \
                or self.nodes.device != torch.device(device):
            self.nodes = torch.empty((capacity, 2), dtype=torch.int64, device=device)
            self.blocks = torch.empty((capacity, 3, 3), dtype=dtype, device=device)
            self.first = torch.empty(capacity, dtype=torch.int64, device=device)
            self.dots = torch.zeros(capacity, dtype=torch.float64, device=device)  # the CG op's scratch

    def load(self, blocks: torch.Tensor, inverse_blocks: torch.Tensor, pairs: PairTerms,
             node_object: torch.Tensor, free: Optional[torch.Tensor]) -> "PairedBlocks":
        """Merge the nodes :func:`paired_nodes` pairs: their blocks (the diagonal ``blocks [V, 3,
        3]`` and the pairs' coupling) inverted whole, D_i and D_j written into ``inverse_blocks`` (in
        place), O into :attr:`blocks`. No host synchronisation."""
        num_nodes = blocks.shape[0]
        first, second, count = paired_nodes(pairs.nodes, pairs.coefficients, node_object, num_nodes, free)
        self.reserve(pairs.nodes.shape[0], num_nodes, blocks.dtype, blocks.device)
        valid = first < num_nodes  # [count]: the merged pairs first, in order of i, then none
        i, j = torch.where(valid, first, 0), torch.where(valid, second, 0)
        cross = _pair_coupling(pairs, i, j, valid, num_nodes)  # Q = A_ij [count, 3, 3]
        # The merged block [[P, Q], [Q^T, R]]'s inverse by its Schur complement S = R - Q^T P^-1 Q:
        # D_j = S^-1, O = -P^-1 Q S^-1, D_i = P^-1 - O Q^T P^-1, with P^-1 the node's own inverse
        # (3 x 3 products written elementwise: batched matmuls and factorisations of many small
        # blocks go to library kernels many times slower)
        p_inverse = inverse_blocks[i]
        p_inverse_q = _products(p_inverse, cross)  # P^-1 Q
        schur = blocks[j] - _products(cross.transpose(1, 2), p_inverse_q)
        schur = torch.where(valid[:, None, None], schur, torch.eye(3, dtype=blocks.dtype, device=blocks.device))
        scale, scale_t, schur_inverse = (torch.empty_like(schur) for _ in range(3))
        block_scaling(0.5 * (schur + schur.transpose(1, 2)), scale, scale_t, schur_inverse)
        d_j = _products(scale, scale_t)  # S^-1 = L^-T L^-1
        off = -_products(p_inverse_q, d_j)  # O
        d_i = p_inverse - _products(off, p_inverse_q.transpose(1, 2))  # P^-1 - O (P^-1 Q)^T
        # D_i, D_j over the nodes' own inverses (other nodes' stay; an index past the pairs writes
        # into a row that is then dropped)
        rows = torch.cat([inverse_blocks, inverse_blocks.new_zeros((1, 3, 3))])
        dummy = torch.full_like(i, num_nodes)
        rows.index_copy_(0, torch.where(valid, i, dummy), d_i)
        rows.index_copy_(0, torch.where(valid, j, dummy), d_j)
        inverse_blocks.copy_(rows[:-1])
        self.nodes.fill_(-1)
        self.nodes[:count, 0] = torch.where(valid, i, -1)
        self.nodes[:count, 1] = torch.where(valid, j, -1)
        self.blocks.zero_()
        self.blocks[:count] = torch.where(valid[:, None, None], off, 0.0)
        self.first.fill_(num_nodes)
        self.first[:count] = first
        return self

    @property
    def key(self) -> tuple:
        """The buffers' storage (what a captured graph reads)."""
        return ("paired", self.nodes.data_ptr(), self.blocks.data_ptr(), self.first.data_ptr())

    def add_to(self, r: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        """z += the off-diagonal part for ``r [V, 3]`` (z_i += O r_j, z_j += O^T r_i), in tensor
        ops, in place; returns z."""
        valid = self.nodes[:, 0] >= 0
        i, j = torch.where(valid, self.nodes[:, 0], 0), torch.where(valid, self.nodes[:, 1], 0)
        blocks = self.blocks  # (zero past the pairs)
        at_i = (blocks * r[j][:, None, :]).sum(-1)
        at_j = (blocks.transpose(1, 2) * r[i][:, None, :]).sum(-1)
        return z.index_add_(0, torch.cat([i, j]), torch.cat([at_i, at_j]))


def _products(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """a b for 3 x 3 blocks ``[K, 3, 3]`` each, elementwise (see :meth:`PairedBlocks.load`)."""
    return (a[:, :, :, None] * b[:, None, :, :]).sum(2)


def paired_nodes(nodes: torch.Tensor, coefficients: torch.Tensor, node_object: torch.Tensor, num_nodes: int,
                 free: Optional[torch.Tensor] = None) -> tuple:
    """The node pairs block Jacobi merges for contact pairs ``nodes [P, 4]`` (vertex, triangle)
    with ``coefficients [P, 4]`` (1, -w_a, -w_b, -w_c; rows of zeros: no pair) over ``num_nodes``
    nodes of bodies ``node_object [V]``: (first, second, count), ``[count]`` int64 each, count =
    min(P, V // 2) (no host synchronisation), the pairs in order of their first node, then
    ``num_nodes`` in both past them. Each pair of contact links its vertex to its triangle's node
    of largest weight (pairs between two bodies only: within one body the elastic coupling would
    be left out of the block); each node takes its link of largest weight (ties: the lowest other
    node), and two nodes are merged where each is the other's, both free. No node is in two
    pairs."""
    device = nodes.device
    weight, slot = (-coefficients[:, 1:]).max(1)
    vertex, node = nodes[:, 0], nodes.gather(1, 1 + slot[:, None])[:, 0]
    between = node_object[vertex] != node_object[node]
    weight = torch.where(between & (weight > 0), weight, -1.0)  # (a link within a body never wins)
    ends = torch.cat([vertex, node])
    others = torch.cat([node, vertex])
    weights = torch.cat([weight, weight])
    best_weight = torch.full((num_nodes,), -1.0, dtype=weights.dtype, device=device)
    best_weight.scatter_reduce_(0, ends, weights, "amax")
    candidate = torch.where((weights == best_weight[ends]) & (weights > 0), others, num_nodes)
    best = torch.full((num_nodes + 1,), num_nodes, dtype=torch.int64, device=device)
    best.scatter_reduce_(0, ends, candidate, "amin")
    every = torch.arange(num_nodes, device=device)
    partner = best[:num_nodes]
    merged = (partner > every) & (best[partner] == every)
    if free is not None:
        held = free.reshape(num_nodes, -1).amin(1) <= 0
        merged &= ~held & ~held[partner.clamp(max=num_nodes - 1)]
    count = min(nodes.shape[0], num_nodes // 2)
    # the merged nodes in order, then num_nodes: a cumulative count places each (no host read)
    place = torch.cumsum(merged, 0) - 1
    first = torch.full((count + 1,), num_nodes, dtype=torch.int64, device=device)
    first.scatter_(0, torch.where(merged, place, count), torch.where(merged, every, num_nodes))
    first = first[:count]
    second = torch.where(first < num_nodes, best[first.clamp(max=num_nodes)], num_nodes)
    return first, second, count


def _pair_coupling(pairs: PairTerms, first: torch.Tensor, second: torch.Tensor, valid: torch.Tensor,
                   num_nodes: int) -> torch.Tensor:
    """A_ij ``[K, 3, 3]`` for the merged nodes (i, j) = (``first``, ``second``) where ``valid``: the
    sum over the pairs' entries that join them (a pair's vertex and one of its triangle's nodes,
    either way round) of coef_vertex coef_node M, M the pairs' matrices (symmetric)."""
    count = first.shape[0]
    merge = torch.full((num_nodes + 1,), count, dtype=torch.int64, device=first.device)  # node -> its pair
    merge[torch.where(valid, first, num_nodes)] = torch.arange(count, device=first.device)
    merge[torch.where(valid, second, num_nodes)] = torch.arange(count, device=first.device)
    merge[num_nodes:].fill_(count)  # (a view's fill: a tensor's item set from a number copies from the host)
    partner = torch.full((num_nodes + 1,), -1, dtype=torch.int64, device=first.device)
    partner[torch.where(valid, first, num_nodes)] = torch.where(valid, second, -1)
    partner[torch.where(valid, second, num_nodes)] = torch.where(valid, first, -1)
    partner[num_nodes:].fill_(-1)
    coefficients, pair_matrices = pairs.coefficients, pairs.matrices()  # [P, 4], [P, 3, 3]
    vertex = pairs.nodes[:, :1].expand(-1, 3)  # [P, 3]
    node = pairs.nodes[:, 1:]
    joins = partner[vertex] == node  # the entry (vertex, node) is a merged pair's
    # the other entries each into a row of their own past the pairs' (the accumulation sorts by
    # row and sums each row's values in turn: one row for them all would be one long serial sum)
    entry = torch.where(joins, merge[vertex], count + torch.arange(joins.numel(), device=joins.device).view_as(joins))
    values = (coefficients[:, :1] * coefficients[:, 1:])[:, :, None, None] * pair_matrices[:, None]  # [P, 3, 3, 3]
    cross = pair_matrices.new_zeros((count + joins.numel(), 3, 3))
    add_at(cross, entry.reshape(-1), values.reshape(-1, 3, 3))
    return cross[:count]


def block_diagonal_product(blocks: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Each node's block times its vector: ``blocks [V, d, d]`` and ``v [V, d]`` -> ``[V, d]``,
    elementwise (a batched matmul of small blocks goes to GEMM kernels many times slower)."""
    return (blocks * v[:, None, :]).sum(-1)


def _block_diagonal(scale: torch.Tensor, inverse: torch.Tensor) -> tuple:
    """(S, S^T, S^-1) as block-diagonal ``multigrid.BsrMatrix`` es for ``scale`` and ``inverse``
    ``[V, d, d]``: S and S^-1 on those very buffers, S^T on a buffer of its own (load refreshes
    it), the index arrays shared."""
    nodes, dim = scale.shape[0], scale.shape[-1]
    rows = torch.arange(nodes + 1, dtype=torch.int32, device=scale.device)
    block_rows = torch.arange(nodes, device=scale.device)
    shape = (nodes * dim, nodes * dim)
    return tuple(BsrMatrix(values, rows[:-1], rows, block_rows, shape)
                 for values in (scale, scale.transpose(-1, -2).contiguous(), inverse))


def _block_product(matrix: BsrMatrix, v: torch.Tensor) -> torch.Tensor:
    """A block-diagonal ``matrix``'s product with ``v [V, d]`` (``[V, d]``)."""
    return bsr_gemv(matrix, v.reshape(-1)).view_as(v)


def optional_module(name: str, choice: str, does: str, extra: str):
    """The module ``name`` a preconditioner ``choice`` needs, or one SceneError saying how to
    install it (``does``: what it does with it; ``extra``: the package's extra that brings it)."""
    import importlib

    try:
        return importlib.import_module(name)
    except ImportError as err:
        raise SceneError(f"preconditioner={choice!r} {does} with {name}, which is not installed: "
                         f"pip install {name} (or tensormass_torch[{extra}])") from err


def system_diagonal(system, mass_coef: float, stiffness_coef: float, node_stiffness: Optional[torch.Tensor],
                    pairs=None, pair_damping: float = 0.0) -> torch.Tensor:
    """The diagonal ``[V, d]`` of a step's matrix c_M M - c_K dF/dx for ``system``
    (``DynamicsSystem`` of a TensorMass): mass, the elastic stiffness at rest, the loaded
    ``node_stiffness [V, d, d]`` (planes, tools, their folded friction; or None) and the body
    contact ``pairs`` with their friction times ``pair_damping`` (or None)."""
    diagonal = stiffness_coef * system.model.stiffness_diagonal() + mass_coef * system.mass
    if node_stiffness is not None:
        diagonal = diagonal + stiffness_coef * torch.diagonal(node_stiffness, dim1=-2, dim2=-1)
    if pairs is not None and len(pairs):
        diagonal = diagonal + pairs.stiffness_diagonal(stiffness_coef, pair_damping)
    return diagonal


def system_rest_preconditioner(system, kind: str, mass_coef: float, stiffness_coef: float, like: torch.Tensor):
    """The preconditioner built from ``system``'s (a ``DynamicsSystem`` of a TensorMass) step
    matrix at rest c_M M + c_K K_rest on ``like``'s dtype and device: ``kind`` ``"multigrid"``
    (``multigrid.Multigrid``) or ``"cholesky"`` (``direct.RestCholesky``). Built at the first
    call and kept while the kind, the coefficients, the model's tensors (a cut edits them), the
    masses and the constraints stay."""
    from . import direct, multigrid

    model = system.model
    tensors = system._matrix_tensors()
    key = (kind, float(mass_coef), float(stiffness_coef), like.dtype, like.device)
    cache = system._rest_preconditioner
    if cache is None or cache[0] != key or not library.unchanged(cache[1], tensors):
        edges, blocks = model.rest_stiffness_edges()
        matrix = multigrid.rest_system_matrix(edges, blocks, system.mass, mass_coef, stiffness_coef, system.free)
        if kind == "multigrid":
            built = multigrid.Multigrid(matrix, multigrid.rigid_body_modes(model.rest), like.dtype, like.device)
        else:
            built = direct.RestCholesky(matrix, like.dtype, like.device)
        cache = system._rest_preconditioner = (key, (tensors, tuple(t._version for t in tensors), built))
    return cache[1][2]


def system_multigrid(system, mass_coef: float, stiffness_coef: float, like: torch.Tensor):
    """``system_rest_preconditioner(system, "multigrid", ...)``."""
    return system_rest_preconditioner(system, "multigrid", mass_coef, stiffness_coef, like)


class MultigridSolve:
    """A solve's multigrid preconditioner r ``[V, d]`` -> z ``[V, d]``: the system's hierarchy
    (``system_multigrid``) with the finest level on this solve's product and scaling, the
    scaling in a buffer whose storage stays from solve to solve (a CUDA graph captured over the
    iterations replays with each step's)."""

    def __init__(self, multigrid):
        self.multigrid = multigrid
        self.inverse_diagonal: Optional[torch.Tensor] = None
        self.product = None
        self._node_stiffness: Optional[torch.Tensor] = None  # what the last load carried (a copy)
        self._with_pairs = True  # whether it had pairs (until the first load: nothing is loaded)

    def load(self, product, node_stiffness: Optional[torch.Tensor] = None, free: Optional[torch.Tensor] = None,
             pair_row_l1: Optional[torch.Tensor] = None) -> "MultigridSolve":
        """The solve's ``product`` (p -> A p, or a fused product's (A p, p . Ap)), its node
        stiffness ``[V, d, d]`` times c_K (or None: it goes into the coarse operators,
        ``Multigrid.load``) and a bound of the body contact pairs' rows' l1 norms ``[V, d]``
        (``ContactPairs.stiffness_row_l1``, or None). The finest level's scaling is the inverse
        of a bound of its rows' l1 norms: the rest matrix's, plus the node stiffness's and the
        pairs' (so that D^-1 A stays within the smoothers' interval, ``multigrid.CHEBYSHEV_TOP``).

        A load with what the last one had (no pairs, and the same node stiffness or none, as a
        floor's penalties while the same nodes touch it) changes nothing and is skipped."""

        def apply(p):
            out = product(p)
            return out[0] if isinstance(out, tuple) else out

        self.product = apply
        if pair_row_l1 is None and not self._with_pairs and (
                (node_stiffness is None and self._node_stiffness is None)
                or (node_stiffness is not None and self._node_stiffness is not None
                    and node_stiffness.shape == self._node_stiffness.shape
                    and torch.equal(node_stiffness, self._node_stiffness))):
            return self
        try:
            self.multigrid.load(node_stiffness, free)
        except SolverError:  # the levels are back at the rest's: the next load must not be skipped
            self._with_pairs, self._node_stiffness = True, None
            raise
        self._with_pairs = pair_row_l1 is not None
        self._node_stiffness = None if node_stiffness is None else node_stiffness.clone()
        row_l1 = self.multigrid.fine_row_l1.view(-1, self.multigrid.dim)
        if node_stiffness is not None:
            row_l1 = row_l1 + node_stiffness.abs().sum(-1)
        if pair_row_l1 is not None:
            row_l1 = row_l1 + pair_row_l1
        inverse = torch.where(row_l1 > 0, 1.0 / row_l1, 0.0)
        if self.inverse_diagonal is None or self.inverse_diagonal.shape != inverse.shape \
                or self.inverse_diagonal.dtype != inverse.dtype or self.inverse_diagonal.device != inverse.device:
            self.inverse_diagonal = inverse
        else:
            self.inverse_diagonal.copy_(inverse)
        return self

    @property
    def key(self) -> tuple:
        """What a graph captured over :meth:`__call__` depends on: the hierarchy and the buffer."""
        return ("multigrid", id(self.multigrid), self.inverse_diagonal.data_ptr())

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        return self.multigrid(r, self.product, self.inverse_diagonal)


def system_diagonal_blocks(system, mass_coef: float, stiffness_coef: float, node_stiffness: Optional[torch.Tensor],
                           pairs=None, pair_damping: float = 0.0) -> torch.Tensor:
    """The diagonal blocks ``[V, d, d]`` of a step's matrix, as :func:`system_diagonal` gives its
    diagonal: mass, the elastic stiffness's blocks at rest (``TensorMass.stiffness_diagonal_blocks``),
    the node stiffness and the pairs' blocks."""
    blocks = stiffness_coef * system.model.stiffness_diagonal_blocks()
    d = blocks.shape[-1]
    blocks = blocks + (mass_coef * system.mass.reshape(-1))[:, None, None] * torch.eye(
        d, dtype=blocks.dtype, device=blocks.device)
    if node_stiffness is not None:
        blocks = blocks + stiffness_coef * node_stiffness
    if pairs is not None and len(pairs):
        blocks = blocks + pairs.stiffness_blocks(stiffness_coef, pair_damping)
    return blocks


__all__ = ["PRECONDITIONERS", "BlockJacobi", "JacobiScaling", "PairTerms", "PairedBlocks", "paired_nodes",
           "block_cholesky_scaling", "block_diagonal_product",
           "MultigridSolve",
           "system_diagonal", "system_diagonal_blocks", "system_multigrid", "system_rest_preconditioner"]
