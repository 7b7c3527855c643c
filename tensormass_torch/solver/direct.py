"""A sparse Cholesky factorisation of the step's matrix at rest, as CG's preconditioner.

Where the step's matrix is constant (hooke, no contact: c_M M + c_K K with fixed coefficients),
its factorisation made once solves every step exactly: preconditioned CG then stops after one
iteration, so ``preconditioner="cholesky"`` is the direct-solver baseline the iterative choices
are measured against. Elsewhere (stvk and corotational tangents, the floor's and tools'
penalties, body contact) the factor is that of the rest matrix and CG corrects the difference
in a few iterations, as for the multigrid's finest level.

The factorisation is cholespy's (a well-kept library: CHOLMOD's supernodal factorisation on the
host, its triangular solves on the solve's device, CPU or CUDA). Its matrix is the one the
multigrid is built from (``multigrid.rest_system_matrix``: fixed nodes' rows and columns the
identity's). Its solves launch their own kernels outside torch's streams, so they are not
captured in CUDA graphs: the iterations that use it run eagerly.
"""
from __future__ import annotations

import numpy as np
import torch

from ..errors import SceneError
from .preconditioner import optional_module


class RestCholesky:
    """r ``[V, d]`` -> A^-1 r ``[V, d]`` for a scipy sparse ``matrix`` A ``[V d, V d]`` (symmetric
    positive definite), factorised once in the solve's ``dtype`` (float32 or float64) for its
    ``device``."""

    def __init__(self, matrix, dtype: torch.dtype, device):
        cholespy = optional_module("cholespy", "cholesky", "factorises", "direct")
        coo = matrix.tocoo()
        solver = {torch.float32: cholespy.CholeskySolverF, torch.float64: cholespy.CholeskySolverD}.get(dtype)
        if solver is None:
            raise SceneError(f"preconditioner='cholesky' needs float32 or float64, got {dtype}")
        device = torch.device(device)
        rows = torch.from_numpy(coo.row.astype(np.int32)).to(device)
        cols = torch.from_numpy(coo.col.astype(np.int32)).to(device)
        values = torch.from_numpy(coo.data).to(device=device, dtype=dtype)
        try:
            self.solver = solver(coo.shape[0], rows, cols, values, cholespy.MatrixType.COO)
        except Exception as err:  # noqa: BLE001 (cholespy's own words, under one clear error)
            raise SceneError(f"preconditioner='cholesky': the factorisation failed ({err})") from err
        self.size = coo.shape[0]
        #: nonzeros of the factorised matrix (the report's size)
        self.nonzeros = int(coo.nnz)

    #: what a captured graph would need and this cannot give (see the module docstring)
    capturable = False

    def __call__(self, r: torch.Tensor) -> torch.Tensor:
        """z = A^-1 r for ``r [V, d]`` (its shape kept)."""
        rhs = r.reshape(-1).contiguous()
        out = torch.empty_like(rhs)
        self.solver.solve(rhs, out)
        return out.reshape(r.shape)


__all__ = ["RestCholesky"]
