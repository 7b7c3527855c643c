"""Rigid kinematic tools (sphere, capsule, box) pressing on the bodies' nodes by a penalty on their
signed distance; the force, its exact stiffness and the reaction on each tool.

A tool is a shape in its own frame (origin ``position``, axes the columns of ``rotation``) moved
along a path given by keyframes (``times``, ``positions``: the origin, linearly interpolated, held
before the first and after the last) or by a callable ``t -> [3]``. Its signed distance d(x)
(negative inside) gives every node x a gap ``g = d(x) - thickness`` and, while ``g < 0``, the
penalty energy, force and stiffness

    E = k/2 g^2         f = -dE/dx = -k g n         d2E/dx2 = k (n n^T + g H)

with ``n = grad d`` (unit) and ``H`` the Hessian of d (the curvature of its level set: (I - n n^T)
/ rho outside a sphere of centre distance rho; zero on a flat face). H n = 0, so the Hessian's
eigenvalues are k along n and k g kappa_i <= 0 across it (g < 0 in contact; kappa_i the surface's
curvatures): a node pressed into a convex tool can slide off it. That negative part, |f| kappa, can
outweigh a light node's mass term M / h^2 and make the step's matrix indefinite (CG breaks down;
docs/contact.md gives the case met). So the stiffness the step uses is, by default
(``tangent="projected"``), the Hessian projected onto the positive semi-definite matrices: k n n^T
(its negative eigenvalues set to 0); the exact Hessian is ``tangent="exact"`` (tests check it
against finite differences of the force, and the projection against the exact one's
eigen-decomposition). On flat parts (a box's faces) the two are the same. The step linearises at
its start with the tool where it will be at the end (``ToolSet.set_time``), as for the planes.

With ``friction`` mu > 0 a tool also drags the nodes touching it: regularised Coulomb against
the tool's velocity over the step (``physics.contact`` gives the law), taken implicitly as a
damper.

The reaction on a tool is minus the sum of the forces it puts on the nodes (penalty and, given
the nodes' velocities, friction); its torque is taken about the tool's origin. Every node of
every body meets every tool (a dense pass over the nodes: tools are few, and a pass is a handful
of elementwise ops).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Callable, Optional, Sequence, Tuple

import torch

from ..errors import MeshError, SceneError
from ..mesh.distance import SignedDistanceGrid, signed_distance_grid
from .contact import (
    NodeDamping,
    check_friction,
    coulomb_damping,
    tangential_part,
    tangential_projector,
    with_values,
)

#: the tool shapes (``Tool.shape``)
SHAPES = ("sphere", "capsule", "box", "mesh")
#: the stiffness a tool gives the implicit step (``Tool.tangent``)
TANGENTS = ("projected", "exact")


def _vector(value, name: str, size: int = 3) -> Tuple[float, ...]:
    try:
        t = torch.as_tensor(value, dtype=torch.float64)
    except (TypeError, ValueError) as exc:
        raise SceneError(f"{name} must be {size} finite numbers, got {value!r}") from exc
    if t.shape != (size,) or not bool(torch.isfinite(t).all()):
        raise SceneError(f"{name} must be {size} finite numbers, got {value!r}")
    return tuple(float(v) for v in t)


def _positive(value, name: str, allow_zero: bool = False) -> float:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if not ok or value < 0 or (value == 0 and not allow_zero):
        raise SceneError(f"{name} must be a {'non-negative' if allow_zero else 'positive'} finite number, "
                         f"got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Tool:
    """A rigid tool (build one with :func:`Sphere`, :func:`Capsule`, :func:`Box` or :func:`MeshTool`).

    Attributes:
        shape: ``"sphere"``, ``"capsule"`` (a segment of half length ``size[1]`` along the tool's
            first axis, radius ``size[0]``), ``"box"`` (half extents ``size``) or ``"mesh"`` (a
            closed triangle surface through its signed distance grid ``grid``).
        size: the shape's dimensions (sphere: ``(radius,)``; a mesh: none).
        stiffness: penalty k (N/m per node).
        thickness: contact distance: a node is pushed back once closer than this to the surface.
        position: the origin ``[3]`` where no path is given.
        rotation: ``[3, 3]`` the tool's axes in world coordinates (columns; a rotation matrix).
        times, positions: keyframes of the origin (``[K]`` increasing, ``[K, 3]``), or empty.
        motion: ``t -> [3]`` origin at time t, or None (instead of keyframes).
        name: for reports.
        tangent: the stiffness the implicit step uses: ``"projected"`` (k n n^T, positive
            semi-definite; default) or ``"exact"`` (the energy's Hessian, with the surface's
            curvature: indefinite in contact with a curved tool). See the module's notes.
        friction: Coulomb coefficient mu between the tool and the nodes (0: frictionless, the
            default; regularised as ``physics.contact`` says, against the tool's velocity).
        friction_velocity: eps_v (m/s), the slip speed below which friction is viscous.
        grid: a mesh tool's ``mesh.distance.SignedDistanceGrid`` in its own frame (None for the
            other shapes).
        surface: a mesh tool's triangles in its own frame, ``(vertices [K, 3] float64, triangles
            [F, 3] int64)`` on the CPU, kept to draw it (None for the other shapes).
    """

    shape: str
    size: Tuple[float, ...]
    stiffness: float
    thickness: float = 0.0
    position: Tuple[float, float, float] = (0.0, 0.0, 0.0)
    rotation: Tuple[Tuple[float, float, float], ...] = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    times: Tuple[float, ...] = ()
    positions: Tuple[Tuple[float, float, float], ...] = ()
    motion: Optional[Callable[[float], Sequence[float]]] = field(default=None, compare=False)
    name: Optional[str] = None
    tangent: str = "projected"
    friction: float = 0.0
    friction_velocity: float = 1e-3
    grid: Optional[SignedDistanceGrid] = field(default=None, compare=False, repr=False)
    surface: Optional[Tuple[torch.Tensor, torch.Tensor]] = field(default=None, compare=False, repr=False)

    def __post_init__(self):
        if self.shape not in SHAPES:
            raise SceneError(f"tool shape must be one of {', '.join(map(repr, SHAPES))}, got {self.shape!r}")
        sizes = {"sphere": ("radius",), "capsule": ("radius", "half_length"),
                 "box": ("half_extents[0]", "half_extents[1]", "half_extents[2]"), "mesh": ()}[self.shape]
        if (self.shape == "mesh") != isinstance(self.grid, SignedDistanceGrid):
            raise SceneError("a mesh tool needs its signed distance grid (build it with tm.MeshTool), and only it")
        if len(self.size) != len(sizes):
            raise SceneError(f"a {self.shape} takes {len(sizes)} sizes ({', '.join(sizes)}), got {self.size!r}")
        for value, name in zip(self.size, sizes):
            _positive(value, f"{self.shape} {name}", allow_zero=self.shape == "capsule" and name == "half_length")
        _positive(self.stiffness, "tool stiffness")
        if self.tangent not in TANGENTS:
            raise SceneError(f"tool tangent must be one of {', '.join(map(repr, TANGENTS))}, got {self.tangent!r}")
        _positive(self.thickness, "tool thickness", allow_zero=True)
        check_friction(self.friction, self.friction_velocity, "tool")
        _vector(self.position, "tool position")
        r = torch.as_tensor(self.rotation, dtype=torch.float64)
        if r.shape != (3, 3) or not bool(torch.isfinite(r).all()) \
                or float((r.T @ r - torch.eye(3, dtype=torch.float64)).abs().max()) > 1e-6 \
                or float(torch.linalg.det(r)) < 0:
            raise SceneError(f"tool rotation must be a 3x3 rotation matrix (orthonormal, det +1), "
                             f"got {self.rotation!r}")
        if len(self.times) != len(self.positions):
            raise SceneError(f"tool times ({len(self.times)}) and positions ({len(self.positions)}) must match")
        if self.times:
            t = torch.as_tensor(self.times, dtype=torch.float64)
            if not bool(torch.isfinite(t).all()) or bool((t[1:] <= t[:-1]).any()):
                raise SceneError(f"tool times must be finite and increasing, got {list(self.times)}")
            for k, p in enumerate(self.positions):
                _vector(p, f"tool positions[{k}]")
            if self.motion is not None:
                raise SceneError("give a tool keyframes (times, positions) or a motion callable, not both")
        if self.motion is not None and not callable(self.motion):
            raise SceneError(f"tool motion must be a callable t -> [3], got {type(self.motion).__name__}")

    @property
    def moves(self) -> bool:
        """Whether the origin changes over time (keyframes at two places, or a callable)."""
        return self.motion is not None or len(set(self.positions)) > 1

    def origin(self, t: float) -> Tuple[float, float, float]:
        """The origin at time ``t``."""
        if self.motion is not None:
            return _vector(self.motion(t), f"tool motion({t:g})")
        if not self.times:
            return tuple(self.position)
        times = self.times
        if t <= times[0]:
            return tuple(self.positions[0])
        if t >= times[-1]:
            return tuple(self.positions[-1])
        k = max(i for i in range(len(times) - 1) if times[i] <= t)
        s = (t - times[k]) / (times[k + 1] - times[k])
        a, b = self.positions[k], self.positions[k + 1]
        return tuple(a[i] + s * (b[i] - a[i]) for i in range(3))


def _path(position, times, positions):
    position = _vector(position, "tool position")
    times = tuple(float(t) for t in times) if times is not None else ()
    positions = tuple(_vector(p, f"tool positions[{k}]") for k, p in enumerate(positions)) if positions is not None \
        else ()
    return position, times, positions


def _rotation(rotation):
    if rotation is None:
        return ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    try:
        r = torch.as_tensor(rotation, dtype=torch.float64)
    except (TypeError, ValueError) as exc:
        raise SceneError(f"tool rotation must be a 3x3 rotation matrix, got {rotation!r}") from exc
    if r.shape != (3, 3):
        raise SceneError(f"tool rotation must be a 3x3 rotation matrix, got shape {tuple(r.shape)}")
    return tuple(tuple(float(v) for v in row) for row in r)


def Sphere(radius: float, position=(0.0, 0.0, 0.0), stiffness: float = 1e5, thickness: float = 0.0, *,
           times=None, positions=None, motion=None, name: Optional[str] = None, tangent: str = "projected",
           friction: float = 0.0, friction_velocity: float = 1e-3) -> Tool:
    """A sphere of ``radius`` centred on its origin (``position``, or keyframes ``times``,
    ``positions``, or ``motion(t) -> [3]``)."""
    position, times, positions = _path(position, times, positions)
    return Tool("sphere", (radius,), stiffness, thickness, position, _rotation(None), times, positions, motion, name,
                tangent, friction, friction_velocity)


def Capsule(radius: float, half_length: float, position=(0.0, 0.0, 0.0), rotation=None, stiffness: float = 1e5,
            thickness: float = 0.0, *, times=None, positions=None, motion=None, name: Optional[str] = None,
            tangent: str = "projected", friction: float = 0.0, friction_velocity: float = 1e-3) -> Tool:
    """A capsule: the points within ``radius`` of the segment from -``half_length`` to
    +``half_length`` along the tool's first axis (``rotation``'s first column; default x)."""
    position, times, positions = _path(position, times, positions)
    return Tool("capsule", (radius, half_length), stiffness, thickness, position, _rotation(rotation), times,
                positions, motion, name, tangent, friction, friction_velocity)


def Box(half_extents, position=(0.0, 0.0, 0.0), rotation=None, stiffness: float = 1e5, thickness: float = 0.0, *,
        times=None, positions=None, motion=None, name: Optional[str] = None, tangent: str = "projected",
        friction: float = 0.0, friction_velocity: float = 1e-3) -> Tool:
    """A box of ``half_extents [3]`` along the tool's axes (``rotation``'s columns)."""
    position, times, positions = _path(position, times, positions)
    return Tool("box", _vector(half_extents, "box half_extents"), stiffness, thickness, position,
                _rotation(rotation), times, positions, motion, name, tangent, friction, friction_velocity)


def MeshTool(surface, position=(0.0, 0.0, 0.0), rotation=None, stiffness: float = 1e5, thickness: float = 0.0, *,
             resolution: int = 32, spacing: Optional[float] = None, times=None, positions=None, motion=None,
             name: Optional[str] = None, tangent: str = "projected", friction: float = 0.0,
             friction_velocity: float = 1e-3, device=None) -> Tool:
    """A tool of any closed triangle surface: ``surface`` is a file path (any meshio surface
    format), a ``tm.TriMesh``, ``(vertices [V, 3], triangles [F, 3])`` or a pyvista PolyData,
    its coordinates in the tool's frame (placed at ``position`` or along a path, turned by
    ``rotation``). Its signed distance is sampled once on a grid of ``resolution`` cells along
    its longest side (or of ``spacing``) that reaches ``thickness`` and two cells past it
    (``mesh.distance``): the distance between grid nodes is trilinear, so corners are rounded
    over about a cell, and parts thinner than about two cells are lost (a finer resolution
    keeps them). Building the grid costs seconds on a CPU for thousands of triangles,
    milliseconds on a GPU (``device``: where it is built; the simulator moves it to its own).

    Raises:
        MeshError: the surface is not closed (an edge not shared by exactly two triangles), is
            wound inconsistently, or encloses no volume.
    """
    from ..mesh.surface import _surface_arrays

    position, times, positions = _path(position, times, positions)
    _positive(thickness, "tool thickness", allow_zero=True)
    what = f"tool mesh {name!r}" if name else "tool mesh"
    try:
        vertices, triangles = _surface_arrays(surface)
    except MeshError as exc:
        raise MeshError(f"{what}: {exc}") from None
    grid = signed_distance_grid(vertices, triangles, resolution=resolution, spacing=spacing, margin=thickness,
                                device=device, what=what)
    surface = (torch.as_tensor(vertices).detach().to("cpu", torch.float64),
               torch.as_tensor(triangles).detach().to("cpu", torch.int64))
    return Tool("mesh", (), stiffness, thickness, position, _rotation(rotation), times, positions, motion, name,
                tangent, friction, friction_velocity, grid, surface)


# ---------------------------------------------------------------------------------------------
# Signed distances in the tool's frame: d [V], its gradient n [V, 3] and Hessian H [V, 3, 3] at
# local points q [V, 3]. Where the gradient is undefined (a sphere's centre, a capsule's axis, a
# box's medial planes) any unit vector is as good: the energy has a kink there, which a node
# reaches only by passing through the tool.
# ---------------------------------------------------------------------------------------------


def _point_distance(w: torch.Tensor, curvature_axes: torch.Tensor):
    """Distance |w| to a point, line or box feature: d [V], n = w/|w| [V, 3] and H = (P - n n^T)/|w|
    where ``curvature_axes [V, 3]`` (0/1) spans the directions in which the feature is a point."""
    rho = torch.linalg.vector_norm(w, dim=-1)
    safe = torch.clamp(rho, min=torch.finfo(w.dtype).tiny)
    fallback = torch.zeros_like(w)
    fallback[:, 0] = 1.0
    n = torch.where((rho > 0)[:, None], w / safe[:, None], fallback)
    hessian = (torch.diag_embed(curvature_axes) - n[:, :, None] * n[:, None, :]) / safe[:, None, None]
    return rho, n, hessian


def _sphere(q: torch.Tensor, size):
    rho, n, hessian = _point_distance(q, torch.ones_like(q))
    return rho - size[0], n, hessian


def _capsule(q: torch.Tensor, size):
    radius, half = size
    axial = torch.clamp(q[:, 0], -half, half)
    w = q.clone()
    w[:, 0] = q[:, 0] - axial
    axes = torch.ones_like(q)
    axes[:, 0] = (q[:, 0].abs() > half).to(q.dtype)  # beyond an end: a point; along the side: a line
    rho, n, hessian = _point_distance(w, axes)
    return rho - radius, n, hessian


def _box(q: torch.Tensor, half: torch.Tensor):
    sign = torch.where(q >= 0, 1.0, -1.0).to(q.dtype)
    excess = q.abs() - half  # [V, 3]
    outside = (excess > 0).any(dim=1)
    w = sign * torch.clamp(excess, min=0.0)
    rho, n_out, h_out = _point_distance(w, (excess > 0).to(q.dtype))
    # inside: the nearest face (the largest excess, the first such axis), flat
    axis = torch.argmax(excess, dim=1)
    d_in = excess.gather(1, axis[:, None])[:, 0]
    n_in = torch.nn.functional.one_hot(axis, 3).to(q.dtype) * sign
    d = torch.where(outside, rho, d_in)
    n = torch.where(outside[:, None], n_out, n_in)
    hessian = torch.where(outside[:, None, None], h_out, torch.zeros_like(h_out))
    return d, n, hessian


def _mesh(q: torch.Tensor, grid: SignedDistanceGrid):
    return grid.sample(q)


_DISTANCES = {"sphere": _sphere, "capsule": _capsule, "box": _box, "mesh": _mesh}


class ToolSet:
    """Tools stacked for evaluation on one device: their origins ``origins [T, 3]`` and velocities
    ``velocities [T, 3]`` (buffers written in place by :meth:`set_time`, so captured launches read
    the current poses), axes ``rotations [T, 3, 3]``, stiffness and thickness. The same interface
    as ``contact.Planes`` (``forces``, ``dforces``, ``linearize``, ``energy``,
    ``friction_damping``) plus :meth:`reactions`."""

    def __init__(self, tools: Sequence[Tool], dtype, device):
        for i, tool in enumerate(tools):
            if not isinstance(tool, Tool):
                raise SceneError(f"tools[{i}] is a {type(tool).__name__}, not a tm.Tool (tm.Sphere, tm.Capsule, "
                                 f"tm.Box)")
        self.tools = list(tools)
        self.origins = torch.tensor([list(t.origin(0.0)) for t in tools], dtype=dtype, device=device).reshape(-1, 3)
        self.rotations = torch.tensor([list(map(list, t.rotation)) for t in tools], dtype=dtype,
                                      device=device).reshape(-1, 3, 3)
        # the shapes' sizes as the distances take them (a box's half extents as a tensor: made here,
        # not at each evaluation, which a captured step replays)
        self.sizes = [torch.tensor(t.size, dtype=dtype, device=device) if t.shape == "box"
                      else t.grid.to(dtype=dtype, device=device) if t.shape == "mesh" else t.size for t in tools]
        #: penalty stiffness per tool ``[T]`` (a buffer: written in place for a rollout's tool_stiffness,
        #: which captured steps then read)
        self.stiffness = torch.tensor([t.stiffness for t in tools], dtype=dtype, device=device)
        self.thickness = [t.thickness for t in tools]
        self.velocities = torch.zeros_like(self.origins)
        #: whether any tool has friction
        self.has_friction = any(t.friction > 0 for t in tools)
        self.time, self.dt = 0.0, None
        #: tool index -> the origin ``(x, y, z)`` it is held at in place of its path (:meth:`hold`)
        self.held = {}
        self._written = self.origins.cpu()  # the origins last written, on the host

    def __len__(self):
        return len(self.tools)

    @property
    def moves(self) -> bool:
        """Whether any tool moves (then its pose changes between steps): a path, or a tool held
        where a caller puts it (:meth:`hold`)."""
        return bool(self.held) or any(t.moves for t in self.tools)

    def hold(self, index: int, position) -> None:
        """Hold tool ``index`` at the origin ``position`` ``[3]`` from the next step on, in place of
        its path (a tool driven live: a viewer's gizmo, a haptic device); its velocity over that
        step is its move from where it was over the step's length. Raises ``SceneError`` naming a
        bad index or position (nothing changes)."""
        if isinstance(index, bool) or not isinstance(index, int) or not 0 <= index < len(self.tools):
            raise SceneError(f"tool index must be an integer in [0, {len(self.tools)}), got {index!r}")
        self.held[index] = _vector(position, "tool position")
        self.time = None  # the next set_time writes the new origin

    def origin_at(self, index: int, t: float) -> Tuple[float, float, float]:
        """Tool ``index``'s origin at time ``t``: where it is held, else its path's."""
        held = self.held.get(index)
        return held if held is not None else self.tools[index].origin(t)

    def set_time(self, t: float, dt: Optional[float] = None) -> None:
        """The tools' origins at time ``t``, written into :attr:`origins` in place, and with the
        length ``dt`` of the step ending at t, their velocities over it, (o(t) - o(t - dt)) / dt,
        into :attr:`velocities` (without dt, zero). A held tool is where it is held, its
        velocity its move from the origin written before over dt."""
        if t == self.time and dt == self.dt:
            return
        origins = torch.tensor([list(self.origin_at(i, t)) for i in range(len(self.tools))],
                               dtype=self.origins.dtype)
        velocities = torch.zeros_like(origins)
        if dt:
            before = torch.tensor([list(self.tools[i].origin(t - dt)) if i not in self.held else
                                   self._written[i].tolist() for i in range(len(self.tools))], dtype=self.origins.dtype)
            velocities = (origins - before) / dt
        self.origins.copy_(origins.reshape(-1, 3), non_blocking=False)
        self.velocities.copy_(velocities.reshape(-1, 3), non_blocking=False)
        self._written = origins.reshape(-1, 3)
        self.time, self.dt = t, dt

    def to(self, dtype=None, device=None) -> "ToolSet":
        """These tools with their tensors in ``dtype`` on ``device`` (a copy; None keeps each)."""
        other = ToolSet.__new__(ToolSet)
        other.tools, other.thickness, other.held = self.tools, self.thickness, dict(self.held)
        other.stiffness = self.stiffness.to(dtype=dtype, device=device).clone()
        other.time, other.dt, other.has_friction = self.time, self.dt, self.has_friction
        other.velocities = self.velocities.to(dtype=dtype, device=device).clone()
        other.sizes = [s.to(dtype=dtype, device=device) if isinstance(s, (torch.Tensor, SignedDistanceGrid)) else s
                       for s in self.sizes]
        other.origins = self.origins.to(dtype=dtype, device=device).clone()
        other._written = self._written.clone()
        other.rotations = self.rotations.to(dtype=dtype, device=device)
        return other

    def replaced(self, origins: Optional[torch.Tensor] = None,
                 stiffness: Optional[torch.Tensor] = None) -> "ToolSet":
        """These tools with ``origins [T, 3]`` / ``stiffness [T]`` in place of theirs (None keeps
        them; the other tensors shared): the tools as functions of those values, for autograd."""
        return with_values(self, origins=origins, stiffness=stiffness)

    def gaps(self, x: torch.Tensor):
        """Per tool: the gap ``g = d - thickness [V]``, the unit normal ``n [V, 3]`` and the
        distance's Hessian ``H [V, 3, 3]``, in world coordinates, at positions ``x [V, 3]``."""
        out = []
        for i, tool in enumerate(self.tools):
            rotation = self.rotations[i]
            q = (x - self.origins[i]) @ rotation  # local coordinates: R^T (x - o), row by row
            d, n, hessian = _DISTANCES[tool.shape](q, self.sizes[i])
            n = n @ rotation.T
            hessian = rotation @ hessian @ rotation.T
            out.append((d - tool.thickness, n, hessian))
        return out

    def linearize(self, x: torch.Tensor):
        """Forces ``[V, 3]`` and node stiffness -(df/dx) ``[V, 3, 3]`` at ``x [V, 3]`` (one
        evaluation of the distances)."""
        forces = torch.zeros_like(x)
        stiffness = x.new_zeros(*x.shape, 3)
        for tool, k, (g, n, hessian) in zip(self.tools, self.stiffness, self.gaps(x)):
            depth = torch.clamp(g, max=0.0)  # g where in contact, else 0
            forces = forces - (k * depth)[:, None] * n
            active = (g < 0).to(x.dtype)
            stiffness = stiffness + (k * active)[:, None, None] * (n[:, :, None] * n[:, None, :])
            if tool.tangent == "exact":
                stiffness = stiffness + (k * depth)[:, None, None] * hessian
        return forces, stiffness

    def forces(self, x: torch.Tensor) -> torch.Tensor:
        """Penalty forces ``[V, 3]`` at positions ``x [V, 3]``."""
        return self.linearize(x)[0]

    def node_stiffness(self, x: torch.Tensor) -> torch.Tensor:
        """-(df/dx) per node ``[V, 3, 3]``."""
        return self.linearize(x)[1]

    def dforces(self, x: torch.Tensor, dx: torch.Tensor) -> torch.Tensor:
        """(df/dx) dx ``[V, 3]``."""
        return -(self.node_stiffness(x) * dx[:, None, :]).sum(-1)

    def energy(self, x: torch.Tensor) -> torch.Tensor:
        """The penalty energy (0-dim) at ``x [V, 3]``: sum over tools and nodes of k/2 min(g, 0)^2."""
        total = x.new_zeros(())
        for k, (g, _, _) in zip(self.stiffness, self.gaps(x)):
            total = total + 0.5 * k * (torch.clamp(g, max=0.0) ** 2).sum()
        return total

    def penetration(self, x: torch.Tensor) -> torch.Tensor:
        """The deepest penetration of each node into any tool ``[V]``: max(0, -g) (0 away from them)."""
        return self.contact_state(x)[0]

    def reactions(self, x: torch.Tensor, v: Optional[torch.Tensor] = None):
        """The force ``[T, 3]`` the nodes at ``x [V, 3]`` (moving at ``v [V, 3]``: with friction)
        put on each tool (minus the sum of the tool's forces on them) and its torque ``[T, 3]``
        about the tool's origin."""
        return self.contact_state(x, v)[1:]

    def _friction(self, i: int, g: torch.Tensor, n: torch.Tensor, v: torch.Tensor):
        """Tool i's friction damping on the nodes: c ``[V]`` and P_t ``[V, 3, 3]`` at gaps ``g``,
        normals ``n`` and node velocities ``v [V, 3]`` (c = 0 away from it)."""
        tool = self.tools[i]
        n = n / torch.clamp(torch.linalg.vector_norm(n, dim=-1, keepdim=True), min=torch.finfo(n.dtype).tiny)
        slip = tangential_part(v - self.velocities[i], n)
        c = coulomb_damping(tool.friction, self.stiffness[i] * torch.clamp(-g, min=0.0),
                            torch.linalg.vector_norm(slip, dim=-1), tool.friction_velocity)
        return c, tangential_projector(n)

    def friction_damping(self, x: torch.Tensor, v: torch.Tensor) -> NodeDamping:
        """The tools' friction over a step from positions ``x [V, 3]`` and velocities ``v [V, 3]``
        (``contact.NodeDamping``: C = sum c P_t, drive = sum c P_t v_tool, each tool's c =
        mu k max(0, -g) / max(|P_t (v - v_tool)|, eps_v))."""
        matrix = x.new_zeros(*x.shape, 3)
        drive = torch.zeros_like(x)
        for i, (g, n, _) in enumerate(self.gaps(x)):
            if self.tools[i].friction > 0:
                c, projector = self._friction(i, g, n, v)
                damping = c[:, None, None] * projector
                matrix = matrix + damping
                drive = drive + (damping * self.velocities[i]).sum(-1)
        return NodeDamping(matrix, drive)

    def contact_state(self, x: torch.Tensor, v: Optional[torch.Tensor] = None):
        """:meth:`penetration` ``[V]`` and :meth:`reactions` (``[T, 3]`` twice) at ``x [V, 3]``
        from one evaluation of the distances (what a step's report needs); with node velocities
        ``v [V, 3]``, the reactions include the friction at (x, v)."""
        depth = x.new_zeros(x.shape[0])
        force, torque = [], []
        for i, (k, (g, n, _)) in enumerate(zip(self.stiffness, self.gaps(x))):
            depth = torch.maximum(depth, torch.clamp(-g, min=0.0))
            on_nodes = -(k * torch.clamp(g, max=0.0))[:, None] * n  # [V, 3]
            if v is not None and self.tools[i].friction > 0:
                c, projector = self._friction(i, g, n, v)
                on_nodes = on_nodes - c[:, None] * (projector * (v - self.velocities[i])[:, None, :]).sum(-1)
            force.append(-on_nodes.sum(0))
            torque.append(-torch.linalg.cross(x - self.origins[i], on_nodes).sum(0))
        if not force:
            return depth, x.new_zeros(0, 3), x.new_zeros(0, 3)
        return depth, torch.stack(force), torch.stack(torque)
