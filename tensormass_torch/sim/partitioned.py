"""One body's mesh over several processes (``torch.distributed``): the implicit step of a mesh too
large for one device, its CG across the ranks.

The nodes are partitioned into connected parts, one a rank (pymetis: METIS's k-way partition of
the node graph, a well-kept library; computed on rank 0 and broadcast). A rank *owns* its part's
nodes and holds every element that touches one of them, so it also holds the *ghost* nodes of
those elements (owned by neighbours). The elements and lumped masses of an owned node are then
all on its rank: its forces, force differentials, mass and right-hand side are complete there,
each as one process computes it (the elements in another order: to rounding).

A step (backward Euler, one linearisation, Rayleigh damping, fixed nodes, planes) on the owned
rows, the ghosts brought up to date by a *halo exchange* (each rank sends the owned values its
neighbours hold as ghosts: point-to-point, the lists found once from the partition) before each
use of the positions, velocities and CG direction:

    rhs = h (f + (h + r_K) K v - r_M M v),   (c_M M - c_K K) dv = rhs   (CG, dots all-reduced)
    v' = v + dv,   x' = x + h v'

with the stopping rule of the one-process CG (||r|| <= tol ||rhs|| over the whole mesh). So the
step equals one process's to the CG's tolerance and rounding (tested: 1e-12 in float64, hooke,
stvk and corotational, fixed nodes and a plane).

This is the pure-torch composed path (the element ops through the model's ``forward`` and
``dforce``, the compiled ones where the extension serves the device): correct on every device
and backend; the fused node-graph kernels of one process are not used here.
"""
from __future__ import annotations

import dataclasses
from typing import List, Optional, Sequence

import torch

from ..errors import SceneError
from ..mesh.meshes import TetMesh, TriMesh
from ..mesh.topology import unique_edges
from ..physics.contact import Planes
from ..physics.tensor_mass import TensorMass
from .distributed import collectively, group_device


def partition_nodes(elements: torch.Tensor, num_nodes: int, parts: int) -> torch.Tensor:
    """A partition of the mesh's nodes into ``parts`` connected parts of about equal size ``[V]``
    (int64 part per node), by METIS's k-way partition of the node graph (pymetis)."""
    if parts == 1:
        return torch.zeros(num_nodes, dtype=torch.int64)
    try:
        import pymetis
    except ImportError as exc:
        raise SceneError(f"partitioning a mesh needs pymetis, which is not installed ({exc}): pip install "
                         f"pymetis") from exc
    edges, _, _ = unique_edges(elements.cpu().long(), num_nodes)
    both = torch.cat([edges, edges.flip(1)])
    order = torch.argsort(both[:, 0] * num_nodes + both[:, 1])
    both = both[order]
    xadj = torch.zeros(num_nodes + 1, dtype=torch.int64)
    xadj[1:] = torch.cumsum(torch.bincount(both[:, 0], minlength=num_nodes), 0)
    adjacency = pymetis.CSRAdjacency(xadj.numpy(), both[:, 1].numpy()) if hasattr(pymetis, "CSRAdjacency") else None
    _, membership = (pymetis.part_graph(parts, adjacency=adjacency) if adjacency is not None
                     else pymetis.part_graph(parts, xadj=xadj.numpy(), adjncy=both[:, 1].numpy()))
    return torch.as_tensor(membership, dtype=torch.int64)


def _material_of(material, element_ids: torch.Tensor):
    """The material of the elements ``element_ids`` (per-element parameters sliced)."""
    changes = {}
    for name in ("young", "poisson", "density", "thickness"):
        value = getattr(material, name)
        if isinstance(value, torch.Tensor) and value.dim() == 1:
            changes[name] = value[element_ids.to(value.device)]
    return dataclasses.replace(material, **changes) if changes else material


class PartitionedSimulator:
    """One body stepped by every rank of the default process group together (module docstring).

    Args:
        body: the ``tm.Body`` (the same on every rank; no prescribed motion).
        dt, gravity, rayleigh_mass, rayleigh_stiffness, planes, cg_tol, cg_max_iter: as
            ``tm.Simulator``'s (``cg_max_iter`` None: 10 x the free degrees of freedom).
        device, dtype: where and in what precision this rank steps.
        partition: the part of each node ``[V]`` (default: :func:`partition_nodes`).
    """

    def __init__(self, body, *, dt: float = 0.01, gravity=(0.0, 0.0, -9.81), rayleigh_mass: float = 0.0,
                 rayleigh_stiffness: float = 0.0, planes: Sequence = (), cg_tol: float = 1e-6,
                 cg_max_iter: Optional[int] = None, device=None, dtype=None,
                 partition: Optional[torch.Tensor] = None):
        import torch.distributed as dist

        if body.motion is not None:
            raise SceneError("a partitioned body takes fixed nodes, not prescribed ones")
        self.rank, self.world = dist.get_rank(), dist.get_world_size()
        mesh = body.mesh
        self.device = torch.device(device) if device is not None else mesh.vertices.device
        self.dtype = dtype if dtype is not None else mesh.vertices.dtype
        num_nodes = mesh.num_vertices
        elements = mesh.elements.cpu().long()
        if partition is None:
            shared = [partition_nodes(elements, num_nodes, self.world) if self.rank == 0 else None]
            dist.broadcast_object_list(shared, src=0)
            partition = shared[0]
        partition = torch.as_tensor(partition, dtype=torch.int64).cpu()
        if partition.shape != (num_nodes,) or int(partition.min()) < 0 or int(partition.max()) >= self.world:
            raise SceneError(f"partition must give each of the {num_nodes} nodes a part in [0, {self.world})")
        self.partition = partition
        self.num_nodes = num_nodes
        # every rank's owned nodes and held elements, known everywhere: the exchange lists need no message
        held_nodes = []
        held_elements = []
        for r in range(self.world):
            touches = (partition[elements] == r).any(1)
            ids = torch.nonzero(touches).flatten()
            held_elements.append(ids)
            held_nodes.append(torch.unique(elements[ids]))
        self.owned = torch.nonzero(partition == self.rank).flatten()  # global ids, ascending
        self.local = held_nodes[self.rank]  # owned and ghost nodes, global ids ascending
        position = torch.full((num_nodes,), -1, dtype=torch.int64)
        position[self.local] = torch.arange(self.local.numel())
        # the owned nodes' rows among the local ones, and the halo lists: what each rank q sends
        # this one (its owned nodes this rank holds as ghosts), and back; on this rank's device,
        # where every CG iteration indexes with them
        self.owned_rows = position[self.owned].to(self.device)
        self.receive, self.send = {}, {}
        for q in range(self.world):
            if q == self.rank:
                continue
            from_q = self.local[partition[self.local] == q]
            if from_q.numel():
                self.receive[q] = position[from_q].to(self.device)
            to_q = held_nodes[q][partition[held_nodes[q]] == self.rank]
            if to_q.numel():
                self.send[q] = position[to_q].to(self.device)
        self.body = body
        self.element_ids = held_elements[self.rank]
        local_elements = position[elements[self.element_ids]]
        kind = TetMesh if mesh.kind == "tet" else TriMesh
        rest = mesh.vertices[self.local.to(mesh.vertices.device)].to(device=self.device, dtype=self.dtype)
        local_mesh = kind(rest, local_elements.to(self.device), check=False)
        # (a rank whose part fails to build stops every rank, rather than leaving them waiting)
        self.model = collectively(lambda: TensorMass(local_mesh, _material_of(body.material, self.element_ids)),
                                  "building a part of the mesh")
        self.mass = self.model.lumped_mass()[:, None]
        self.free = (~body.fixed.cpu()[self.local]).to(device=self.device, dtype=self.dtype)[:, None]
        self.gravity = torch.as_tensor(gravity, dtype=self.dtype, device=self.device)
        self.external = self.mass * self.gravity
        self.planes = Planes(list(planes), self.dtype, self.device) if planes else None
        self.dt = float(dt)
        self.rayleigh_mass, self.rayleigh_stiffness = float(rayleigh_mass), float(rayleigh_stiffness)
        free_dofs = self._sum(torch.tensor(float(3 * int((~body.fixed.cpu()[self.owned]).sum())),
                                           dtype=torch.float64))
        self.cg_tol = float(cg_tol)
        self.cg_max_iter = int(cg_max_iter) if cg_max_iter is not None else max(100, 10 * int(free_dofs))
        self.x = rest.clone()
        self.v = torch.zeros_like(rest)
        if body.velocity is not None:
            velocity = torch.as_tensor(body.velocity, dtype=self.dtype).expand(num_nodes, 3)
            self.v = velocity[self.local.to(velocity.device)].to(self.device).clone() * self.free
        self.time = 0.0
        self.steps_done = 0
        self.last_iterations = 0

    # ---------------------------------------------------------------- communication

    def _sum(self, value: torch.Tensor) -> torch.Tensor:
        """The sum over the ranks (all-reduced; float64 0-dim)."""
        import torch.distributed as dist

        total = value.detach().to(device=group_device(self.device), dtype=torch.float64).reshape(1).clone()
        dist.all_reduce(total)
        return total[0]

    def _exchange(self, field: torch.Tensor) -> None:
        """Bring ``field``'s ghost rows ``[L, 3]`` up to date from their owners (in place)."""
        import torch.distributed as dist

        ops, incoming = [], {}
        for q, rows in self.send.items():
            ops.append(dist.P2POp(dist.isend, field[rows].contiguous(), q))
        for q, rows in self.receive.items():
            incoming[q] = torch.empty(rows.numel(), field.shape[1], dtype=field.dtype, device=field.device)
            ops.append(dist.P2POp(dist.irecv, incoming[q], q))
        if ops:
            for request in dist.batch_isend_irecv(ops):
                request.wait()
        for q, rows in self.receive.items():
            field[rows] = incoming[q]

    def _dot(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        rows = self.owned_rows
        return self._sum((a[rows].double() * b[rows].double()).sum())

    # ---------------------------------------------------------------- the step

    def step(self, n: int = 1) -> None:
        for _ in range(int(n)):
            self._step()

    def _step(self) -> None:
        h, r_m, r_k = self.dt, self.rayleigh_mass, self.rayleigh_stiffness
        c_m, c_k = 1.0 + h * r_m, h * (h + r_k)
        x, v = self.x, self.v
        self._exchange(x)
        self._exchange(v)
        forces = self.model(x) + self.external
        stiffness = None
        if self.planes is not None:
            contact, stiffness = self.planes.linearize(x)
            forces = forces + contact

        def tangent(w):
            out = self.model.dforce(x, w)
            if stiffness is not None:
                out = out - (stiffness * w[:, None, :]).sum(-1)
            return out

        rhs = h * (forces + tangent((h + r_k) * v) - r_m * self.mass * v) * self.free

        def product(p):
            self._exchange(p)
            return (c_m * self.mass * p - c_k * tangent(p)) * self.free

        dv = self._cg(product, rhs)
        self.v = v + dv
        self.x = x + h * self.v
        self.time += h
        self.steps_done += 1

    def _cg(self, product, rhs: torch.Tensor) -> torch.Tensor:
        """Classic CG on the owned rows: ||r|| <= tol ||rhs|| over every rank; a solve that does not
        converge within the cap raises (on every rank alike: the scalars are the same everywhere)."""
        from ..errors import SolverError

        x = torch.zeros_like(rhs)
        r = rhs.clone()
        p = r.clone()
        rr = self._dot(r, r)
        threshold = max(self.cg_tol, torch.finfo(rhs.dtype).eps) ** 2 * float(rr)
        iterations = 0
        while float(rr) > threshold:
            if iterations >= self.cg_max_iter:
                raise SolverError(f"partitioned CG did not converge: relative residual "
                                  f"{(float(rr) / max(threshold, 1e-300)) ** 0.5 * self.cg_tol:.2e} after "
                                  f"{iterations} iterations", ["not converged"], None)
            ap = product(p)
            curvature = self._dot(p, ap)
            if not float(curvature) > 0:
                raise SolverError("partitioned CG broke down (the system is not positive definite)", ["breakdown"],
                                  None)
            alpha = rr / curvature
            x = x + alpha.to(x.dtype) * p
            r = r - alpha.to(r.dtype) * ap
            rr_new = self._dot(r, r)
            p = r + (rr_new / rr).to(r.dtype) * p
            rr = rr_new
            iterations += 1
        self.last_iterations = iterations
        return x

    # ---------------------------------------------------------------- results

    def snapshot(self) -> "PartitionedFrame":
        """The whole body's state now, gathered on every rank (a collective: every rank calls
        it), in the shape ``sim.output.FrameWriter`` writes a simulator's."""
        return PartitionedFrame(self.body, self.time, self.positions(), self.velocities())

    def positions(self) -> torch.Tensor:
        """Every node's position ``[V, 3]`` (gathered from the owners; on every rank)."""
        return self._gather(self.x)

    def velocities(self) -> torch.Tensor:
        return self._gather(self.v)

    def _gather(self, field: torch.Tensor) -> torch.Tensor:
        import torch.distributed as dist

        parts: List[Optional[torch.Tensor]] = [None] * self.world
        dist.all_gather_object(parts, field[self.owned_rows].detach().cpu())
        full = torch.empty(self.num_nodes, 3, dtype=self.dtype)
        for r, values in enumerate(parts):
            full[torch.nonzero(self.partition == r).flatten()] = values
        return full


@dataclasses.dataclass
class PartitionedFrame:
    """A partitioned body's gathered state (:meth:`PartitionedSimulator.snapshot`): one body,
    read as a one-body simulator's by ``FrameWriter`` (``positions(0)`` ``[V, 3]``, ...)."""

    body: object
    time: float
    x: torch.Tensor
    v: torch.Tensor

    @property
    def bodies(self) -> list:
        return [self.body]

    def positions(self, i: int = 0) -> torch.Tensor:
        return self.x

    def velocities(self, i: int = 0) -> torch.Tensor:
        return self.v

    def displacements(self, i: int = 0) -> torch.Tensor:
        return self.x - self.body.mesh.vertices.to(self.x)

    def mesh(self, i: int = 0):
        return self.body.mesh


__all__ = ["PartitionedFrame", "PartitionedSimulator", "partition_nodes"]
