"""Smoothed-aggregation multigrid as the step's CG preconditioner, with the rigid-body modes.

Unpreconditioned CG needs more iterations the finer and the stiffer the mesh (a converged step
of a 300k-tet beam takes hundreds); a multilevel preconditioner keeps the count nearly flat.
The hierarchy is built once per mesh and per step coefficients, on the host, by pyamg's
smoothed aggregation (a well-kept library: aggregation, tentative prolongators fitted to the
near-null space, Jacobi-smoothed prolongators, Galerkin coarse operators). It is handed the
step's matrix at rest,

    A = c_M M + c_K K_rest,   fixed nodes' rows and columns replaced by the identity,

as a ``[V d, V d]`` block-sparse matrix (``TensorMass.rest_stiffness_edges``), and the rigid-body
modes (3 translations and 3 rotations in 3-D, 2 and 1 in 2-D) as the near-null space: what
elasticity's low-energy modes look like locally, which is what makes the coarse levels
represent bending. Its operators then live on the solve's device as CSR tensors and one
V-cycle runs there (``Multigrid.__call__``):

    level l < L:  x = S_l b (pre-smoothing from 0);  r = b - A_l x;  x += P_l V_{l+1}(P_l^T r);
                  x += S_l (b - A_l x) (post-smoothing)
                  (level 0: the step's own product and scaling, where the solve gives them)
    level L:      x = A_L^-1 b (a dense inverse, from a Cholesky factorisation made once: one
                  matrix-vector product, where triangular solves would be sequential)

S_l is a Chebyshev polynomial of D_l^-1 A_l with l1-Jacobi's D_l (the rows' l1 norms: D^-1 A's
spectrum in (0, 1] by construction, whatever a step's penalties add) over [lambda/30, 1.1]
(lambda: the largest eigenvalue at rest, estimated at set-up), the same polynomial before and
after: the cycle is a symmetric positive definite operator, as CG needs. Polynomial smoothers
are the GPU's: products and vector updates, no ordering as Gauss-Seidel would need.

Invariants: objects of a packed batch share no edge, so no aggregate crosses two objects and
the cycle acts on each object alone (what the batched CG's per-object scalars assume). The
finest level smooths with the step's own product (the floor's and tools' stiffness, stvk's and
corotational's tangents, body contact pairs); the coarse levels hold the rest stiffness plus
the floor's and tools' node stiffness (:meth:`Multigrid.load`, each solve). Where the step's
matrix differs from that (tangents, pairs), the cycle approximates its inverse: more
iterations, never a wrong answer (the stopping rule is on the true residual).
"""
from __future__ import annotations

import warnings
from typing import List, Optional

import numpy as np
import torch

from ..errors import SceneError, SolverError
from ..ops.multigrid import BsrMatrix, bsr_gemv, chebyshev
from .preconditioner import optional_module

#: Unknowns of the coarsest level (solved with a dense inverse): coarsening stops below it, and
#: a hierarchy whose coarsest level is above ``MAX_DIRECT`` (a mesh aggregation cannot reduce)
#: is refused.
COARSE_SIZE = 2000
MAX_DIRECT = 20000
#: The top of the smoothers' Chebyshev interval. Their scaling is l1-Jacobi, D = diag(sum_j |a_ij|),
#: for which D - A is diagonally dominant, so D^-1 A's spectrum lies in (0, 1] whatever the
#: penalties a step adds (an estimate made at rest would not bound them); the margin covers the
#: finest level's step tangent, whose row sums are those at rest.
CHEBYSHEV_TOP = 1.1


def rigid_body_modes(positions: torch.Tensor) -> np.ndarray:
    """The rigid-body modes at ``positions [V, d]`` as columns ``[V d, 6]`` (3-D) or ``[V d, 3]``
    (2-D), float64: translations, then rotations about the centroid (scaled to the mesh's size,
    so that every column has a comparable norm)."""
    x = positions.detach().to("cpu", torch.float64).numpy()
    x = x - x.mean(axis=0)
    x = x / max(float(np.abs(x).max()), np.finfo(np.float64).tiny)
    v, d = x.shape
    if d == 2:
        modes = np.zeros((v, 2, 3))
        modes[:, 0, 0] = modes[:, 1, 1] = 1.0
        modes[:, 0, 2], modes[:, 1, 2] = -x[:, 1], x[:, 0]
        return modes.reshape(v * 2, 3)
    modes = np.zeros((v, 3, 6))
    for axis in range(3):
        modes[:, axis, axis] = 1.0
    ex, ey, ez = x[:, 0], x[:, 1], x[:, 2]
    modes[:, 1, 3], modes[:, 2, 3] = -ez, ey  # about x
    modes[:, 0, 4], modes[:, 2, 4] = ez, -ex  # about y
    modes[:, 0, 5], modes[:, 1, 5] = -ey, ex  # about z
    return modes.reshape(v * 3, 6)


def rest_system_matrix(edges: torch.Tensor, blocks: torch.Tensor, mass: torch.Tensor, mass_coef: float,
                       stiffness_coef: float, free: Optional[torch.Tensor] = None):
    """The step's matrix at rest c_M M + c_K K as a scipy BSR matrix ``[V d, V d]`` (float64),
    from the stiffness's edge blocks (``rest_stiffness_edges``: ``edges [E, 2]``, ``blocks
    [E, d, d]``), the lumped ``mass [V]`` and ``free [V, 1]`` (None: all free); a fixed node's
    row and column are the identity's. Blocks sorted by (row, column), duplicates summed in
    that order: the same matrix for the same mesh."""
    import scipy.sparse as sp

    v, d = mass.shape[0], blocks.shape[-1]  # mass: [V] or [V, 1]
    e = edges.to("cpu", torch.int64)
    k = blocks.detach().to("cpu", torch.float64)
    m = mass.detach().to("cpu", torch.float64).reshape(-1)
    eye = torch.eye(d, dtype=torch.float64)
    low, high = e[:, 0], e[:, 1]
    diagonal = torch.zeros(v, d, d, dtype=torch.float64)
    diagonal.index_add_(0, low, -k)
    diagonal.index_add_(0, high, -k.transpose(1, 2))
    diagonal = stiffness_coef * diagonal + mass_coef * m[:, None, None] * eye
    rows = torch.cat([low, high, torch.arange(v)])
    cols = torch.cat([high, low, torch.arange(v)])
    values = torch.cat([stiffness_coef * k, stiffness_coef * k.transpose(1, 2), diagonal])
    if free is not None:
        fixed = (free.detach().to("cpu").reshape(-1) == 0)
        touches = fixed[rows] | fixed[cols]
        values = torch.where(touches[:, None, None], torch.zeros_like(values), values)
        on_fixed_diagonal = touches & (rows == cols)
        values[on_fixed_diagonal] = eye
    order = np.lexsort((cols.numpy(), rows.numpy()))
    rows, cols, values = rows.numpy()[order], cols.numpy()[order], values.numpy()[order]
    indptr = np.concatenate([[0], np.cumsum(np.bincount(rows, minlength=v))])
    matrix = sp.bsr_matrix((values, cols, indptr), shape=(v * d, v * d))
    matrix.sum_duplicates()
    return matrix


def _csr(matrix, dtype: torch.dtype, device) -> torch.Tensor:
    """A scipy sparse matrix as a torch CSR tensor (int32 indices): the operands of the sparse
    products that carry a node stiffness into the coarse levels (:meth:`Multigrid.load`)."""
    csr = matrix.tocsr()
    csr.sort_indices()
    with warnings.catch_warnings():  # torch's notice that its sparse CSR support is in beta
        warnings.simplefilter("ignore", UserWarning)
        return torch.sparse_csr_tensor(torch.from_numpy(csr.indptr.astype(np.int32)),
                                       torch.from_numpy(csr.indices.astype(np.int32)),
                                       torch.from_numpy(csr.data), size=csr.shape, dtype=dtype,
                                       check_invariants=False).to(device)


def _block_of(matrix, rows: int, cols: int) -> tuple:
    """The block shape to store ``matrix`` in: its own where it is a BSR matrix of one the ops
    take, else ``(rows, cols)`` where they divide its shape, else 1 x 1."""
    own = getattr(matrix, "blocksize", None)
    if own is not None and tuple(own) in _BLOCKS:
        return tuple(own)
    if (rows, cols) in _BLOCKS and matrix.shape[0] % rows == 0 and matrix.shape[1] % cols == 0:
        return rows, cols
    return 1, 1


#: the block shapes of the multigrid ops (csrc/multigrid/ops.h)
_BLOCKS = {(6, 6), (3, 6), (6, 3), (3, 3), (2, 3), (3, 2), (2, 2), (1, 1)}


class _Level:
    """One level: its operator A ``[n, n]``, prolongator P ``[n, n_coarse]`` and restriction P^T
    (block-sparse: ``ops.multigrid.BsrMatrix``), the inverse of its rows' l1 norms ``[n]`` and the
    Chebyshev coefficients on D^-1 A."""

    def __init__(self, level, dtype, device, degree: int, dim: int, modes: int):
        import pyamg.util.linalg as amg_linalg
        import scipy.sparse as sp

        a = level.A
        self.size = a.shape[0]
        self.dtype, self.device = dtype, device
        unknowns = a.blocksize[0] if hasattr(a, "blocksize") else 1  # a node's (level 0) or aggregate's
        self.matrix = BsrMatrix.from_scipy(a, _block_of(a, unknowns, unknowns), dtype, device)
        self.prolong = BsrMatrix.from_scipy(level.P, _block_of(level.P, self.matrix.block[0], modes), dtype, device)
        self.restrict = BsrMatrix.from_scipy(level.P.T.tocsr(), tuple(reversed(self.prolong.block)), dtype, device)
        self._scipy_prolong = level.P  # for the sparse products of Multigrid.load, made there when needed
        self._csr = None
        row_l1 = row_sums(a)
        inverse = np.where(row_l1 > 0, 1.0 / np.where(row_l1 > 0, row_l1, 1.0), 0.0)
        self.inverse_diagonal = torch.from_numpy(inverse).to(device=device, dtype=dtype)
        # what a change of the finest level's node stiffness updates in place (Multigrid.load)
        self.rest_values = self.matrix.values.clone()
        self.rest_l1 = torch.from_numpy(row_l1).to(device=device, dtype=dtype)
        top = float(amg_linalg.approximate_spectral_radius(sp.diags(inverse) @ a.tocsr(), symmetric=False))
        self.steps = chebyshev_steps(top / 30.0, CHEBYSHEV_TOP, degree)

    def sparse_transfers(self):
        """(P, P^T) as torch CSR tensors (made at the first call)."""
        if self._csr is None:
            p = self._scipy_prolong
            self._csr = (_csr(p, self.dtype, self.device), _csr(p.T, self.dtype, self.device))
        return self._csr


def row_sums(matrix) -> np.ndarray:
    """The l1 norms of a scipy sparse matrix's rows ``[n]``: sum_j |a_ij|."""
    return np.asarray(abs(matrix).sum(axis=1), dtype=np.float64).reshape(-1)


def chebyshev_steps(low: float, high: float, degree: int):
    """The scalars of ``degree`` steps of Chebyshev iteration for A x = b preconditioned by D on
    the interval [low, high] of D^-1 A's spectrum: the first step is c_0 D r, each next
    a_k (last step) + c_k D r. Returns [(a_k, c_k)] (a_0 = 0)."""
    theta, delta = (high + low) / 2.0, (high - low) / 2.0
    sigma = theta / delta
    rho = 1.0 / sigma
    steps = [(0.0, 1.0 / theta)]
    for _ in range(degree - 1):
        rho_next = 1.0 / (2.0 * sigma - rho)
        steps.append((rho_next * rho, 2.0 * rho_next / delta))
        rho = rho_next
    return steps


def _smooth(matrix: Optional[BsrMatrix], product, inverse_diagonal: torch.Tensor, steps, b: torch.Tensor,
            x: Optional[torch.Tensor]) -> torch.Tensor:
    """Chebyshev smoothing of A x = b ``[n]`` from x (None: 0) with the level's ``matrix``, or the
    operator ``product`` (x -> A x ``[n]``) where it is None, and D^-1 ``inverse_diagonal [n]``: the
    same polynomial whatever x, hence a symmetric operator b -> x from x = 0. One op a step
    (``ops.multigrid.chebyshev``: the residual, the step and the update fused)."""
    step = torch.empty_like(b)
    for a, c in steps:
        if x is None:
            x = chebyshev(b, inverse_diagonal, step, torch.empty_like(b), 0.0, c)
        elif matrix is not None:  # (other rows read x: the new x in a new buffer)
            x = chebyshev(b, inverse_diagonal, step, torch.empty_like(b), a, c, x=x, matrix=matrix)
        else:
            x = chebyshev(b, inverse_diagonal, step, x, a, c, x=x, product=product(x))
    return x


#: The seed of the random start vectors pyamg's hierarchy build draws (its spectral radius estimates).
HIERARCHY_SEED = 0


class Multigrid:
    """A smoothed-aggregation V-cycle ``r [V, d] -> z [V, d]`` for the step's matrix at rest.

    Args:
        matrix: the scipy BSR matrix ``[V d, V d]`` (:func:`rest_system_matrix`).
        modes: the near-null space ``[V d, k]`` (:func:`rigid_body_modes`).
        dtype, device: of the solve.
        degree: Chebyshev smoothing steps before and after the coarse correction (>= 1).
        coarse_size: unknowns of the coarsest level (solved by a dense inverse).
    """

    def __init__(self, matrix, modes: np.ndarray, dtype: torch.dtype, device, degree: int = 2,
                 coarse_size: int = COARSE_SIZE):
        pyamg = optional_module("pyamg", "multigrid", "builds its hierarchy", "multigrid")
        if degree < 1:
            raise ValueError(f"multigrid smoothing degree must be >= 1, got {degree}")
        #: unknowns per node
        self.dim = matrix.blocksize[0] if hasattr(matrix, "blocksize") else 1
        # pyamg counts a level's size in blocks; the coarse levels' blocks are the modes
        # pyamg's spectral radius estimates (the prolongation's smoothing, each level's Chebyshev
        # interval) start from random vectors of numpy's global generator: seeded here, so that one
        # mesh gives one hierarchy (and a simulation its trajectory, bit for bit), the caller's
        # generator state put back after
        state = np.random.get_state()
        np.random.seed(HIERARCHY_SEED)
        try:
            hierarchy = pyamg.smoothed_aggregation_solver(matrix, B=modes, symmetry="symmetric",
                                                          max_coarse=max(coarse_size // modes.shape[1], 1),
                                                          max_levels=12, keep=False)
            coarse = hierarchy.levels[-1].A
            if coarse.shape[0] > MAX_DIRECT:
                raise SceneError(f"multigrid: aggregation could not coarsen this mesh below {coarse.shape[0]} "
                                 f"unknowns (at most {MAX_DIRECT} are solved directly); use preconditioner='jacobi'")
            self.levels: List[_Level] = [_Level(level, dtype, device, degree, self.dim, modes.shape[1])
                                         for level in hierarchy.levels[:-1]]
        finally:
            np.random.set_state(state)
        dense = torch.from_numpy(coarse.toarray()).to(device=device, dtype=torch.float64)
        factor, info = torch.linalg.cholesky_ex(dense)
        if int(info) != 0:
            raise SceneError("multigrid: the coarsest level's matrix is not positive definite (a node with no "
                             "mass?); use preconditioner='jacobi'")
        self.coarse_inverse = torch.cholesky_inverse(factor).to(dtype)
        self.coarse_rest = dense
        #: the finest level's rest row l1 norms ``[V d]``: its smoothing's scaling before the step's
        #: penalties (``MultigridSolve.load`` adds them)
        self.fine_row_l1 = torch.from_numpy(row_sums(matrix)).to(device=device, dtype=dtype)
        self._loaded = False  # whether the coarse operators hold a node stiffness (else the rest's)
        #: unknowns per level, finest first (the report's "levels")
        self.sizes = [level.size for level in self.levels] + [coarse.shape[0]]
        self.operator_complexity = float(hierarchy.operator_complexity())

    def load(self, node_stiffness: Optional[torch.Tensor], free: Optional[torch.Tensor] = None) -> None:
        """Carry a node stiffness N ``[V, d, d]`` (the floor's and tools' penalties, already times
        the step's c_K; None: none) into the coarse operators, in place: A_1 = A_1,rest +
        P_0^T N P_0 and so on down, the coarsest level's inverse formed again. N is block
        diagonal, so P^T N P has the pattern of P^T A P (A holds every diagonal block): the
        values are added where the coarse matrix already has entries. Rows of fixed nodes
        (``free [V, 1]`` zero) are left out, as the hierarchy's identity rows. Without the
        update the coarse corrections fight a penalty they do not know of, tens of times the
        elastic diagonal of the rows it acts on (docs/preconditioners.md). Raises SolverError,
        the levels back at the rest's, where a sparse product fails (cuSPARSE's SpGEMM runs out
        of resources on the GPU piles of hundreds of blocks)."""
        acting = None
        if node_stiffness is not None:
            block_norm = node_stiffness.abs().amax(dim=(-2, -1))
            if free is not None:
                block_norm = block_norm * free.reshape(-1)
            acting = torch.nonzero(block_norm > 0).reshape(-1)
            if acting.numel() == 0:
                acting = None
        if acting is None:
            if self._loaded:
                self._restore()
            return
        d = node_stiffness.shape[-1]
        axes = torch.arange(d, device=acting.device)
        rows = (acting[:, None, None] * d + axes[None, :, None]).expand(-1, d, d).reshape(-1)
        cols = (acting[:, None, None] * d + axes[None, None, :]).expand(-1, d, d).reshape(-1)
        values = node_stiffness[acting].reshape(-1).to(self.coarse_inverse.dtype)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            delta = torch.sparse_coo_tensor(torch.stack([rows, cols]), values, (self.sizes[0], self.sizes[0]))
            delta = delta.to_sparse_csr()
            for depth, level in enumerate(self.levels):
                try:
                    delta = self._galerkin(level, delta)
                except RuntimeError as err:  # (cuSPARSE's SpGEMM runs out of resources on large piles)
                    self._restore()  # (the levels above may hold part of this update)
                    raise SolverError(
                        f"preconditioner='multigrid' could not carry the floor's and tools' penalties into its "
                        f"coarse levels: the sparse product P^T N P of level {depth} ({level.size} unknowns) failed "
                        f"on {delta.device} ({str(err).splitlines()[0]}); use preconditioner='auto' (block Jacobi "
                        f"where contact pairs join a solve) for this scene; the state was not changed") from err
                if depth + 1 < len(self.levels):
                    self._add(self.levels[depth + 1], delta)
        factor, info = torch.linalg.cholesky_ex(self.coarse_rest + delta.to_dense().to(torch.float64))
        if int(info) == 0:  # (a penalty adds a positive semidefinite part: always, but for roundoff)
            self.coarse_inverse.copy_(torch.cholesky_inverse(factor))
        self._loaded = True

    @staticmethod
    def _galerkin(level: "_Level", delta: torch.Tensor) -> torch.Tensor:
        """P^T ``delta`` P (CSR) for the level's prolongation P: the level below's part of a fine
        node stiffness (torch's sparse products)."""
        prolong, restrict = level.sparse_transfers()
        return restrict @ (delta @ prolong)

    @staticmethod
    def _add(level: "_Level", delta: torch.Tensor) -> None:
        """The level's matrix made rest + ``delta`` (CSR, within its pattern), its l1 scaling
        rest + |delta|'s row sums."""
        coo = torch._convert_indices_from_csr_to_coo(delta.crow_indices(), delta.col_indices()).long()
        where = level.matrix.index_of(coo[0], coo[1])
        level.matrix.values.view(-1).copy_(level.rest_values.view(-1).index_add(0, where, delta.values()))
        row_l1 = level.rest_l1.index_add(0, coo[0], delta.values().abs())  # >= the row's l1: D^-1 A stays in (0, 1]
        level.inverse_diagonal.copy_(torch.where(row_l1 > 0, 1.0 / row_l1, 0.0))

    def _restore(self) -> None:
        for level in self.levels[1:]:
            level.matrix.values.copy_(level.rest_values)
            level.inverse_diagonal.copy_(torch.where(level.rest_l1 > 0, 1.0 / level.rest_l1, 0.0))
        self.coarse_inverse.copy_(torch.cholesky_inverse(torch.linalg.cholesky(self.coarse_rest)))
        self._loaded = False

    def _cycle(self, depth: int, b: torch.Tensor, fine) -> torch.Tensor:
        if depth == len(self.levels):
            return self.coarse_inverse @ b
        level = self.levels[depth]
        if depth == 0 and fine is not None:
            matrix, (product, inverse_diagonal) = None, fine
        else:
            matrix, product, inverse_diagonal = level.matrix, None, level.inverse_diagonal
        x = _smooth(matrix, product, inverse_diagonal, level.steps, b, None)
        residual = b - product(x) if matrix is None else bsr_gemv(matrix, x, b, alpha=-1.0, beta=1.0)
        coarse = self._cycle(depth + 1, bsr_gemv(level.restrict, residual), None)
        bsr_gemv(level.prolong, coarse, x, out=x)  # x += P e
        return _smooth(matrix, product, inverse_diagonal, level.steps, b, x)

    def __call__(self, r: torch.Tensor, fine_product=None, fine_inverse_diagonal=None) -> torch.Tensor:
        """z = V(r): one V-cycle on the residual ``r [V, d]`` (its shape kept).

        ``fine_product`` (p ``[V, d]`` -> A p ``[V, d]``) and ``fine_inverse_diagonal [V, d]``:
        the finest level's operator and its smoothing's scaling (the inverse of its rows' l1
        norms, or a bound of them) in place of the hierarchy's (the step's true matrix, with its
        contact stiffness and tangent, where the hierarchy holds the rest stiffness); both or
        neither."""
        fine = None
        if fine_product is not None:
            shape = r.shape
            fine = (lambda x: fine_product(x.view(shape)).reshape(-1), fine_inverse_diagonal.reshape(-1))
        return self._cycle(0, r.reshape(-1), fine).reshape(r.shape)


__all__ = ["Multigrid", "rest_system_matrix", "rigid_body_modes", "COARSE_SIZE", "MAX_DIRECT"]
