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

A rank's part is a one-process system (``solver.implicit_euler.DynamicsSystem`` over the part's
``TensorMass``): its right-hand side and CG product are the one-process ops (the fused node-graph
kernels where the extension serves the device, their references elsewhere), their ghost rows
ignored. The CG's scalars stay on the device: each dot is a local sum over the owned rows and one
all-reduce (on the stream under NCCL), and the host reads the residual only every
``check_every`` iterations, so an iteration costs the one-process product plus a halo exchange
and two small all-reduces, with no host wait.
"""
from __future__ import annotations

import dataclasses
from typing import List, Optional, Sequence

import torch

from ..errors import SceneError
from ..mesh.meshes import TetMesh, TriMesh
from ..mesh.topology import unique_edges
from ..ops.segments import Segments
from ..physics.contact import Planes
from ..physics.tensor_mass import TensorMass
from ..solver.implicit_euler import DynamicsSystem
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
        check_every: CG iterations between the host's reads of the residual (the iterations in
            between run without a host synchronisation; those past convergence change nothing).
    """

    def __init__(self, body, *, dt: float = 0.01, gravity=(0.0, 0.0, -9.81), rayleigh_mass: float = 0.0,
                 rayleigh_stiffness: float = 0.0, planes: Sequence = (), cg_tol: float = 1e-6,
                 cg_max_iter: Optional[int] = None, device=None, dtype=None,
                 partition: Optional[torch.Tensor] = None, check_every: int = 16,
                 cuda_graphs: bool = True):
        import torch.distributed as dist

        if body.motion is not None:
            raise SceneError("a partitioned body takes fixed nodes, not prescribed ones")
        if int(check_every) < 1:
            raise SceneError(f"check_every must be a positive number of CG iterations, got {check_every}")
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
            held = torch.zeros(num_nodes, dtype=torch.bool)  # (a mask, not a sort: linear in the mesh)
            held[elements[ids].flatten()] = True
            held_nodes.append(torch.nonzero(held).flatten())
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
        mass = self.model.lumped_mass()
        fixed = body.fixed.cpu()[self.local].to(self.device)
        self.free = (~fixed).to(self.dtype)[:, None]
        self.gravity = torch.as_tensor(gravity, dtype=self.dtype, device=self.device)
        self.planes = Planes(list(planes), self.dtype, self.device) if planes else None
        # the one-process integrator's view of the part: its fused system product (node graph,
        # contact stiffness, fixed-node projection) and right-hand side serve the owned rows
        self.system = DynamicsSystem(self.model, mass, mass[:, None] * self.gravity,
                                     Segments.single(self.local.numel(), self.device), fixed, self.planes,
                                     keep_mask=True)
        self.owned_weight = torch.zeros(self.local.numel(), dtype=torch.float64, device=self.device)
        self.owned_weight[self.owned_rows] = 1.0
        self.dt = float(dt)
        self.rayleigh_mass, self.rayleigh_stiffness = float(rayleigh_mass), float(rayleigh_stiffness)
        free_dofs = self._sum(torch.tensor(float(3 * int((~body.fixed.cpu()[self.owned]).sum())),
                                           dtype=torch.float64))
        self.cg_tol = float(cg_tol)
        self.cg_max_iter = int(cg_max_iter) if cg_max_iter is not None else max(100, 10 * int(free_dofs))
        self.check_every = int(check_every)
        self.cuda_graphs = bool(cuda_graphs)
        self._cg_state = None  # the CG's buffers, kept across steps (a CUDA graph replays over them)
        self._graphs = {}  # (matvec, iterations) -> captured iterations (solver.capture.run_captured)
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
        matvec = self.system.system_matvec(c_m, c_k)
        # the owned rows of rhs are complete (every element of an owned node is held here); the
        # ghost rows are not, and no owned row reads them
        rhs = matvec.load_step(x, v, h, r_m, h + r_k) * self.free
        dv = self._cg(matvec, rhs)
        self.v = v + dv
        self.x = x + h * self.v
        self.time += h
        self.steps_done += 1

    def _owned_dot(self, per_node: torch.Tensor) -> torch.Tensor:
        """The all-reduced sum of a per-node quantity ``[L]`` over the owned rows (float64 ``[1]``
        on this rank's device; no host synchronisation under NCCL)."""
        import torch.distributed as dist

        total = torch.dot(per_node.to(torch.float64), self.owned_weight).reshape(1)
        total = total.to(group_device(self.device))
        dist.all_reduce(total)
        return total.to(self.device)

    def _cg(self, matvec, rhs: torch.Tensor) -> torch.Tensor:
        """Classic CG on the owned rows, its scalars kept on the device: ||r|| <= tol ||rhs|| over
        every rank, the same rule and iterates as one process's CG. The host reads the scalars once
        every ``check_every`` iterations; the iterations in between past convergence change
        nothing (their step length is 0). A solve that does not converge within the cap, or that
        breaks down, raises on every rank alike (the scalars are the same everywhere). Returns
        the solution ``[L, 3]``, a buffer overwritten by the next solve."""
        from ..errors import SolverError
        from ..solver.capture import run_captured

        s = self._cg_state
        if s is None or s["x"].shape != rhs.shape or s["x"].dtype != rhs.dtype:
            s = self._cg_state = dict(x=torch.empty_like(rhs), r=torch.empty_like(rhs), p=torch.empty_like(rhs),
                                      zero=torch.zeros((), dtype=torch.float64, device=self.device),
                                      **{k: torch.zeros(1, dtype=torch.float64, device=self.device)
                                         for k in ("rr", "threshold", "count", "broken")})
            self._graphs = {}
        s["x"].zero_()
        s["r"].copy_(rhs)
        s["p"].copy_(rhs)
        s["rr"].copy_(self._owned_dot((rhs * rhs).sum(-1)))
        torch.mul(s["rr"], max(self.cg_tol, torch.finfo(rhs.dtype).eps) ** 2, out=s["threshold"])
        s["count"].zero_()
        s["broken"].zero_()
        while True:
            left, iterations, failed = torch.cat([s["rr"] - s["threshold"], s["count"], s["broken"]]).tolist()
            if failed:
                raise SolverError("partitioned CG broke down (the system is not positive definite)", ["breakdown"],
                                  None)
            if not left > 0:
                break
            if iterations >= self.cg_max_iter:
                relative = (float(s["rr"]) / max(float(s["threshold"]), 1e-300)) ** 0.5 * self.cg_tol
                raise SolverError(f"partitioned CG did not converge: relative residual {relative:.2e} after "
                                  f"{int(iterations)} iterations", ["not converged"], None)
            block = min(self.check_every, self.cg_max_iter - int(iterations))

            def work(block=block):
                self._iterations(matvec, s, block)

            if self.cuda_graphs and self.device.type == "cuda":
                run_captured(self._graphs, (id(matvec), block), work)
            else:
                work()
        self.last_iterations = int(iterations)
        return s["x"]

    def _iterations(self, matvec, s: dict, count: int) -> None:
        """``count`` CG iterations on the buffers ``s`` in place (the same storage each time: a
        CUDA graph can replay them); an iteration with the residual at the threshold, or past the
        cap, changes nothing."""
        x, r, p, rr, zero = s["x"], s["r"], s["p"], s["rr"], s["zero"]
        for _ in range(count):
            self._exchange(p)
            ap, p_ap = matvec(p)
            curvature = self._owned_dot(p_ap)
            active = (rr > s["threshold"]) & (s["count"] < self.cg_max_iter)
            s["broken"].logical_or_(active & ~(curvature > 0))
            step = torch.where(active, rr / curvature, zero).to(x.dtype)
            x.addcmul_(p, step)
            r.addcmul_(ap, step, value=-1.0)
            rr_new = torch.where(active, self._owned_dot((r * r).sum(-1)), rr)
            p.mul_(torch.where(active, rr_new / rr, zero).to(x.dtype)).add_(r)
            rr.copy_(rr_new)
            s["count"].add_(active.double())

    def close(self) -> None:
        """Free the captured CUDA graphs and the CG's buffers (the simulator can step again: they
        are made anew). Call it, or drop the simulator, before ``destroy_process_group``: NCCL's
        teardown waits on graphs that captured its exchanges, so a live graph hangs it."""
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        self._graphs = {}
        self._cg_state = None

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
