"""Diagnostics of a simulation's state: contact, interpenetration between bodies, inverted
elements and volume change per object, and an inventory of the tensors a scene allocates.

Inversion is measured by each element's signed measure at the current positions against its
rest measure (the ratio is 1 at rest, <= 0 once inverted):

    tetrahedra     signed volume det[x1 - x0, x2 - x0, x3 - x0] / 6
    triangles      signed area 0.5 (x1 - x0) x (x2 - x0) . R n_rest, with n_rest the element's
                   unit rest normal and R the object's best-fit rotation (rest -> current, Kabsch):
                   a membrane element whose normal has flipped against its rest normal, carried
                   by the object's overall rotation, has a negative area. A triangle in 3-D has
                   no orientation of its own (a flipped one is a rotated one), so without R a
                   sheet turned over as a whole would count as inverted; with R only elements
                   folded against the object's motion count. For 2-D triangles (placed in
                   z = 0, R a rotation about z) it is the signed planar area.

Per object: the number of inverted elements, the volume (area) ratio sum(current) / sum(rest)
and the smallest element ratio. Everything stays on the device until a caller asks for element
ids (``InversionReport.worst``) or a message.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Dict, List, Optional, Sequence

import torch

from ..mesh.distance import signed_distances_to_surfaces, surface_signed_distances
from ..mesh.topology import expand_ranges


@dataclass
class ContactReport:
    """Contact at the end of a step (device tensors: nothing is read back until asked).

    Attributes:
        tool_force: the force the bodies put on each tool ``[T, 3]`` (minus the sum of the
            tool's penalty and friction forces on the nodes: what a haptic device renders).
        tool_torque: its torque about each tool's origin ``[T, 3]``.
        contacts: per body, the nodes inside a tool's or a plane's contact distance ``[B]``.
        max_penetration: per body, the deepest of those ``[B]`` (0 with no contact).
        body_contacts: per body, its surface vertices in contact with another body's surface
            (or its own, with self-contact) ``[B]`` (zeros without body contact).
        body_penetration: per body, the deepest interpenetration of its surface into another's
            ``[B]``: max(0, -signed distance), the thickness layer's compression not counted.
    """

    tool_force: torch.Tensor
    tool_torque: torch.Tensor
    contacts: torch.Tensor
    max_penetration: torch.Tensor
    body_contacts: Optional[torch.Tensor] = None
    body_penetration: Optional[torch.Tensor] = None


def contact_report(sim, x: Optional[torch.Tensor] = None) -> ContactReport:
    """The :class:`ContactReport` of simulator ``sim`` at positions ``x [V, 3]`` (default: its
    state), with its tools where they are now."""
    x = sim.x if x is None else x
    depth = x.new_zeros(x.shape[0])
    force = torque = x.new_zeros(0, 3)
    if sim.tools is not None:
        depth, force, torque = sim.tools.contact_state(x, sim.v if x is sim.x else None)
    if sim.planes is not None:
        depth = torch.maximum(depth, sim.planes.penetration(x).amax(dim=1))
    lengths = sim.segments.lengths
    contacts = torch.segment_reduce((depth > 0).to(x.dtype), "sum", lengths=lengths).to(torch.int64)
    deepest = torch.segment_reduce(depth, "max", lengths=lengths, unsafe=True, initial=0.0)
    body = getattr(sim, "body_contact", None)
    if body is None:
        body_counts, body_depth = torch.zeros_like(contacts), torch.zeros_like(deepest)
    else:
        # at the simulator's state, the pairs its next step linearises with (found once for both)
        pairs = body.detect_at_state(x, sim.v, sim.options.dt) if x is sim.x else body.detect(x)
        body_counts, body_depth = pairs.penetration(sim.num_bodies, sim.segments.node_object)
    return ContactReport(force, torque, contacts, deepest, body_counts, body_depth)


def interpenetration(sim, x: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Per body ``[B]``, how deep its surface is inside the other bodies at positions ``x [V, 3]``
    (default: the simulator's state): the largest distance from one of its surface vertices
    that lies inside another tetrahedral body to that body's surface (0 with none; a body's own
    folds are not counted).

    Exact and independent of the contact's search: every vertex inside another body's bounding
    box is measured against that body's whole surface (nearest triangle, the side by
    angle-weighted pseudonormals, ``mesh.distance.signed_distances_to_surfaces``), so a body that
    went through another, further than any contact pair reaches, shows here and not in
    ``ContactReport``. All bodies at once: the bodies' surfaces in one ``boundary_faces``
    (``Simulator.surfaces``), the (vertex, body) candidates from the pairs of bodies whose boxes
    meet, one batched distance query (for checks, not for every step)."""
    x = sim.x if x is None else x
    depth = x.new_zeros(sim.num_bodies)
    triangles, triangle_body = sim.surfaces()
    triangles, triangle_body = triangles.to(x.device), triangle_body.to(x.device)
    if triangles.shape[0] == 0 or int(triangle_body.unique().numel()) < 2:
        return depth
    node_body = sim.segments.node_object.to(x.device)
    surface = torch.unique(triangles)  # [S] every tet body's surface vertices, body after body
    surface_body = node_body[surface]
    big = torch.finfo(x.dtype).max
    index = surface_body[:, None].expand(-1, 3)
    lower = x.new_full((sim.num_bodies, 3), big).scatter_reduce(0, index, x[surface], "amin")  # [B, 3]
    upper = x.new_full((sim.num_bodies, 3), -big).scatter_reduce(0, index, x[surface], "amax")
    # (container, other) pairs of bodies whose boxes meet (a body without a surface has an empty box)
    overlap = ((lower[:, None] <= upper[None]) & (lower[None] <= upper[:, None])).all(-1)
    overlap.fill_diagonal_(False)
    container, other = torch.nonzero(overlap, as_tuple=True)
    # each pair's candidates: the other body's surface vertices, those inside the container's box
    counts = torch.bincount(surface_body, minlength=sim.num_bodies)
    first = torch.cumsum(counts, 0) - counts
    pair, index = expand_ranges(first[other], counts[other])
    vertex, body = surface[index], container[pair]
    inside_box = ((x[vertex] >= lower[body]) & (x[vertex] <= upper[body])).all(-1)
    vertex, body = vertex[inside_box], body[inside_box]
    if vertex.numel() == 0:
        return depth
    signed = signed_distances_to_surfaces(x[vertex], body, x, triangles, triangle_body)
    return depth.scatter_reduce_(0, node_body[vertex], torch.clamp(-signed, min=0.0), "amax")


def depth_inside(x: torch.Tensor, nodes: torch.Tensor, faces: torch.Tensor, lower: Optional[torch.Tensor] = None,
                 upper: Optional[torch.Tensor] = None):
    """(the ``nodes`` within the box ``lower, upper [3]`` of the closed surface ``faces [F, 3]``
    (default: its vertices' box) at positions ``x [V, 3]``, how deep each is inside the surface
    ``[N]``, 0 outside): the exact signed distance to the whole surface, as
    :func:`interpenetration` measures it."""
    if lower is None or upper is None:
        corners = x[torch.unique(faces)]
        lower, upper = corners.amin(0), corners.amax(0)
    nodes = nodes[((x[nodes] >= lower) & (x[nodes] <= upper)).all(-1)]
    if nodes.numel() == 0:
        return nodes, x.new_zeros(0)
    signed = surface_signed_distances(x[nodes].reshape(-1, 1, 1, 3), x, faces, block=1).reshape(-1)
    return nodes, torch.clamp(-signed, min=0.0)


def signed_measures(x: torch.Tensor, elements: torch.Tensor,
                    rest_normals: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Signed measures ``[N]`` of elements ``[N, n]`` at positions ``x [V, 3]``: volumes of tets
    (n = 4), areas of triangles (n = 3) signed by ``rest_normals [N, 3]`` (unit)."""
    nodes = x[elements]  # [N, n, 3]
    e1, e2 = nodes[:, 1] - nodes[:, 0], nodes[:, 2] - nodes[:, 0]
    normal = torch.linalg.cross(e1, e2)
    if elements.shape[1] == 4:
        return (normal * (nodes[:, 3] - nodes[:, 0])).sum(-1) / 6.0
    return 0.5 * (normal * rest_normals).sum(-1)


@dataclass
class InversionReport:
    """Inversion and volume change of each of B objects at one state.

    Attributes:
        inverted: inverted elements per object ``[B]`` int64 (signed measure <= 0).
        volume_ratio: sum of signed measures / sum of rest measures per object ``[B]`` (areas for
            triangle objects).
        min_ratio: smallest element measure ratio per object ``[B]`` (< 0: inverted).
        element_ratios: per object, the measure ratio of each of its elements ``[N_b]`` (element
            ids are the object's own mesh ids).
    """

    inverted: torch.Tensor
    volume_ratio: torch.Tensor
    min_ratio: torch.Tensor
    element_ratios: List[torch.Tensor]

    def worst(self, k: int = 5) -> List[List[int]]:
        """Per object, the ids of its (up to k) inverted elements, most inverted first."""
        out = []
        for ratios in self.element_ratios:
            bad = torch.nonzero(ratios <= 0).flatten()
            order = torch.argsort(ratios[bad])[:k]
            out.append(bad[order].tolist())
        return out

    def describe(self, names: Optional[Sequence[Optional[str]]] = None, k: int = 5) -> str:
        """One line per object with inverted elements: its count, worst ids and their ratios."""
        lines = []
        worst = self.worst(k)
        for b, count in enumerate(self.inverted.tolist()):
            if count == 0:
                continue
            label = f"object {b}" + (f" ({names[b]})" if names and names[b] else "")
            ratios = self.element_ratios[b]
            ids = ", ".join(f"{i} ({float(ratios[i]):+.3g})" for i in worst[b])
            lines.append(f"{label}: {count} inverted elements, worst {ids}")
        return "; ".join(lines)


def best_rotations(rest: torch.Tensor, x: torch.Tensor, lengths: torch.Tensor) -> torch.Tensor:
    """Per object, the rotation ``[B, 3, 3]`` that best maps its rest points onto its current
    points (least squares about the centroids, Kabsch): ``rest, x [M, 3]`` stacked object by
    object, ``lengths [B]`` points per object."""
    def centred(p):
        means = torch.segment_reduce(p, "sum", lengths=lengths, axis=0) / lengths[:, None].to(p.dtype)
        return p - torch.repeat_interleave(means, lengths, dim=0)

    a, b = centred(rest), centred(x)
    cov = torch.segment_reduce((a[:, :, None] * b[:, None, :]).reshape(-1, 9), "sum", lengths=lengths, axis=0)
    u, _, vh = torch.linalg.svd(cov.reshape(-1, 3, 3))
    v = vh.transpose(1, 2)
    # a proper rotation: flip the weakest axis when the best orthogonal map is a reflection
    sign = torch.sign(torch.linalg.det(v @ u.transpose(1, 2)))
    sign = torch.where(sign == 0, torch.ones_like(sign), sign)
    fix = torch.ones_like(v[:, 0])
    fix[:, 2] = sign
    return (v * fix[:, None, :]) @ u.transpose(1, 2)


class _KindGroup:
    """The objects of one element kind, measured together (one gather, segmented sums)."""

    def __init__(self, rest: torch.Tensor, objects: Sequence[torch.Tensor], ids: List[int],
                 alive: Optional[Sequence[torch.Tensor]] = None):
        self.ids = ids
        # removed elements (Simulator.remove_elements) keep their ids but count for nothing
        self.alive = None if alive is None else torch.cat([alive[b] for b in ids])
        self.index = torch.tensor(ids, device=rest.device)
        self.element_counts = [int(objects[b].shape[0]) for b in ids]
        self.lengths = torch.tensor(self.element_counts, device=rest.device)
        self.elements = torch.cat([objects[b] for b in ids])
        self.normals = None
        if self.elements.shape[1] == 3:
            corners = rest[self.elements]
            normals = torch.linalg.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            self.normals = normals / torch.linalg.vector_norm(normals, dim=1, keepdim=True)
            # each object's nodes (for its best-fit rotation) and each element's object
            nodes = [torch.unique(objects[b]) for b in ids]
            self.nodes = torch.cat(nodes)
            self.node_counts = torch.tensor([n.numel() for n in nodes], device=rest.device)
            self.rest_nodes = rest[self.nodes]
            self.element_object = torch.repeat_interleave(torch.arange(len(ids), device=rest.device), self.lengths)
        self.rest_measures = signed_measures(rest, self.elements, self.normals)
        self.rest_totals = torch.segment_reduce(self._counted(self.rest_measures), "sum", lengths=self.lengths)

    def _counted(self, measures: torch.Tensor) -> torch.Tensor:
        return measures if self.alive is None else torch.where(self.alive, measures, measures.new_zeros(()))

    def measures(self, x: torch.Tensor) -> torch.Tensor:
        """Signed measures ``[N_k]`` at positions ``x [V, 3]`` (0 for removed elements)."""
        if self.normals is None:
            return self._counted(signed_measures(x, self.elements, None))
        rotations = best_rotations(self.rest_nodes, x[self.nodes], self.node_counts)
        normals = (rotations[self.element_object] @ self.normals[:, :, None])[:, :, 0]
        return self._counted(signed_measures(x, self.elements, normals))

    def ratios(self, measures: torch.Tensor) -> torch.Tensor:
        """Measure ratios to the rest ``[N_k]`` (1 for removed elements: never inverted)."""
        ratios = measures / self.rest_measures
        return ratios if self.alive is None else torch.where(self.alive, ratios, ratios.new_ones(()))


class InversionCheck:
    """Inverted-element and volume measurement of packed objects (built once, applied per state).

    Args:
        rest: rest positions of all nodes ``[V, 3]``.
        objects: per object, its elements ``[N_b, n]`` in global node ids (n = 4 or 3; one kind
            per object).
        alive: per object ``[N_b]`` bool, the elements that count (removed ones keep their ids
            in reports but are never inverted and add no volume), or None: all.
    """

    def __init__(self, rest: torch.Tensor, objects: Sequence[torch.Tensor],
                 alive: Optional[Sequence[torch.Tensor]] = None):
        self.num_objects = len(objects)
        self.kinds = []
        for n in (4, 3):
            ids = [b for b, e in enumerate(objects) if e.shape[1] == n]
            if ids:
                self.kinds.append(_KindGroup(rest, objects, ids, alive))

    @classmethod
    def for_simulator(cls, sim) -> "InversionCheck":
        """The check of a ``Simulator``'s bodies (element ids are each body's mesh ids)."""
        objects = [b.mesh.elements.to(sim.device) + sim.ptr[i] for i, b in enumerate(sim.bodies)]
        alive = [sim.alive_elements(i) for i in range(len(sim.bodies))]
        return cls(sim.model.rest, objects, None if all(bool(a.all()) for a in alive) else alive)

    def __call__(self, x: torch.Tensor) -> InversionReport:
        """The report at positions ``x [V, 3]``."""
        like = x.new_zeros(self.num_objects)
        inverted = torch.zeros(self.num_objects, dtype=torch.long, device=x.device)
        volume_ratio, min_ratio = like.clone(), like.clone()
        element_ratios: List[Optional[torch.Tensor]] = [None] * self.num_objects
        for kind in self.kinds:
            measures = kind.measures(x)
            ratios = kind.ratios(measures)
            counts = torch.segment_reduce((ratios <= 0).to(x.dtype), "sum", lengths=kind.lengths)
            inverted.index_copy_(0, kind.index, counts.round().long())
            totals = torch.segment_reduce(measures, "sum", lengths=kind.lengths)
            volume_ratio.index_copy_(0, kind.index, totals / kind.rest_totals)
            min_ratio.index_copy_(0, kind.index, torch.segment_reduce(ratios, "min", lengths=kind.lengths))
            for b, part in zip(kind.ids, torch.split(ratios, kind.element_counts)):
                element_ratios[b] = part
        return InversionReport(inverted, volume_ratio, min_ratio, element_ratios)


def inversion_report(sim, x: Optional[torch.Tensor] = None) -> InversionReport:
    """A one-off :class:`InversionReport` of a ``Simulator`` at ``x [V, 3]`` (default: its state)."""
    return InversionCheck.for_simulator(sim)(sim.x if x is None else x)


# ---------------------------------------------------------------------------------------------
# what a scene allocates
# ---------------------------------------------------------------------------------------------


def allocations(sim) -> Dict[str, int]:
    """Bytes of every tensor a ``Simulator`` holds, by name: ``model.*`` (rest, mass),
    ``group<i>.<kind>.<model>.<form>.*`` (each element group's buffers, gather plan and the
    extension's cached copies: int32 indices, Lame parameters), ``system.*`` (external forces,
    free mask, segments, planes), ``solver.*`` (the CG's vectors and per-object scalars, the
    linearisation buffers of each system matvec, the CUDA step buffers) and ``state.*``
    (positions, velocities, constraint masks).

    Each entry counts its tensor's whole storage; a tensor that shares its storage with one
    listed before (a view, or the same tensor held twice) is not listed again. The solver's tensors appear
    after the first step."""
    out: Dict[str, int] = {}
    seen = set()

    def add(name, t):
        if not isinstance(t, torch.Tensor):
            return
        storage = t.untyped_storage()
        key = (t.device, storage.data_ptr())
        if storage.nbytes() and key in seen:
            return
        seen.add(key)
        out[name] = storage.nbytes()  # what is allocated (a view's whole storage)

    model = sim.model
    add("model.rest", model.rest)
    add("model.mass", model.mass)
    for i, g in enumerate(model.groups):
        prefix = f"group{i}.{g.kind}.{g.model}.{g.form}"
        for name, buf in g.named_buffers():
            add(f"{prefix}.{name}", buf)
        for name in ("index", "force_index", "incidences"):
            add(f"{prefix}.plan.{name}", getattr(g.plan, name, None))
        cached = getattr(g.plan, "_native_indices", None)
        for name, t in zip(("index", "force_index", "incidences"), cached[2] if cached else ()):
            add(f"{prefix}.native.{name}", t)
        cached = g.__dict__.get("_native_lame")
        for name, t in zip(("lam", "mu"), cached[2] if cached else ()):
            add(f"{prefix}.native.{name}", t)
    system = sim.system
    add("system.mass", system.mass)
    add("system.external", system.external)
    add("system.free", system.free)
    add("system.segments.lengths", system.segments.lengths)
    add("system.segments.node_object", system.segments.node_object)
    if system.planes is not None:
        for name in ("normals", "offsets", "stiffness"):
            add(f"system.planes.{name}", getattr(system.planes, name))
    cg = system._cg
    if cg is not None:
        for name, t in vars(cg.state).items():
            add(f"solver.cg.{name}", t)
        add("solver.cg.rhs_sq", cg.rhs_sq)
    for k, matvec in enumerate(system._matvecs.values()):
        add(f"solver.matvec{k}.u", matvec.u)
        for j, s in enumerate(matvec.states or []):
            add(f"solver.matvec{k}.state{j}", s)
        add(f"solver.matvec{k}.node_stiffness", matvec.node_stiffness)
    for k, graphs in enumerate(system._step_graphs.values()):
        for name in ("x", "v", "imposed", "x_new", "v_new", "dv_imposed", "norms", "v_norms"):
            add(f"solver.step_graphs{k}.{name}", getattr(graphs, name, None))
    for k, (_, _, refinement) in enumerate(system._refinements.values()):  # precision="mixed"'s float32 copy
        for name, t in refinement.system32.model.named_buffers():
            add(f"solver.refine{k}.model.{name}", t)
        for name, t in vars(refinement.cg32.state).items():
            add(f"solver.refine{k}.cg.{name}", t)
    for k, (_, _, space) in enumerate(system._solution_spaces.values()):  # warm_start="project"'s basis
        for name in ("basis", "share", "valid"):
            add(f"solver.space{k}.{name}", getattr(space, name))
        for name, t in zip(("basis", "share", "valid", "node_stiffness"), space._kept or ()):
            add(f"solver.space{k}.kept.{name}", t)  # (the copy chained refined steps rewind to)
    for name in ("x", "v", "fixed", "prescribed"):
        add(f"state.{name}", getattr(sim, name))
    return out


def allocation_summary(sim) -> Dict[str, int]:
    """``allocations(sim)`` summed by part: ``model`` (rest, mass, element groups), ``solver``
    (system and solver buffers) and ``state`` (bytes)."""
    parts = {"model": 0, "solver": 0, "state": 0}
    for name, nbytes in allocations(sim).items():
        head = name.split(".", 1)[0]
        part = "model" if head == "model" or head.startswith("group") else "state" if head == "state" else "solver"
        parts[part] += nbytes
    return parts


__all__ = ["InversionCheck", "InversionReport", "allocation_summary", "allocations", "best_rotations", "depth_inside",
           "inversion_report", "signed_measures"]
