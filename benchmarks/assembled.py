"""The alternative a user would pick instead of a matrix-free solver: assemble the implicit-Euler
system matrix as a sparse matrix and run CG on it.

    A = P (c_M M - c_K K) P + (I - P),   c_M = 1 + h r_M,   c_K = h (h + r_K)

K = dF/du at a linearisation point u (negative semi-definite: ``ops.dforces`` is K du), M the
lumped masses (3 x 3 diagonal blocks), P the projection on the free nodes; the identity on the
constrained dofs keeps A symmetric positive definite, and a right-hand side that is zero there
gives the same iterates as the matrix-free CG with its projections.

Assembly is exact for every model and form, through the ops: on a copy of each group whose
items (elements, or edges for the hooke tensor form) own their nodes (``exploded``), one call of
``ops.element_dforces`` per local unit vector (a, k) gives column (a, k) of the stiffness block
of every item at once (n d calls). A node term (the vertex tensors of the hooke tensor form) is
what ``ops.dforces`` adds to the gather of ``ops.element_dforces``: three calls along the unit
fields E_k give its diagonal blocks.

Layouts: torch sparse CSR (scalar, int32 indices where they fit) and BSR with 3 x 3 blocks;
CG in torch ops with per-object scalars (``cg_fixed``) or CuPy's ``cupyx.scipy.sparse.linalg.cg``
(``cupy_solver``). ``AssembledStepper`` runs whole implicit Euler steps this way.
"""
from __future__ import annotations

import contextlib
import copy
import warnings
from typing import Callable, Optional, Sequence

import torch

from tensormass_torch import ops
from tensormass_torch.mesh.topology import GatherPlan

# ---------------------------------------------------------------------------------------------
# element blocks
# ---------------------------------------------------------------------------------------------


def exploded(group):
    """A copy of ``group`` whose items own their nodes: item e's local node a is node e n + a of
    ``[N n, d]`` fields (nothing shared, so a unit vector at one local node of every item at
    once gives every item's stiffness column). Everything else (material, shape vectors,
    tensors, rest nodes) is the group's own; the group itself is not changed."""
    index = group.plan.index
    n_items, n = index.shape
    ids = torch.arange(n_items * n, device=index.device).reshape(n_items, n)
    copy_ = copy.copy(group)
    copy_._buffers = dict(group._buffers)  # a shallow copy would share (and change) the original's
    names = [k for k, b in group._buffers.items() if b is not None and b.shape == index.shape and torch.equal(b, index)]
    if not names:
        raise ValueError("cannot tell which buffer of the group holds its items")
    for name in names:
        copy_._buffers[name] = ids.to(group._buffers[name].dtype)
    copy_.plan = GatherPlan.build(ids, n_items * n)
    copy_.num_nodes = n_items * n
    copy_.__dict__.pop("_native_lame", None)
    return copy_


def element_blocks(group, u: torch.Tensor, split=None) -> torch.Tensor:
    """Stiffness blocks ``[N, n d, n d]`` of the items of ``group`` (elements, or edges for the
    hooke tensor form) at displacements ``u [V, d]``: ``blocks[e, b*d + l, a*d + k]`` =
    d(partial force of item e on its node b, dim l) / d(u of its node a, dim k), by n d calls
    of ``ops.element_dforces`` on ``split = exploded(group)`` (made here when None)."""
    index = group.plan.index
    n_items, n = index.shape
    d = u.shape[1]
    split = exploded(group) if split is None else split
    u_split = u[index].reshape(-1, d)
    state = ops.linearize(split, u_split)
    blocks = u.new_empty(n_items, n * d, n * d)
    du = torch.zeros_like(u_split)
    du_items = du.view(n_items, n, d)
    for a in range(n):
        for k in range(d):
            du.zero_()
            du_items[:, a, k] = 1.0
            blocks[:, :, a * d + k] = ops.element_dforces(split, u_split, du, state).reshape(n_items, n * d)
    return blocks


def node_blocks(group, u: torch.Tensor) -> Optional[torch.Tensor]:
    """Diagonal blocks ``[V, d, d]`` that ``ops.dforces`` adds to the gather of the item
    partials (the hooke tensor form's vertex tensors), or None when it adds nothing."""
    V, d = u.shape
    state = ops.linearize(group, u)
    cols = []
    for k in range(d):
        unit = torch.zeros_like(u)
        unit[:, k] = 1.0
        total = ops.dforces(group, u, unit, state)
        items = ops.node_gather(ops.element_dforces(group, u, unit, state), group.plan)
        cols.append(total - items)
    term = torch.stack(cols, dim=-1)  # [V, l, k]
    return term if bool(term.abs().max() > 0) else None


# ---------------------------------------------------------------------------------------------
# the system matrix
# ---------------------------------------------------------------------------------------------


@contextlib.contextmanager
def _quiet():
    """Without torch's "sparse CSR/BSR support is in beta" warning (once per process is noise)."""
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message="Sparse (CSR|BSR) tensor support is in beta")
        yield


class SystemMatrix:
    """A = P (c_M M - c_K K) P + (I - P) at ``u``, in 3 x 3 blocks, and its sparse layouts.

    Args:
        model: ``tm.TensorMass`` (e.g. ``sim.model``) over V nodes, d = 3.
        u: displacements ``[V, d]`` (positions minus ``model.rest``).
        mass: lumped masses ``[V]``. free: ``[V]`` bool (True: free node) or None (all free).
        c_mass, c_stiff: the coefficients c_M, c_K.
        splits: per group, ``exploded(group)`` (kept by callers that reassemble).
    Attributes:
        block_rows, block_cols: ``[M]`` node ids of the nonzero 3 x 3 blocks (sorted, unique).
        block_values: ``[M, d, d]``.
    """

    def __init__(self, model, u, mass, free, c_mass: float, c_stiff: float, splits: Optional[Sequence] = None):
        V, d = u.shape
        self.num_nodes, self.dim = V, d
        rows, cols, vals = [], [], []
        for g, group in enumerate(model.groups):
            index = group.plan.index
            n = index.shape[1]
            blocks = element_blocks(group, u, None if splits is None else splits[g])
            # [N, n(b), d(l), n(a), d(k)] -> per (b, a) node pair a 3 x 3 block
            blocks = blocks.reshape(-1, n, d, n, d).permute(0, 1, 3, 2, 4)
            rows.append(index[:, :, None].expand(-1, n, n).reshape(-1))
            cols.append(index[:, None, :].expand(-1, n, n).reshape(-1))
            vals.append(blocks.reshape(-1, d, d))
            term = node_blocks(group, u)
            if term is not None:
                ids = torch.arange(V, device=u.device)
                rows.append(ids)
                cols.append(ids)
                vals.append(term)
        values = -c_stiff * torch.cat(vals)
        rows, cols = torch.cat(rows), torch.cat(cols)
        eye = torch.eye(d, dtype=u.dtype, device=u.device)
        if free is not None:
            keep = (free[rows] & free[cols]).to(u.dtype)
            values = values * keep[:, None, None]
            diag = torch.where(free, c_mass * mass, torch.ones_like(mass))
        else:
            diag = c_mass * mass
        ids = torch.arange(V, device=u.device)
        rows = torch.cat([rows, ids])
        cols = torch.cat([cols, ids])
        values = torch.cat([values, diag[:, None, None] * eye])
        coo = torch.sparse_coo_tensor(torch.stack([rows, cols]), values, (V, V, d, d),
                                      check_invariants=False).coalesce()
        self.block_rows, self.block_cols = coo.indices()[0], coo.indices()[1]
        self.block_values = coo.values()

    def _index_dtype(self, nnz: int):
        return torch.int32 if nnz < 2**31 - 1 and self.num_nodes * self.dim < 2**31 - 1 else torch.int64

    def csr(self) -> torch.Tensor:
        """Scalar CSR ``[V d, V d]`` (int32 indices where they fit)."""
        d = self.dim
        br, bc, bv = self.block_rows, self.block_cols, self.block_values
        local = torch.arange(d, device=br.device)
        rows = (br[:, None, None] * d + local[None, :, None]).expand(-1, d, d).reshape(-1)
        cols = (bc[:, None, None] * d + local[None, None, :]).expand(-1, d, d).reshape(-1)
        n = self.num_nodes * d
        key = rows * n + cols
        order = torch.argsort(key)
        rows, cols, vals = rows[order], cols[order], bv.reshape(-1)[order]
        itype = self._index_dtype(vals.numel())
        crow = torch.zeros(n + 1, dtype=torch.long, device=rows.device)
        crow[1:] = torch.cumsum(torch.bincount(rows, minlength=n), 0)
        with _quiet():
            return torch.sparse_csr_tensor(crow.to(itype), cols.to(itype), vals, (n, n), check_invariants=False)

    def bsr(self) -> torch.Tensor:
        """BSR ``[V d, V d]`` with d x d blocks (the block COO is sorted by row, then column)."""
        d, V = self.dim, self.num_nodes
        itype = self._index_dtype(self.block_values.numel() * d * d)
        crow = torch.zeros(V + 1, dtype=torch.long, device=self.block_rows.device)
        crow[1:] = torch.cumsum(torch.bincount(self.block_rows, minlength=V), 0)
        with _quiet():
            return torch.sparse_bsr_tensor(crow.to(itype), self.block_cols.to(itype), self.block_values.contiguous(),
                                           (V * d, V * d), check_invariants=False)

    @property
    def nnz(self) -> int:
        return int(self.block_values.numel())

    def nbytes(self, layout: str) -> int:
        """Bytes one product reads from the matrix: values + column ids + row pointers."""
        s = self.block_values.element_size()
        ix = torch.empty((), dtype=self._index_dtype(self.nnz)).element_size()
        if layout == "bsr":
            return self.nnz * s + self.block_values.shape[0] * ix + (self.num_nodes + 1) * ix
        return self.nnz * (s + ix) + (self.num_nodes * self.dim + 1) * ix


def matrix_for(layout: str, system: SystemMatrix) -> torch.Tensor:
    if layout == "csr":
        return system.csr()
    if layout == "bsr":
        return system.bsr()
    raise ValueError(f"unknown sparse layout {layout!r}; expected 'csr' or 'bsr'")


def sparse_matvec(matrix: torch.Tensor) -> Callable[[torch.Tensor], torch.Tensor]:
    """p ``[V, d]`` -> A p ``[V, d]`` through the sparse layout's product."""

    def apply(p: torch.Tensor) -> torch.Tensor:
        return (matrix @ p.reshape(-1, 1)).reshape(p.shape)

    return apply


# ---------------------------------------------------------------------------------------------
# CG on the assembled matrix
# ---------------------------------------------------------------------------------------------


def cg_fixed(matvec: Callable[[torch.Tensor], torch.Tensor], rhs: torch.Tensor, lengths: Optional[torch.Tensor],
             iterations: int) -> torch.Tensor:
    """``iterations`` CG iterations from x = 0 on A x = rhs ``[V, d]``, with per-object scalars
    (objects own contiguous node ranges of ``lengths [B]`` nodes; None: one object). No host
    synchronisation: a zero curvature or residual stops an object by zeroing its step."""
    def dot(a, b):
        if lengths is None:
            return (a * b).sum()
        return torch.segment_reduce((a * b).sum(-1), "sum", lengths=lengths)

    def spread(s):
        return s if lengths is None else torch.repeat_interleave(s, lengths, output_size=rhs.shape[0])[:, None]

    x = torch.zeros_like(rhs)
    r = rhs.clone()
    p = r.clone()
    rr = dot(r, r)
    for _ in range(iterations):
        ap = matvec(p)
        pap = dot(p, ap)
        alpha = torch.where(pap > 0, rr / torch.where(pap > 0, pap, torch.ones_like(pap)), torch.zeros_like(pap))
        x = x + spread(alpha) * p
        r = r - spread(alpha) * ap
        rr_new = dot(r, r)
        beta = torch.where(rr > 0, rr_new / torch.where(rr > 0, rr, torch.ones_like(rr)), torch.zeros_like(rr))
        p = r + spread(beta) * p
        rr = rr_new
    return x


def cupy_solver(matrix_csr: torch.Tensor):
    """``solve(rhs [V, d], iterations) -> x [V, d]`` through ``cupyx.scipy.sparse.linalg.cg`` on
    the same CSR (shared through DLPack), tolerance 0 so it runs every iteration; None when
    CuPy does not import or the matrix is not on a CUDA device."""
    if matrix_csr.device.type != "cuda":
        return None
    try:
        import cupy
        import cupyx.scipy.sparse as cusparse
        import cupyx.scipy.sparse.linalg as culinalg
    except Exception:
        return None
    crow = cupy.from_dlpack(matrix_csr.crow_indices().to(torch.int32).contiguous())
    col = cupy.from_dlpack(matrix_csr.col_indices().to(torch.int32).contiguous())
    val = cupy.from_dlpack(matrix_csr.values().contiguous())
    a = cusparse.csr_matrix((val, col, crow), shape=tuple(matrix_csr.shape))

    def solve(rhs: torch.Tensor, iterations: int) -> torch.Tensor:
        b = cupy.from_dlpack(rhs.reshape(-1).contiguous())
        try:
            x, _ = culinalg.cg(a, b, tol=0.0, atol=0.0, maxiter=iterations)
        except TypeError:  # newer CuPy names the relative tolerance rtol
            x, _ = culinalg.cg(a, b, rtol=0.0, atol=0.0, maxiter=iterations)
        return torch.from_dlpack(x).reshape(rhs.shape)

    return solve


# ---------------------------------------------------------------------------------------------
# whole implicit Euler steps
# ---------------------------------------------------------------------------------------------


class AssembledStepper:
    """Implicit Euler steps of a ``tm.Simulator``'s scene through an assembled matrix: the same
    equations as ``sim.step`` (one linearisation per step, Rayleigh damping, fixed CG budget
    ``sim.options.cg_max_iter``), forces from ``sim.model`` (the same op as ours), and

        A  assembled at x (every step, or once for ``hooke``, whose K does not depend on x)
        K v on the free rows as (c_M M v - A v) / c_K (exact there: fixed nodes have v = 0)
        CG ``cg_fixed`` on the sparse layout (or CuPy's cg with ``layout="cupy"``, one object)

    Contact planes and prescribed motion are not modelled (the benchmark scenes' planes are
    not touched during the measured steps). It starts from the simulator's current state and
    does not change it.

    Args:
        sim: the ``tm.Simulator``. gravity: its ``[3]`` gravity (not kept by the Simulator).
        layout: "csr" | "bsr" | "cupy".
    """

    def __init__(self, sim, gravity, layout: str = "csr"):
        self.sim, self.layout = sim, layout
        self.model = sim.model
        opts = sim.options
        self.h = opts.dt
        self.r_mass, self.r_stiff = opts.rayleigh_mass, opts.rayleigh_stiffness
        self.c_mass = 1.0 + self.h * self.r_mass
        self.c_stiff = self.h * (self.h + self.r_stiff)
        self.iterations = opts.cg_max_iter
        self.mass = self.model.lumped_mass()
        self.free = ~(sim.fixed | sim.prescribed)
        self.free_col = self.free.to(self.mass.dtype)[:, None]
        g = torch.as_tensor(gravity, dtype=self.mass.dtype, device=self.mass.device)
        self.external = self.mass[:, None] * g
        self.lengths = None if sim.num_bodies == 1 else torch.as_tensor(
            [sim.ptr[i + 1] - sim.ptr[i] for i in range(sim.num_bodies)], device=self.mass.device)
        if layout == "cupy" and sim.num_bodies != 1:
            raise ValueError("the CuPy alternative runs one object (its cg has one set of scalars)")
        self.reassemble = any(gr.model != "hooke" for gr in self.model.groups)
        self.splits = [exploded(gr) for gr in self.model.groups]
        self.x, self.v = sim.x.clone(), sim.v.clone()
        self._matrix = None
        self.system = None

    def assemble(self, x) -> None:
        """A at positions x ``[V, 3]``: its block values, then the layout (and solver)."""
        self.system = SystemMatrix(self.model, x - self.model.rest, self.mass, self.free, self.c_mass,
                                   self.c_stiff, self.splits)
        matrix = matrix_for("csr" if self.layout == "cupy" else self.layout, self.system)
        if self.layout == "cupy":
            solve = cupy_solver(matrix)
            if solve is None:
                raise RuntimeError("CuPy is not importable here or the matrix is not on a CUDA device")
            self._solve = solve
        else:
            product = sparse_matvec(matrix)
            self._solve = lambda rhs, k: cg_fixed(product, rhs, self.lengths, k)
        self._matvec = sparse_matvec(matrix)
        self._matrix = matrix

    def solve(self, rhs: torch.Tensor, iterations: Optional[int] = None) -> torch.Tensor:
        """CG on the current matrix: ``iterations`` (default: the simulator's budget)."""
        return self._solve(rhs, self.iterations if iterations is None else iterations)

    def rhs(self) -> torch.Tensor:
        """The step's right-hand side ``[V, 3]`` at the current state, on the matrix assembled last:
        h (f + (h + r_K) K v - r_M M v) on the free rows."""
        h = self.h
        f = self.model(self.x) + self.external
        kv = (self.c_mass * self.mass[:, None] * self.v - self._matvec(self.v)) / self.c_stiff
        return h * (f + (h + self.r_stiff) * kv - self.r_mass * self.mass[:, None] * self.v) * self.free_col

    def step(self, n: int = 1) -> None:
        h = self.h
        for _ in range(int(n)):
            if self._matrix is None or self.reassemble:
                self.assemble(self.x)
            rhs = self.rhs()
            dv = self.solve(rhs)
            self.v = self.v + dv
            self.x = self.x + h * self.v
