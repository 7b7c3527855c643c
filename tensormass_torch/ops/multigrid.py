"""The multigrid op family (``csrc/multigrid/``): the products of a V-cycle's coarse levels.

A level's operator, prolongator and restriction are block-sparse (:class:`BsrMatrix`: blocks of
k x k, d x k and k x d values, k the near-null space's modes); these ops take one product each
with its epilogue fused, so that a V-cycle is a few launches per level (captured in a CUDA graph
with the rest of a CG iteration):

    multigrid_bsr_gemv(values, block_cols, row_ptr, x, y?, alpha, beta, out!)
            out = alpha A x + beta y: the residual b - A x, a restriction P^T r, a prolongation
            added x + P e
    multigrid_chebyshev(values?, block_cols?, row_ptr?, product?, b, inverse_diagonal, x?, step!,
        x_out!, a, c)
            one Chebyshev smoothing step: r = b - A x (or b - product, or b from x = 0),
            step = a step + c D^-1 r, x_out = x + step
    multigrid_block_cholesky(blocks, scale!, scale_t!, inverse!)
            block Jacobi's scaling of the finest level (``solver.preconditioner.JacobiScaling``):
            S = L^-T, S^T and S^-1 = L^T of each diagonal block L L^T, in one launch (as tensor
            ops, some seventy small kernels at every solve)
    multigrid_rigid_restrict(node_inverse, arm, range_ptr, r, out!)
    multigrid_rigid_prolong(node_inverse, arm, node_body, coarse, r?, weight, out!)
            the rigid correction's transfers (``solver.rigid_modes``) with its basis
            Z'_i = N_i [I | -[a_i]x] formed at each node from N_i (3 x 3) and the lever arm a_i:
            a body's (u, a x u) summed over its nodes (u = N^T r), and r + weight N (t + w x a)
    multigrid_match_clusters(edge_keys, edge_ends, incident_ptr, incident_edges, most, rounds,
        label!, work!)
            heavy-edge matching of a graph's nodes into clusters of at most ``most`` (the rigid
            correction's groups, ``solver.rigid_modes.contact_clusters``): one call of 4 launches a
            round where the tensor ops take some thirty small kernels a round

Each block row is summed in a fixed order (deterministic, no atomics). The pure-torch references
below are the tests' oracle and the path where the extension does not serve the device. Not
differentiable (solver kernels).
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from . import library
from .library import OpDef

__all__ = ["BsrMatrix", "bsr_gemv", "chebyshev", "block_scaling", "block_cholesky_scaling", "match_clusters",
           "incident_lists", "rigid_restrict", "rigid_prolong", "rigid_motion_reference"]


@dataclass
class BsrMatrix:
    """A block-sparse matrix ``[Rb R, Cb C]``: ``values [nb, R, C]``, ``block_cols [nb]`` and
    ``row_ptr [Rb + 1]`` (int32), the blocks of block row I at ``row_ptr[I] .. row_ptr[I + 1] - 1``;
    ``block_rows [nb]`` (int64, each block's row: the reference's)."""

    values: torch.Tensor
    block_cols: torch.Tensor
    row_ptr: torch.Tensor
    block_rows: torch.Tensor
    shape: tuple

    @classmethod
    def from_scipy(cls, matrix, block: tuple, dtype: torch.dtype, device) -> "BsrMatrix":
        """A scipy sparse matrix as blocks of ``block = (R, C)`` (its shape divisible by them),
        columns sorted within each row."""
        bsr = matrix.tobsr(blocksize=block)
        bsr.sort_indices()
        rows = np.repeat(np.arange(bsr.shape[0] // block[0]), np.diff(bsr.indptr))

        def to(array, dt):
            return torch.from_numpy(np.ascontiguousarray(array)).to(device=device, dtype=dt)

        return cls(to(bsr.data, dtype), to(bsr.indices.astype(np.int32), torch.int32),
                   to(bsr.indptr.astype(np.int32), torch.int32), to(rows.astype(np.int64), torch.int64),
                   tuple(bsr.shape))

    @property
    def block(self) -> tuple:
        return tuple(self.values.shape[1:])

    def arrays(self):
        """``(values, block_cols, row_ptr)``: the ops' matrix arguments."""
        return self.values, self.block_cols, self.row_ptr

    def to_dense(self) -> torch.Tensor:
        """The matrix ``[Rb R, Cb C]`` as a dense tensor (tests)."""
        r, c = self.block
        dense = torch.zeros(self.shape[0] // r, r, self.shape[1] // c, c, dtype=self.values.dtype,
                            device=self.values.device)
        dense[self.block_rows, :, self.block_cols.long(), :] = self.values
        return dense.reshape(self.shape)

    def index_of(self, rows: torch.Tensor, cols: torch.Tensor) -> torch.Tensor:
        """The positions in ``values.view(-1)`` of the entries ``(rows, cols)`` ``[M]`` (int64), which
        must lie in blocks the matrix holds."""
        r, c = self.block
        keys = self.block_rows * (self.shape[1] // c) + self.block_cols.long()  # sorted (rows, then columns)
        block = torch.searchsorted(keys, (rows // r) * (self.shape[1] // c) + cols // c)
        return block * (r * c) + (rows % r) * c + cols % c


# ---------------------------------------------------------------------------------------------
# References (the op signatures)
# ---------------------------------------------------------------------------------------------


def _block_rows(row_ptr: torch.Tensor, blocks: int) -> torch.Tensor:
    counts = row_ptr.long().diff()
    return torch.repeat_interleave(torch.arange(counts.numel(), device=row_ptr.device), counts, output_size=blocks)


def _ref_product(values, block_cols, row_ptr, x):
    """A x ``[Rb R]`` in the reference's order (per-block products, then their sum per row)."""
    nb, r, c = values.shape
    blocks = torch.einsum("kij,kj->ki", values, x.view(-1, c)[block_cols.long()])
    out = torch.zeros(row_ptr.numel() - 1, r, dtype=values.dtype, device=values.device)
    return out.index_add_(0, _block_rows(row_ptr, nb), blocks).reshape(-1)


def _ref_multigrid_bsr_gemv(values, block_cols, row_ptr, x, y, alpha, beta, out):
    product = alpha * _ref_product(values, block_cols, row_ptr, x)
    out.copy_(product if y is None else product + beta * y)


def _ref_multigrid_chebyshev(values, block_cols, row_ptr, product, b, inverse_diagonal, x, step, x_out, a, c):
    if values is not None:
        r = b - _ref_product(values, block_cols, row_ptr, x)
    elif product is not None:
        r = b - product
    else:
        r = b
    s = c * inverse_diagonal * r
    if a != 0:
        s = s + a * step
    step.copy_(s)
    x_out.copy_(s if x is None else x + s)


def _ref_multigrid_block_cholesky(blocks, scale, scale_t, inverse):
    s, s_inverse = block_cholesky_scaling(blocks)
    scale.copy_(s)
    scale_t.copy_(s.transpose(-1, -2))
    inverse.copy_(s_inverse)


def _node_inverse(node_inverse):
    """N ``[V, 3, 3]`` of the rigid transfers' ``node_inverse`` ``[V, 3, 3]`` or ``[V]`` (n_i I)."""
    if node_inverse.dim() == 3:
        return node_inverse
    return node_inverse[:, None, None] * torch.eye(3, dtype=node_inverse.dtype, device=node_inverse.device)


def _ref_multigrid_rigid_restrict(node_inverse, arm, range_ptr, r, out):
    u = (_node_inverse(node_inverse) * r.view(-1, 3, 1)).sum(1)  # N^T r [V, 3]
    per_node = torch.cat([u, torch.linalg.cross(arm, u, dim=-1)], 1)  # [V, 6]
    out.copy_(torch.segment_reduce(per_node, "sum", lengths=range_ptr.long().diff(), unsafe=True).reshape(-1))


def rigid_motion_reference(node_inverse, arm, node_body, coarse, weight) -> torch.Tensor:
    """weight Z' coarse ``[V, 3]``: each node's motion N_i (t + w x a_i) under its body's six coarse
    values (``coarse [6 B]``, ``node_body [V]``), weighted, in tensor ops (``common/rigid_modes.h``:
    the oracle of the rigid prolongation and of ``cg_direction``'s coarse term)."""
    per_body = coarse.view(-1, 6)[node_body.long()]  # [V, 6]
    moved = per_body[:, :3] + torch.linalg.cross(per_body[:, 3:], arm, dim=-1)
    return weight * (_node_inverse(node_inverse) * moved[:, None, :]).sum(-1)


def _ref_multigrid_rigid_prolong(node_inverse, arm, node_body, coarse, r, weight, out):
    moved = rigid_motion_reference(node_inverse, arm, node_body, coarse, weight)
    out.copy_((moved if r is None else r.view(-1, 3) + moved).reshape(-1))


def _ref_multigrid_match_clusters(edge_keys, edge_ends, incident_ptr, incident_edges, most, rounds, label, work):
    """The matching as whole-array rounds: each cluster's offer by a scatter of the edges' keys."""
    nodes = label.numel()
    device = label.device
    clusters = torch.arange(nodes, device=device)
    u, v = edge_ends[:, 0], edge_ends[:, 1]
    for _ in range(rounds if edge_keys.numel() else 0):
        size = torch.bincount(clusters, minlength=nodes)
        cu, cv = clusters[u], clusters[v]
        offer = torch.where((cu != cv) & (size[cu] + size[cv] <= most), edge_keys, -1)
        best = torch.full((nodes,), -1, dtype=offer.dtype, device=device)
        best = best.scatter_reduce(0, cu, offer, "amax").scatter_reduce(0, cv, offer, "amax")
        chosen = (offer >= 0) & (offer == best[cu]) & (offer == best[cv])
        root = torch.minimum(cu, cv)
        relabel = torch.arange(nodes, device=device)
        relabel = relabel.scatter_reduce(0, cu, torch.where(chosen, root, cu), "amin")
        relabel = relabel.scatter_reduce(0, cv, torch.where(chosen, root, cv), "amin")
        clusters = relabel[clusters]
    label.copy_(clusters)


def block_cholesky_scaling(blocks: torch.Tensor):
    """(S = L^-T, S^-1 = L^T), both ``[V, d, d]``, of symmetric blocks ``[V, d, d]`` = L L^T (the
    lower triangle read), the identity for both where a block is not positive definite (a pivot
    <= 0). Elementwise over the blocks: a column-by-column Cholesky, then L^-1 by forward
    substitution (d is 2 or 3). The reference of ``multigrid_block_cholesky``."""
    dim = blocks.shape[-1]
    tiny = torch.finfo(blocks.dtype).tiny
    lower = torch.zeros_like(blocks)
    positive = torch.ones(blocks.shape[:-2], dtype=torch.bool, device=blocks.device)
    for j in range(dim):
        pivot = blocks[..., j, j] - (lower[..., j, :j] ** 2).sum(-1)
        positive &= pivot > 0
        lower[..., j, j] = torch.sqrt(pivot.clamp(min=tiny))
        for i in range(j + 1, dim):
            lower[..., i, j] = (blocks[..., i, j] - (lower[..., i, :j] * lower[..., j, :j]).sum(-1)) / lower[..., j, j]
    inverse_lower = torch.zeros_like(blocks)
    for j in range(dim):
        inverse_lower[..., j, j] = 1.0 / lower[..., j, j]
        for i in range(j + 1, dim):
            inverse_lower[..., i, j] = -(lower[..., i, j:i] * inverse_lower[..., j:i, j]).sum(-1) / lower[..., i, i]
    eye = torch.eye(dim, dtype=blocks.dtype, device=blocks.device)
    keep = positive[..., None, None]
    return (torch.where(keep, inverse_lower.transpose(-1, -2), eye),
            torch.where(keep, lower.transpose(-1, -2), eye))


def _example(name):
    def example(device, dtype):
        gen = torch.Generator().manual_seed(5)

        def rand(*shape):
            return torch.randn(*shape, generator=gen, dtype=torch.float64).to(device=device, dtype=dtype)

        row_ptr = torch.tensor([0, 2, 3, 5], dtype=torch.int32, device=device)
        block_cols = torch.tensor([0, 2, 1, 0, 1], dtype=torch.int32, device=device)
        if name == "multigrid_bsr_gemv":  # 3 x 3 block rows of 3 x 6 blocks
            return (rand(5, 3, 6), block_cols, row_ptr, rand(18), rand(9), 1.5, -0.5, rand(9)), {}
        if name == "multigrid_block_cholesky":  # symmetric blocks, one of them not positive definite
            half = rand(4, 3, 3)
            blocks = half @ half.transpose(-1, -2) + 0.1 * torch.eye(3, dtype=dtype, device=device)
            blocks[2] = -blocks[2]
            return (blocks, rand(4, 3, 3), rand(4, 3, 3), rand(4, 3, 3)), {}
        if name in ("multigrid_rigid_restrict", "multigrid_rigid_prolong"):  # bodies of 3, 0 and 4 nodes
            node_inverse, arm = rand(7, 3, 3), rand(7, 3)
            if name == "multigrid_rigid_restrict":
                ptr = torch.tensor([0, 3, 3, 7], dtype=torch.int32, device=device)
                return (node_inverse, arm, ptr, rand(21), rand(18)), {}
            body = torch.tensor([0, 0, 0, 2, 2, 2, 2], dtype=torch.int32, device=device)
            return (node_inverse, arm, body, rand(18), rand(21), 0.5, rand(21)), {}
        if name == "multigrid_match_clusters":  # a path 0-1-2-3-4 and a triangle 5-6-7, clusters of 3
            ends = torch.tensor([[0, 1], [1, 2], [2, 3], [3, 4], [5, 6], [6, 7], [5, 7]], device=device)
            keys = torch.tensor([4, 6, 1, 5, 2, 3, 0], device=device) * 8 + torch.arange(7, device=device)
            ptr, incident = incident_lists(ends, 8)
            return (keys, ends, ptr, incident, 3, 4, torch.zeros(8, dtype=torch.int64, device=device),
                    torch.zeros(6, 8, dtype=torch.int64, device=device)), {}
        values = rand(5, 3, 3)
        return (values, block_cols, row_ptr, None, rand(9), rand(9).abs(), rand(9), rand(9), rand(9), 0.3, 0.7), {}

    return example


OPS = (
    OpDef("multigrid_bsr_gemv", _ref_multigrid_bsr_gemv, None, differentiable=False, mutates=True,
          example=_example("multigrid_bsr_gemv")),
    OpDef("multigrid_chebyshev", _ref_multigrid_chebyshev, None, differentiable=False, mutates=True,
          example=_example("multigrid_chebyshev")),
    OpDef("multigrid_block_cholesky", _ref_multigrid_block_cholesky, None, differentiable=False, mutates=True,
          example=_example("multigrid_block_cholesky")),
    OpDef("multigrid_rigid_restrict", _ref_multigrid_rigid_restrict, None, differentiable=False, mutates=True,
          example=_example("multigrid_rigid_restrict")),
    OpDef("multigrid_rigid_prolong", _ref_multigrid_rigid_prolong, None, differentiable=False, mutates=True,
          example=_example("multigrid_rigid_prolong")),
    OpDef("multigrid_match_clusters", _ref_multigrid_match_clusters, None, differentiable=False, mutates=True,
          example=_example("multigrid_match_clusters"), scratch=("work",)),
)
library.define(OPS, lambda: library.register(OPS))

# ---------------------------------------------------------------------------------------------
# Calls
# ---------------------------------------------------------------------------------------------


def bsr_gemv(matrix: BsrMatrix, x: torch.Tensor, y: Optional[torch.Tensor] = None, alpha: float = 1.0,
             beta: float = 1.0, out: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``alpha A x + beta y`` (without ``y``: ``alpha A x``) ``[Rb R]`` for flat ``x [Cb C]``, into
    ``out`` (may be ``y``, not ``x``; None: a new tensor)."""
    if out is None:
        out = torch.empty(matrix.shape[0], dtype=x.dtype, device=x.device)
    library.op_or_reference("multigrid_bsr_gemv", x.device)(*matrix.arrays(), x, y, float(alpha), float(beta), out)
    return out


def chebyshev(b: torch.Tensor, inverse_diagonal: torch.Tensor, step: torch.Tensor, x_out: torch.Tensor, a: float,
              c: float, x: Optional[torch.Tensor] = None, matrix: Optional[BsrMatrix] = None,
              product: Optional[torch.Tensor] = None) -> torch.Tensor:
    """One Chebyshev step (``multigrid_chebyshev``) on flat vectors ``[n]``: the residual of ``x``
    through ``matrix`` or its ``product`` A x (neither: x = 0 and ``x`` None); returns ``x_out``."""
    arrays = matrix.arrays() if matrix is not None else (None, None, None)
    library.op_or_reference("multigrid_chebyshev", b.device)(*arrays, product, b, inverse_diagonal, x, step, x_out,
                                                       float(a), float(c))
    return x_out


def block_scaling(blocks: torch.Tensor, scale: torch.Tensor, scale_t: torch.Tensor, inverse: torch.Tensor):
    """Block Jacobi's scaling of symmetric blocks ``[n, d, d]`` into ``scale`` (S = L^-T),
    ``scale_t`` (S^T) and ``inverse`` (S^-1 = L^T), each ``[n, d, d]`` and written in place, the
    identity where a block is not positive definite (``multigrid_block_cholesky``: one launch
    where the extension serves the device, else its reference)."""
    library.op_or_reference("multigrid_block_cholesky", blocks.device)(blocks.contiguous(), scale, scale_t, inverse)



def rigid_restrict(node_inverse: torch.Tensor, arm: torch.Tensor, range_ptr: torch.Tensor, r: torch.Tensor,
                   out: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Each range's Z'^T r ``[6 R]`` for ``r [3 V]`` (``multigrid_rigid_restrict``; Z'_i = N_i
    [I | -[a_i]x], ``node_inverse [V, 3, 3]`` N or ``[V]`` (N_i = n_i I), ``arm [V, 3]`` a,
    ``range_ptr [R + 1]`` int32 the ranges of nodes: the bodies', or runs within them), into
    ``out`` (None: a new tensor)."""
    if out is None:
        out = torch.empty(6 * (range_ptr.shape[0] - 1), dtype=r.dtype, device=r.device)
    library.op_or_reference("multigrid_rigid_restrict", r.device)(node_inverse, arm, range_ptr, r, out)
    return out


def rigid_prolong(node_inverse: torch.Tensor, arm: torch.Tensor, node_body: torch.Tensor, coarse: torch.Tensor,
                  r: Optional[torch.Tensor] = None, weight: float = 1.0,
                  out: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``r + weight Z' coarse`` ``[3 V]`` (no ``r``: ``weight Z' coarse``; ``multigrid_rigid_prolong``,
    ``node_body [V]`` int32 each node's body, ``coarse [6 B]`` each body's t and w), into ``out``
    (may be ``r``; None: a new tensor)."""
    if out is None:
        out = torch.empty(3 * node_inverse.shape[0], dtype=coarse.dtype, device=coarse.device)
    library.op_or_reference("multigrid_rigid_prolong", coarse.device)(node_inverse, arm, node_body, coarse, r,
                                                                      float(weight), out)
    return out


def incident_lists(edge_ends: torch.Tensor, nodes: int) -> tuple:
    """(``incident_ptr [B + 1]``, ``incident_edges [2 E]``) int64: each of ``nodes`` nodes' edges
    (``edge_ends [E, 2]``), in edge order, its range ``incident_ptr[b] .. incident_ptr[b + 1]``; a
    loop (both ends one node, which never offers) is in no list (the entries past ``incident_ptr[B]``).
    No host synchronisation (a search of the sorted ends, not a count)."""
    edges = edge_ends.shape[0]
    loop = (edge_ends[:, 0] == edge_ends[:, 1])[:, None]
    ends = torch.where(loop, nodes, edge_ends).t().reshape(-1)
    listed, order = torch.sort(ends, stable=True)
    ptr = torch.searchsorted(listed, torch.arange(nodes + 1, device=ends.device))
    return ptr, order % max(edges, 1)


def match_clusters(edge_keys: torch.Tensor, edge_ends: torch.Tensor, nodes: int, most: int,
                   rounds: int) -> torch.Tensor:
    """``[B]`` int64: each of ``nodes`` nodes' cluster (its smallest node) after ``rounds`` rounds
    of heavy-edge matching (``multigrid_match_clusters``) over the edges ``edge_ends [E, 2]``
    int64 with distinct keys ``edge_keys [E]`` (>= 0; an edge from a node to itself never joins),
    clusters of at most ``most`` nodes. No host synchronisation."""
    label = torch.empty(nodes, dtype=torch.int64, device=edge_keys.device)
    work = torch.empty(6, nodes, dtype=torch.int64, device=edge_keys.device)
    ptr, incident = incident_lists(edge_ends, nodes)
    library.op_or_reference("multigrid_match_clusters", label.device)(
        edge_keys.contiguous(), edge_ends.contiguous(), ptr, incident, int(most), int(rounds), label, work)
    return label
