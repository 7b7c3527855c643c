"""ElementGroup: the precomputed data of one set of elements with one model and one form.

A model (one mesh, or a packed batch of bodies) holds one group per (element kind, model,
form): a tetrahedral ``stvk`` body and a triangular ``hooke`` body in one batch give two groups
over the same global nodes. A group stores only what its form needs:

    stress form            shape vectors m [N, n, d], measures [N], young/poisson [N],
                           tangent projectors [N, d, d] (membranes in 3-D only);
                           corotational adds the rest element nodes [N, n, 3] (QR frame,
                           membranes) and rest normals [N, 3] (membranes, polar)
    tensor form, hooke     vertex tensors [V, d, d], edges [Ed, 2], edge tensors [Ed, d, d]
    tensor form, stvk      B [N, n, n, d, d], C [N, n, n, n, d], D [N, n, n, n, n]

plus the gather plan of the paper (``index``, ``ForceIndex``, ``N_n``) over its items
(elements, or edges for the hooke tensor form).
"""
from __future__ import annotations

import torch
from torch import nn

from ..errors import CapacityError, MaterialError
from ..mesh import geometry
from ..mesh.topology import GatherPlan, unique_edges
from ..ops import library, node_graph, solve, topology
from ..ops.reference import tensor_form
from .materials import lame

FORMS = ("stress", "tensor")


class ElementGroup(nn.Module):
    """Elements of one kind, model and form.

    Args:
        rest: rest positions of all nodes ``[V, d]``.
        elements: global node ids ``[N, n]`` (n = 4 tetrahedra, 3 triangles), positively oriented.
        young, poisson: per-element parameters ``[N]``.
        model: ``"hooke"`` or ``"stvk"``.
        form: ``"stress"`` or ``"tensor"``.
        measure_scale: per-element factor on the rest measure ``[N]`` (membrane thickness), or None.
        rotation: the corotational rotation method; tangent: ``"exact"`` or ``"definite"`` (stvk).
    """

    def __init__(self, rest, elements, young, poisson, model, form, measure_scale=None, rotation="polar",
                 tangent="exact"):
        super().__init__()
        if form not in FORMS:
            raise ValueError(f"unknown form {form!r}; known forms: {', '.join(FORMS)}")
        if tangent == "definite" and form != "stress":
            raise MaterialError("tangent='definite' has the stress form only; use form='stress' (or 'auto')")
        self.model = model
        self.form = form
        self.tangent = tangent
        self.nodes_per_element = elements.shape[1]
        self.dim = rest.shape[1]
        self.num_nodes = rest.shape[0]
        self.kind = "tet" if self.nodes_per_element == 4 else "tri"
        #: slots added to the plan for cuts in place (:meth:`reserve_slots`)
        self.reserved_slots = 0
        self.membrane = geometry.needs_projector(self.nodes_per_element, self.dim)

        element_rest = geometry.element_nodes(rest, elements)
        m, measure = geometry.shape_vectors(element_rest)
        measure = measure.abs()  # orientation is checked by the mesh; the measure is a size
        if measure_scale is not None:
            measure = measure * measure_scale
        proj = geometry.tangent_projectors(element_rest) if self.membrane else None
        self.register_buffer("elements", elements)
        self.register_buffer("measure", measure)

        if model == "corotational" and form != "stress":
            raise MaterialError("the corotational model has the stress form only")
        self.rotation = rotation if model == "corotational" else None
        if self.rotation == "qr" and self.dim != 3:
            raise MaterialError("the QR rotation frame needs 3-D elements; use rotation='polar'")
        if self.rotation == "qr" or (self.rotation == "polar" and self.membrane):
            self.register_buffer("rest_elements", element_rest)
        if self.rotation == "polar" and self.membrane:
            edges = element_rest[:, 1:3] - element_rest[:, :1]
            normal = torch.linalg.cross(edges[:, 0], edges[:, 1])
            self.register_buffer("rest_normals", normal / torch.linalg.vector_norm(normal, dim=1, keepdim=True))
        if form == "stress":
            self.register_buffer("shape_vectors", m)
            self.register_buffer("young", young)
            self.register_buffer("poisson", poisson)
            self.register_buffer("projector", proj)
            self.plan = GatherPlan.build(elements, self.num_nodes)
            return

        if young.requires_grad or poisson.requires_grad:
            # The tensors are precomputed once; a gradient would silently stop at them.
            raise MaterialError("the tensor form precomputes its tensors, so no gradient reaches material "
                                "parameters that require grad: use form='stress'")
        lam, mu = self.lame(young, poisson)
        if model == "hooke":
            element_k = tensor_form.element_stiffness(m, measure, lam, mu, proj)
            edges, edge_k = tensor_form.assemble_edges(element_k, elements, self.num_nodes)
            self.register_buffer("edges", edges)
            self.register_buffer("edge_k", edge_k)
            self.plan = GatherPlan.build(edges, self.num_nodes)
        else:
            b, c, d = tensor_form.stvk_tensors(m, measure, lam, mu, proj)
            self.register_buffer("tensor_b", b)
            self.register_buffer("tensor_c", c)
            self.register_buffer("tensor_d", d)
            self.plan = GatherPlan.build(elements, self.num_nodes)

    # ---------------------------------------------------------------- topology changes
    def prepare_removals(self, young: torch.Tensor, poisson: torch.Tensor, ids: torch.Tensor) -> None:
        """What :meth:`remove_rows` needs beyond the group's own data, made at the first removal
        only (a scene that never removes an element holds none of it): for the hooke tensor form
        the parameters to form an element's tensors again (``young, poisson [N]``), the edge of
        each local pair of each element (``element_edges [N, P]``) and each edge's incidence list
        (``edge_slots [S, Ed]``: the model ids ``ids [N]`` of its elements, in the order its
        tensor was assembled, -1 past the last), index tensors of the elements' dtype."""
        if self.form == "tensor" and self.model == "hooke":
            self.register_buffer("young", young.contiguous())
            self.register_buffer("poisson", poisson.contiguous())
            _, pairs, element_edges = unique_edges(self.elements.long(), self.num_nodes)  # the edges' own order
            self.register_buffer("element_edges", element_edges.to(self.elements.dtype).contiguous())
            items = ids.to(self.elements.dtype).repeat_interleave(pairs.shape[0])
            self.register_buffer("edge_slots", topology.incidence_table(element_edges.reshape(-1), items,
                                                                        self.edges.shape[0]))

    @torch.no_grad()  # a removal is not differentiable (the tensor form holds no gradient anyway)
    def remove_rows(self, rows: torch.Tensor, rest: torch.Tensor, removed: torch.Tensor,
                    element_row: torch.Tensor) -> None:
        """Remove the elements at ``rows`` (local row ids ``[R]`` of the elements' index dtype,
        unique, in range, alive before, already flagged in the model's ``removed [N_model]``;
        ``element_row [N_model]``: the row of each model id; the caller checks and flags) in
        place. Every buffer keeps its storage and shape and the gather plan stays as built, so
        whatever reads them (the node graphs, captured CUDA graphs, a packed solve) stays valid; a
        removed row stays but contributes exactly nothing:

            stress form     shape vectors and measure 0: F = P, no strain; every force, product and
                            energy term of the element is a product with m or the measure, so 0
            stvk tensor     B, C, D 0 (the forces are polynomials in them)
            hooke tensor    each edge of the rows summed again from the elements left on it, their
                            tensors formed again from ``rest [V, d]`` in the order of assembly (an
                            edge left with no element holds exactly 0); the node graphs cached on
                            the group follow

        The forces are then those of a group built without the rows (exactly, but for the edge
        tensors of the hooke tensor form, formed by other code). A corotational element's
        rotation is still computed from its current nodes: finite unless three of them are exactly
        collinear. Needs :meth:`prepare_removals` first."""
        if self.form == "stress":
            self.shape_vectors.index_fill_(0, rows, 0.0)
            self.measure.index_fill_(0, rows, 0.0)
        elif self.model == "hooke":
            topology.refresh_hooke_edges(rest, self.elements, rows, self.element_edges, self.edge_slots, element_row,
                                         removed, self.measure, self.young, self.poisson, self.edge_k)
            if node_graph.has_cached_graph(self):
                node_graph.edges_changed(self, self.element_edges[rows].reshape(-1))
        else:
            for tensor in (self.tensor_b, self.tensor_c, self.tensor_d):
                tensor.index_fill_(0, rows, 0.0)

    # ---------------------------------------------------------------- cuts (elements re-pointed)
    def reserve_slots(self, extra: int) -> None:
        """Room for ``extra`` (>= 1) more items on each node of the gather plan (its
        ``num_slots``; the gathers read a node's first ``incidences`` slots only): what cuts in
        place need where a node gains items, the hooke tensor form's edges (a node split next to
        it adds an edge). The last slot is kept empty: edges a cut leaves with no element write
        their zero there (the sink slot of node 0). Before any graph of the group is built (the
        node graphs take their slot count from it)."""
        if self.form == "tensor" and self.model == "hooke" and extra > 0:
            self.reserved_slots = int(extra)
            self.plan = GatherPlan(self.plan.index, self.plan.force_index, self.plan.num_slots + int(extra),
                                   self.plan.num_nodes, self.plan.incidences)

    def _node_items(self) -> torch.Tensor:
        """The gather plan's lists ``[N_n, V]``: slot s of node i holds the item ``row * w + a``
        (w: the plan's items' width, n or 2) whose ``force_index`` is s, -1 past the last; made
        at the first cut."""
        if "node_items" not in self._buffers:
            flat = self.plan.index.reshape(-1).long()
            items = torch.arange(flat.numel(), device=flat.device, dtype=self.elements.dtype)
            table = torch.full((self.plan.num_slots, self.num_nodes), -1, dtype=items.dtype, device=flat.device)
            table[self.plan.force_index.reshape(-1).long(), flat] = items
            self.register_buffer("node_items", table)
        return self.node_items

    def _edge_plan(self) -> bool:
        return self.form == "tensor" and self.model == "hooke"

    @torch.no_grad()
    def cut_plan(self, rows: torch.Tensor, nodes: torch.Tensor, removed: torch.Tensor) -> dict:
        """What re-pointing the elements at ``rows`` (``[M]``, ascending, alive) to ``nodes [M, n]``
        takes, checked against the room there is before anything changes (:meth:`apply_cut` does
        it; ``removed [N_model]``: the model's removed flags). Where a node id changes, the new
        id must be a node no element was ever on (a cut's new node). The hooke tensor form: the
        edges that gain a new node become new edge rows and the old edges left with no element
        leave the plan; every node's edges must fit ``num_slots - 1``
        (:meth:`reserve_slots`; one host read).

        Raises:
            CapacityError: a node would need more slots than the plan has.
        """
        old = self.elements[rows]
        plan = {"rows": rows, "old": old, "nodes": nodes.to(self.elements.dtype), "changed": old != nodes}
        if not self._edge_plan():
            return plan
        pairs = self._pairs(rows.device)
        changed = plan["changed"]
        moved = changed[:, pairs[:, 0]] | changed[:, pairs[:, 1]]  # [M, P]: the pair's edge changes
        a, b = nodes[:, pairs[:, 0]][moved].long(), nodes[:, pairs[:, 1]][moved].long()
        keys = torch.minimum(a, b) * self.num_nodes + torch.maximum(a, b)
        unique_keys, edge_of = torch.unique(keys, return_inverse=True)
        edges = torch.stack([unique_keys // self.num_nodes, unique_keys % self.num_nodes], 1)  # [E', 2]
        # the old edges the moved pairs leave, and those of them no alive element is left on
        old_edges = self.element_edges[rows]
        left, moving = torch.unique(old_edges[moved].long(), return_counts=True)
        listed = self.edge_slots[:, left].long()
        alive = ((listed >= 0) & ~removed[listed.clamp(min=0)]).sum(0)
        dead = left[alive == moving]
        change = torch.zeros_like(self.plan.incidences)
        change.index_add_(0, edges.reshape(-1), torch.ones_like(edges.reshape(-1), dtype=change.dtype))
        dead_ends = self.edges[dead].reshape(-1).long()
        change.index_add_(0, dead_ends, torch.full_like(dead_ends, -1, dtype=change.dtype))
        need = int((self.plan.incidences + change).max()) if self.num_nodes else 0
        if need > self.plan.num_slots - 1:
            raise CapacityError(f"a node would have {need} edges; the plan has room for {self.plan.num_slots - 1}")
        plan.update(moved=moved, edges=edges, edge_of=edge_of, dead=dead, old_edges=old_edges)
        return plan

    def _pairs(self, device) -> torch.Tensor:
        n = self.nodes_per_element
        return torch.tensor([(a, b) for a in range(n) for b in range(a + 1, n)], device=device)

    def _edit_plan(self, gone_items, gone_nodes, new_items, new_nodes) -> None:
        """The gather plan's lists edited in place: items ``gone_items [R]`` (``row * w + a``)
        leave their nodes ``gone_nodes [R]`` (each list packed in order), ``new_items [A]`` join
        ``new_nodes [A]`` after the items there (in the order given); ``force_index`` and
        ``incidences`` follow, and the native copies of the plan (``library.refresh_plan_indices``)."""
        table = self._node_items()
        force_index, incidences = self.plan.force_index.view(-1), self.plan.incidences
        if gone_items.numel():
            touched, lists = topology.remove_from_lists(table, gone_nodes, gone_items)
            used = lists >= 0
            slot_of = torch.arange(lists.shape[0], device=lists.device)[:, None].expand_as(lists)
            force_index[lists[used].long()] = slot_of[used].to(force_index.dtype)
            incidences[touched] = used.sum(0).to(incidences.dtype)
        if new_items.numel():
            slots = topology.append_slots(incidences[new_nodes], new_nodes)
            table[slots, new_nodes] = new_items.to(table.dtype)
            force_index[new_items.long()] = slots.to(force_index.dtype)
            incidences.index_add_(0, new_nodes, torch.ones_like(new_nodes, dtype=incidences.dtype))
        library.refresh_plan_indices(self.plan)

    @torch.no_grad()
    def apply_cut(self, plan: dict, ids: torch.Tensor, rest: torch.Tensor, removed: torch.Tensor,
                  element_row: torch.Tensor) -> bool:
        """Re-point the elements as :meth:`cut_plan` planned (``ids [M]``: their model ids; ``rest``
        ``[V, d]`` already holding the new nodes' rest positions). Element data (shape vectors,
        measures, tensors B, C, D) are per element and unchanged: the rest shape is the same. Only
        sums over nodes or edges change, in place:

            element plans   each moved incidence leaves its node's list (the list packed in order)
                            and joins the new node's (in element order): the slots of a group
                            built from the new elements
            hooke tensor    an edge that gains a new node is a new edge row (edges, edge_k,
                            edge_slots grow; its slots appended at both ends); an old edge sums
                            its remaining elements again, and one left with none leaves its
                            nodes' lists (its row stays, a zero edge of node 0's sink slot); the
                            node graphs cached on the group are written again in place
                            (``node_graph.topology_changed``)

        Forces, products and energy are then those of a group built from the new elements (to
        rounding: edge tensors summed in another order of edges). Needs :meth:`prepare_removals`.

        Returns:
            whether solves captured before must be captured again: the stress forms' tangent
            graph dropped (built again at its next use), or a chunk of the pipelined solve grown
            past the slots its launches were given (``solve.chunk_slots_grew``)."""
        rows, old, nodes, changed = plan["rows"], plan["old"], plan["nodes"], plan["changed"]
        self._node_items()  # the plan's lists, made (at the first cut) from the plan before it changes
        if not self._edge_plan():
            n = self.nodes_per_element
            items = (rows.long()[:, None] * n + torch.arange(n, device=rows.device))[changed]
            self.elements[rows] = nodes  # the plan's index (the same tensor)
            self._edit_plan(items, old[changed].long(), items, nodes[changed].long())
            dropped = [self.__dict__.pop(name, None) for name in ("_native_tangent_graph", "_native_rows_tangent",
                                                                  "_native_by_rows_tangent")]
            return dropped[0] is not None
        moved, edge_of, edges, dead, old_edges = (plan[k] for k in ("moved", "edge_of", "edges", "dead", "old_edges"))
        moved_ids = ids.to(self.edge_slots.dtype)[:, None].expand_as(moved)[moved]
        topology.remove_from_lists(self.edge_slots, old_edges[moved].long(), moved_ids)
        # the old edges of the rows summed again without the moved pairs (element_edges still old)
        topology.refresh_hooke_edges(rest, self.elements, rows, self.element_edges, self.edge_slots, element_row,
                                     removed, self.measure, self.young, self.poisson, self.edge_k)
        first_new, sink = self.edges.shape[0], self.plan.num_slots - 1
        lists = torch.full((self.edge_slots.shape[0], edges.shape[0]), -1, dtype=self.edge_slots.dtype,
                           device=edges.device)
        # each new edge's elements in id order (ids ascending, an element once per edge)
        lists[topology.append_slots(torch.zeros_like(edge_of), edge_of), edge_of] = moved_ids
        self.edge_slots = torch.cat([self.edge_slots, lists], 1)
        self.edges = torch.cat([self.edges, edges.to(self.edges.dtype)])
        self.edge_k = torch.cat([self.edge_k, self.edge_k.new_zeros((edges.shape[0],) + self.edge_k.shape[1:])])
        new_edges = old_edges.clone()
        new_edges[moved] = (edge_of + first_new).to(old_edges.dtype)
        self.element_edges[rows] = new_edges
        # the plan (the object kept: its caches follow it) over the grown edges
        self.plan.index = self.edges
        self.plan.force_index = torch.cat([self.plan.force_index, self.plan.force_index.new_full(edges.shape, sink)])
        dead_items = (dead[:, None] * 2 + torch.arange(2, device=dead.device)).reshape(-1)
        new_items = torch.arange(2 * first_new, 2 * (first_new + edges.shape[0]), device=edges.device)
        self._edit_plan(dead_items, self.edges[dead].reshape(-1).long(), new_items, edges.reshape(-1))
        self.edges[dead] = 0  # a zero edge (0, 0) in node 0's sink slot: its partial forces, 0, never read
        self.plan.force_index[dead] = sink
        self.elements[rows] = nodes
        topology.refresh_hooke_edges(rest, self.elements, rows, self.element_edges, self.edge_slots, element_row,
                                     removed, self.measure, self.young, self.poisson, self.edge_k)
        node_graph.topology_changed(self)
        return solve.chunk_slots_grew(self)

    def lame(self, young=None, poisson=None):
        """(lam, mu) ``[N]``, plane-stress for membranes and 2-D triangles."""
        young = self.young if young is None else young
        poisson = self.poisson if poisson is None else poisson
        return lame(young, poisson, plane_stress=self.kind == "tri")

    def _apply(self, fn, *args, **kwargs):
        super()._apply(fn, *args, **kwargs)
        # The plan's integer tensors follow the module's device (not its dtype).
        self.plan = self.plan.to(self.elements.device)
        return self

    def buffer_bytes(self) -> int:
        """Bytes held by this group's tensors (buffers and gather plan)."""
        total = sum(b.numel() * b.element_size() for b in self.buffers())
        p = self.plan
        return total + sum(t.numel() * t.element_size() for t in (p.index, p.force_index, p.incidences))

    def extra_repr(self) -> str:
        """What ``print(group)`` shows: kind, model, form, rotation, tangent, sizes."""
        return (f"kind={self.kind}, model={self.model}, form={self.form}, rotation={self.rotation}, "
                f"tangent={self.tangent}, "
                f"elements={self.elements.shape[0]}, "
                f"dim={self.dim}, N_n={self.plan.num_slots}")
