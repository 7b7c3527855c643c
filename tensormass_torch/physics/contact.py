"""Penalty contact with planes: f = k max(0, d - n.x) n on every node, and its differential; the
regularised Coulomb friction that planes and tools put on the nodes in contact with them.

Friction (a plane's or a tool's ``friction`` mu > 0). A node in contact with normal force lambda
= k max(0, -g) and tangential velocity v_t (relative to the surface, P_t (v - v_surface), P_t =
I - n n^T) feels

    f = -c P_t (v - v_surface),     c = mu lambda / max(|v_t|, eps_v)

Coulomb's mu lambda against a slip faster than ``friction_velocity`` eps_v, a viscous drag below it
(a sticking node creeps at less than eps_v). c is taken at the step's start (lagged, as the
contact's linearisation is), so over a step the friction is a damper, linear in the velocity:
:class:`NodeDamping` (C = sum c P_t per node, symmetric positive semi-definite), which implicit
Euler takes implicitly (h C joins the step's matrix). The same law as between bodies
(``body_contact``), here per node.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Sequence

import torch

from ..errors import SceneError


def coulomb_damping(friction, normal_force: torch.Tensor, slip_speed: torch.Tensor,
                    friction_velocity) -> torch.Tensor:
    """The regularised Coulomb damping c = mu lambda / max(|v_t|, eps_v) (N s/m), elementwise:
    ``friction`` mu, ``normal_force`` lambda >= 0, ``slip_speed`` |v_t|, ``friction_velocity``
    eps_v > 0 (numbers or broadcastable tensors)."""
    return friction * normal_force / torch.clamp(slip_speed, min=friction_velocity)


@dataclass
class NodeDamping:
    """Friction on nodes over one step, as a damper: ``f = drive - C v``.

    Attributes:
        matrix: ``[V, 3, 3]`` C, per node the sum of c P_t over what it touches (symmetric
            positive semi-definite).
        drive: ``[V, 3]`` C v_surface: the force at rest on a node touching a moving surface
            (zero against planes and still tools).
    """

    matrix: torch.Tensor
    drive: torch.Tensor

    def product(self, v: torch.Tensor) -> torch.Tensor:
        """C v ``[V, 3]``."""
        return (self.matrix * v[:, None, :]).sum(-1)

    def forces(self, v: torch.Tensor) -> torch.Tensor:
        """The friction forces ``drive - C v`` ``[V, 3]`` at node velocities ``v [V, 3]``."""
        return self.drive - self.product(v)

    def __add__(self, other: "NodeDamping") -> "NodeDamping":
        return NodeDamping(self.matrix + other.matrix, self.drive + other.drive)


def tangential_part(vector: torch.Tensor, normal: torch.Tensor) -> torch.Tensor:
    """P_t w = w - (w . n) n ``[..., 3]``: the part of ``vector`` across unit ``normal`` (both
    ``[..., 3]``, broadcast)."""
    return vector - (vector * normal).sum(-1, keepdim=True) * normal


def tangential_projector(normal: torch.Tensor) -> torch.Tensor:
    """P_t = I - n n^T ``[..., 3, 3]`` for unit normals ``[..., 3]``."""
    eye = torch.eye(3, dtype=normal.dtype, device=normal.device)
    return eye - normal[..., :, None] * normal[..., None, :]


def check_friction(friction, friction_velocity, what: str) -> None:
    """Raise a SceneError naming ``what`` unless mu >= 0 and eps_v > 0 are finite numbers."""
    def number(value):
        return isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)

    if not number(friction) or friction < 0:
        raise SceneError(f"{what} friction must be a non-negative finite number, got {friction!r}")
    if not number(friction_velocity) or friction_velocity <= 0:
        raise SceneError(f"{what} friction_velocity must be a positive finite number (m/s), "
                         f"got {friction_velocity!r}")


@dataclass(frozen=True)
class Plane:
    """The half-space n.x >= offset, pushed back by a penalty of ``stiffness`` (N/m per node).

    ``normal`` is normalised on use; the force on a node below the plane is
    ``stiffness * (offset - n.x) * n`` (SOFA's ``PlaneForceField``). ``friction``: the Coulomb
    coefficient mu against the plane (0: frictionless, the default); ``friction_velocity``: eps_v
    (m/s), the slip speed below which friction is viscous (see the module).
    """

    normal: Sequence[float]
    offset: float
    stiffness: float
    friction: float = 0.0
    friction_velocity: float = 1e-3

    def __post_init__(self):
        n = torch.as_tensor(self.normal, dtype=torch.float64)
        if n.shape != (3,) or not torch.isfinite(n).all() or float(n.norm()) == 0.0:
            raise SceneError(f"plane normal must be 3 finite numbers, not all zero; got {self.normal!r}")
        if not (self.stiffness > 0 and torch.isfinite(torch.tensor(float(self.stiffness)))):
            raise SceneError(f"plane stiffness must be positive and finite; got {self.stiffness!r}")
        check_friction(self.friction, self.friction_velocity, "plane")


def with_values(term, **values):
    """A shallow copy of the contact term ``term`` (planes, tools) with the attributes given in
    ``values`` in their place (None keeps the term's; the other tensors shared): the term as a
    function of those values, for autograd."""
    other = type(term).__new__(type(term))
    other.__dict__.update(term.__dict__)
    for name, value in values.items():
        if value is not None:
            setattr(other, name, value)
    return other


class Planes:
    """Planes stacked for evaluation: normals ``[P, 3]``, offsets ``[P]``, stiffness ``[P]``,
    friction coefficients and velocities ``[P]``."""

    def __init__(self, planes: Sequence[Plane], dtype, device):
        normals = torch.tensor([list(p.normal) for p in planes], dtype=dtype, device=device).reshape(-1, 3)
        self.normals = normals / normals.norm(dim=1, keepdim=True)
        self.offsets = torch.tensor([float(p.offset) for p in planes], dtype=dtype, device=device)
        self.stiffness = torch.tensor([float(p.stiffness) for p in planes], dtype=dtype, device=device)
        self.friction = torch.tensor([float(p.friction) for p in planes], dtype=dtype, device=device)
        self.friction_velocity = torch.tensor([float(p.friction_velocity) for p in planes], dtype=dtype,
                                              device=device)
        #: whether any plane has friction (known on the host: no device read to decide)
        self.has_friction = any(p.friction > 0 for p in planes)

    def __len__(self):
        return self.offsets.numel()

    def to(self, dtype=None, device=None) -> "Planes":
        """These planes with their tensors in ``dtype`` on ``device`` (a copy; None keeps each)."""
        other = Planes.__new__(Planes)
        for name in ("normals", "offsets", "stiffness", "friction", "friction_velocity"):
            setattr(other, name, getattr(self, name).to(dtype=dtype, device=device))
        other.has_friction = self.has_friction
        return other

    def replaced(self, offsets: Optional[torch.Tensor] = None, stiffness: Optional[torch.Tensor] = None) -> "Planes":
        """These planes with ``offsets`` / ``stiffness`` ``[P]`` in place of theirs (None keeps them;
        the other tensors shared): the planes as functions of those values, for autograd."""
        return with_values(self, offsets=offsets, stiffness=stiffness)

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

    def friction_damping(self, x: torch.Tensor, v: torch.Tensor) -> NodeDamping:
        """The planes' friction over a step from positions ``x [V, 3]`` and velocities ``v [V, 3]``
        (see the module): per node and plane it is below, c P_t with c = mu k depth /
        max(|P_t v|, eps_v)."""
        depth = self.penetration(x)  # [V, P]
        slip = tangential_part(v[:, None, :], self.normals)  # [V, P, 3]
        c = coulomb_damping(self.friction, self.stiffness * depth, torch.linalg.vector_norm(slip, dim=-1),
                            self.friction_velocity)  # [V, P]
        matrix = (c[:, :, None, None] * tangential_projector(self.normals)).sum(1)
        return NodeDamping(matrix, torch.zeros_like(x))
