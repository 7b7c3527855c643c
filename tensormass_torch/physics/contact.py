"""Penalty contact with planes: f = k max(0, d - n.x) n on every node, and its differential."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Sequence

import torch

from ..errors import SceneError


@dataclass(frozen=True)
class Plane:
    """The half-space n.x >= offset, pushed back by a penalty of ``stiffness`` (N/m per node).

    ``normal`` is normalised on use; the force on a node below the plane is
    ``stiffness * (offset - n.x) * n`` (SOFA's ``PlaneForceField``).
    """

    normal: Sequence[float]
    offset: float
    stiffness: float

    def __post_init__(self):
        n = torch.as_tensor(self.normal, dtype=torch.float64)
        if n.shape != (3,) or not torch.isfinite(n).all() or float(n.norm()) == 0.0:
            raise SceneError(f"plane normal must be 3 finite numbers, not all zero; got {self.normal!r}")
        if not (self.stiffness > 0 and torch.isfinite(torch.tensor(float(self.stiffness)))):
            raise SceneError(f"plane stiffness must be positive and finite; got {self.stiffness!r}")


class Planes:
    """Planes stacked for evaluation: normals ``[P, 3]``, offsets ``[P]``, stiffness ``[P]``."""

    def __init__(self, planes: Sequence[Plane], dtype, device):
        normals = torch.tensor([list(p.normal) for p in planes], dtype=dtype, device=device).reshape(-1, 3)
        self.normals = normals / normals.norm(dim=1, keepdim=True)
        self.offsets = torch.tensor([float(p.offset) for p in planes], dtype=dtype, device=device)
        self.stiffness = torch.tensor([float(p.stiffness) for p in planes], dtype=dtype, device=device)

    def __len__(self):
        return self.offsets.numel()

    def to(self, dtype=None, device=None) -> "Planes":
        """These planes with their tensors in ``dtype`` on ``device`` (a copy; None keeps each)."""
        other = Planes.__new__(Planes)
        for name in ("normals", "offsets", "stiffness"):
            setattr(other, name, getattr(self, name).to(dtype=dtype, device=device))
        return other

    # Elementwise products and small sums over the 3 coordinates / P planes rather than matrix
    # products: x @ normals.T is a [V, 3] x [3, P] product that BLAS runs as a slow skinny GEMV
    # (17 us for 19k nodes on an H100, against ~2 us for the elementwise form).

    def penetration(self, x: torch.Tensor) -> torch.Tensor:
        """max(0, d - n.x) per node and plane ``[V, P]``."""
        return torch.clamp(self.offsets - (x[:, None, :] * self.normals).sum(-1), min=0.0)

    def _forces(self, depth: torch.Tensor) -> torch.Tensor:
        return ((depth * self.stiffness)[:, :, None] * self.normals).sum(1)

    def _node_stiffness(self, depth: torch.Tensor) -> torch.Tensor:
        active = (depth > 0).to(depth.dtype) * self.stiffness  # [V, P]
        outer = self.normals[:, :, None] * self.normals[:, None, :]  # [P, 3, 3]
        return (active[:, :, None, None] * outer).sum(1)

    def forces(self, x: torch.Tensor) -> torch.Tensor:
        """Penalty forces ``[V, 3]`` at positions ``x [V, 3]``."""
        return self._forces(self.penetration(x))

    def node_stiffness(self, x: torch.Tensor) -> torch.Tensor:
        """-(df/dx) per node ``[V, 3, 3]``: sum over the planes a node is below of k n n^T."""
        return self._node_stiffness(self.penetration(x))

    def linearize(self, x: torch.Tensor):
        """Forces ``[V, 3]`` and node stiffness ``[V, 3, 3]`` (as :meth:`forces`,
        :meth:`node_stiffness`) at ``x [V, 3]`` from one evaluation of the penetrations: what
        an implicit step needs (its force differential is ``-node_stiffness @ dx``)."""
        depth = self.penetration(x)  # [V, P]
        return self._forces(depth), self._node_stiffness(depth)

    def energy(self, x: torch.Tensor) -> torch.Tensor:
        """The penalty energy (0-dim) at ``x [V, 3]``: sum over nodes and planes of k/2 pen^2."""
        return 0.5 * (self.stiffness * self.penetration(x) ** 2).sum()

    def dforces(self, x: torch.Tensor, dx: torch.Tensor) -> torch.Tensor:
        """(df/dx) dx = -k n (n.dx) on nodes in contact ``[V, 3]``."""
        active = (self.penetration(x) > 0).to(x.dtype)
        along = (active * self.stiffness) * (dx[:, None, :] * self.normals).sum(-1)  # [V, P]
        return -(along[:, :, None] * self.normals).sum(1)
