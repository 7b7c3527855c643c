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

from typing import Optional

import torch
from torch import nn

from ..errors import MaterialError
from ..mesh import geometry
from ..mesh.topology import GatherPlan, add_at, unique_edges
from ..ops import cutting, library, node_graph, solve, topology
from ..ops.reference import tensor_form
from .materials import lame

FORMS = ("stress", "tensor")


class ElementGroup(nn.Module):
    """Elements of one kind, model and form.

    Args:
        rest: rest positions of all nodes ``[V, d]``.
        elements: global node ids ``[N, n]`` (n = 4 tetrahedra, 3 triangles), positively oriented;
            kept as int32 where the node count and ``N n`` fit (every index tensor of the group
            then has that dtype, the one the kernels read), else int64.
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
        #: edge rows added to the stress forms' tangent graph for cuts in place (:meth:`reserve_slots`)
        self.reserved_edges = 0
        self.membrane = geometry.needs_projector(self.nodes_per_element, self.dim)
        if self.num_nodes < 2**31 - 1 and elements.numel() < 2**31 - 1:
            elements = elements.to(torch.int32)  # (arithmetic that can pass 2^31 widens: unique_edges)

        m, measure, proj = geometry.rest_geometry(rest, elements, self.membrane)
        measure = measure.abs()  # orientation is checked by the mesh; the measure is a size
        if measure_scale is not None:
            measure = measure * measure_scale
        self.register_buffer("elements", elements)
        self.register_buffer("measure", measure)

        if model == "corotational" and form != "stress":
            raise MaterialError("the corotational model has the stress form only")
        self.rotation = rotation if model == "corotational" else None
        if self.rotation == "qr" and self.dim != 3:
            raise MaterialError("the QR rotation frame needs 3-D elements; use rotation='polar'")
        if self.rotation == "qr" or (self.rotation == "polar" and self.membrane):
            element_rest = geometry.element_nodes(rest, elements)
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
            edges, edge_k = tensor_form.assemble_hooke_edges(m, measure, lam, mu, proj, elements, self.num_nodes)
            self.register_buffer("edges", edges)
            self.register_buffer("edge_k", edge_k)
            self.plan = GatherPlan.build(edges, self.num_nodes)
            #: the edge rows in use, live or emptied by a cut (the rows past it: the pool cuts
            #: take new edges from, :meth:`reserve_slots`)
            self.edge_rows_used = edges.shape[0]
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
            _, pairs, element_edges = unique_edges(self.elements, self.num_nodes)  # the edges' own order
            self.register_buffer("element_edges", element_edges.contiguous())
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
            self.shape_vectors.index_fill_(0, rows.long(), 0.0)
            self.measure.index_fill_(0, rows.long(), 0.0)
        elif self.model == "hooke":
            topology.refresh_hooke_edges(rest, self.elements, rows, self.element_edges, self.edge_slots, element_row,
                                         removed, self.measure, self.young, self.poisson, self.edge_k)
            if node_graph.has_cached_graph(self):
                node_graph.edges_changed(self, self.element_edges[rows].reshape(-1))
        else:
            for tensor in (self.tensor_b, self.tensor_c, self.tensor_d):
                tensor.index_fill_(0, rows.long(), 0.0)

    # ---------------------------------------------------------------- cuts (elements re-pointed)
    def reserve_slots(self, extra: int, spare_edges: int = 0) -> None:
        """Room for ``extra`` (>= 1) more items on each node of the gather plan (its
        ``num_slots``; the gathers read a node's first ``incidences`` slots only): what cuts in
        place need where a node gains items, the hooke tensor form's edges (a node split next to
        it adds an edge). The last slot is kept empty: edges a cut leaves with no element write
        their zero there (the sink slot of node 0). The hooke tensor form also gets a pool of
        ``spare_edges`` edge rows, zero edges (0, 0) in the sink slot, from which cuts take their
        new edges: while it lasts, a cut moves no edge array (what captured launches read). Before
        any graph of the group is built (the node graphs take their slot count from it).

        A stress-form stvk or corotational group keeps its plan (a cut's new node takes items its
        parent had: it never needs more slots) and notes the room for its tangent graph
        (``reserved_slots``, ``reserved_edges``), which ``node_graph.tangent_graph`` builds with
        it so that a cut writes that graph again in place."""
        if self.form == "stress" and self.model != "hooke" and extra > 0:
            self.reserved_slots, self.reserved_edges = int(extra), int(spare_edges)
        if self.form == "tensor" and self.model == "hooke" and extra > 0:
            self.reserved_slots = int(extra)
            sink = self.plan.num_slots + int(extra) - 1
            edge_slots = getattr(self, "edge_slots", None)
            self.edges, force_index, edge_slots = _edge_pool(self.edges, self.plan.force_index, edge_slots,
                                                             int(spare_edges), sink)
            if edge_slots is not None:
                self.edge_slots = edge_slots
            self._edge_k_over_edges()
            self.plan = GatherPlan(self.edges, force_index, self.plan.num_slots + int(extra),
                                   self.plan.num_nodes, self.plan.incidences)
            self.__dict__.pop("_cut_tables", None)

    def _edge_k_over_edges(self) -> None:
        """``edge_k`` grown with zero blocks to the rows of ``edges`` (the pool's), where it has fewer."""
        grown = self.edges.shape[0] - self.edge_k.shape[0]
        if grown > 0:
            self.edge_k = torch.cat([self.edge_k, self.edge_k.new_zeros((grown,) + self.edge_k.shape[1:])])

    def _edge_plan(self) -> bool:
        return self.form == "tensor" and self.model == "hooke"

    def _plans_on_a_copy(self) -> bool:
        """Whether cuts are planned on host copies of the tables (:meth:`cut_tables`): on an
        accelerator, so that a cut reads nothing back from it."""
        return self.elements.device.type != "cpu"

    def cut_tables(self) -> dict:
        """The integer tables a cut reads and edits, on the host, by name: ``elements [N, n]``, the
        gather plan's ``force_index`` and ``incidences [V]``, its lists ``node_items [N_n, V]``
        (slot s of node i holds the item ``row * w + a``, w the width of the plan's items, n or 2,
        whose ``force_index`` is s; -1 past the last) and, for the hooke tensor form, ``edges
        [Ed, 2]``, ``edge_slots [S, Ed]`` and ``element_edges [N, P]``. On the CPU the group's own
        tensors (and ``node_items``); on an accelerator copies, made at the first cut (one device
        read) and kept equal to the group's by each cut, which is planned on them and written to
        the device once (:meth:`edit_cut`, :meth:`write_cut`). Needs :meth:`prepare_removals`."""
        tables = self.__dict__.get("_cut_tables")
        if tables is None:
            copy = (lambda t: t.to("cpu", copy=True)) if self._plans_on_a_copy() else (lambda t: t)
            tables = {"elements": copy(self.elements), "force_index": copy(self.plan.force_index),
                      "incidences": copy(self.plan.incidences)}
            if self._edge_plan():
                tables.update(edges=copy(self.edges), edge_slots=copy(self.edge_slots),
                              element_edges=copy(self.element_edges))
            index = tables["edges" if self._edge_plan() else "elements"]
            flat = index.reshape(-1).long()
            items = torch.arange(flat.numel(), dtype=index.dtype)
            slots = tables["force_index"].reshape(-1).long()
            # the listed items only: the pool's and emptied edges (0, 0) sit in node 0's sink slot,
            # past its count, and belong to no list
            listed = slots < tables["incidences"].long()[flat]
            node_items = torch.full((self.plan.num_slots, self.num_nodes), -1, dtype=index.dtype)
            node_items[slots[listed], flat[listed]] = items[listed]
            tables["node_items"] = node_items
            self.__dict__["_cut_tables"] = tables
        return tables

    def _grow_edge_pool(self, rows: int) -> None:
        """The edge pool of the tables of :meth:`cut_tables` grown to at least ``rows`` edge rows,
        by an eighth of the rows at least (new tensors: the arrays move, on the device too, at
        :meth:`write_cut`)."""
        tables = self.cut_tables()
        capacity = tables["edges"].shape[0]
        grow = max(rows - capacity, capacity // 8)
        tables["edges"], tables["force_index"], tables["edge_slots"] = _edge_pool(
            tables["edges"], tables["force_index"], tables["edge_slots"], grow, self.plan.num_slots - 1)

    @torch.no_grad()
    def edit_cut(self, rows: torch.Tensor, ids: torch.Tensor, nodes: torch.Tensor, node_slots: torch.Tensor,
                 element_row: torch.Tensor, removed: torch.Tensor) -> tuple:
        """The tables of :meth:`cut_tables` and the model's lists ``node_slots [S', V]`` (model
        element ids) edited for the elements at ``rows [M]`` (ascending, alive; ``ids [M]``: their
        model ids, int64) re-pointed to ``nodes [M, n]``, in one host call
        (``ops.cutting.edit_cut_tables``; ``element_row``, ``removed``: the model's, on the host),
        the room checked before anything changes. Where a node id changes, the new id must be a
        node no element was ever on (a cut's new node). Element data (shape vectors, measures,
        tensors B, C, D) are per element and unchanged: the rest shape is the same. Only sums over
        nodes or edges change:

            element plans   each moved incidence leaves its node's list (the list packed in order)
                            and joins the new node's (in element order): the slots of a group
                            built from the new elements
            hooke tensor    an edge that gains a new node is a new edge row, taken from the pool
                            (:meth:`reserve_slots`; grown where short: the arrays move); its
                            elements listed in id order, its slots appended at both ends; an old
                            edge keeps the elements that stay, and one left with none leaves its
                            nodes' lists (its row stays, a zero edge (0, 0) in node 0's sink slot,
                            the plan's last); every node's edges must fit ``num_slots - 1``

        Returns:
            the host tensors :meth:`write_cut` needs on the device (by name; on an accelerator,
            the tables' changed parts too) and the op's results by name (the model's among them:
            ``slot_nodes``, ``node_slot_lists``, ``both``).

        Raises:
            CapacityError: a node would need more slots than the plan has (nothing changed).
        """
        tables = self.cut_tables()
        nodes = nodes.to(tables["elements"].dtype)
        edge_plan = self._edge_plan()
        old_nodes = tables["elements"][rows.long()].clone()  # (the tangent graph's edit reads them)
        done, rows_used = cutting.edit_cut_tables(tables, node_slots, rows, ids, nodes, element_row, removed,
                                                  self.edge_rows_used if edge_plan else 0, self._grow_edge_pool)
        done["old_nodes"] = old_nodes
        copy = tables["elements"] is not self.elements
        if not edge_plan:
            sends = {}
            if copy:
                sends.update(rows=rows, nodes=nodes, incidence_nodes=done["incidence_nodes"],
                             incidences=done["incidences"], items=done["items"], force_index=done["force_index"])
            return sends, done
        self.edge_rows_used = rows_used
        sends = {name: done[name] for name in ("refresh_rows", "dead", "graph_edges", "incidence_nodes")}
        if copy:
            sends.update(slot_edges=done["slot_edges"], slot_lists=done["edge_slot_lists"], edge_rows=done["edge_rows"],
                         edge_values=done["edge_values"], rows=rows, element_edges=done["element_edges"], nodes=nodes,
                         incidences=done["incidences"], items=done["items"], force_index=done["force_index"])
        return sends, done

    @torch.no_grad()
    def write_cut(self, sent: dict, rest: torch.Tensor, removed: torch.Tensor, element_row: torch.Tensor,
                  cut: Optional[tuple] = None) -> bool:
        """The device side of a cut :meth:`edit_cut` made on the tables: ``sent`` its tensors on
        the group's device (``ops.topology.upload``; ``rest [V, d]`` already holding the new
        nodes' rest positions, ``removed``, ``element_row``: the model's; ``cut``: the host's
        ``(rows [M], old nodes [M, n], new nodes [M, n])``, which the stress forms' tangent graph
        on the CPU is edited from, or None: built again). Writes the changed
        parts of the tables where they are copies, then the sums: the hooke tensor form's edges
        of the cut's rows (and of one alive element of each edge the cut left) summed again
        (``ops.topology.refresh_hooke_edges``; new edges' tensors grow), emptied edges zeroed,
        the node graphs cached on the group written again in place where they changed
        (``node_graph.topology_changed``, ``node_graph.tangent_topology_changed``); the plans'
        native copies overwritten in place.

        Forces, products and energy are then those of a group built from the new elements (to
        rounding: edge tensors summed in another order of edges).

        Returns:
            whether solves captured before must be captured again: the stress forms' tangent
            graph dropped where it did not fit its room (``node_graph.tangent_topology_changed``;
            built again at its next use), or a chunk of the pipelined solve grown past the slots
            its launches were given (``solve.chunk_slots_grew``)."""
        tables = self.cut_tables()
        copy = tables["elements"] is not self.elements
        if copy:
            self.elements.index_copy_(0, sent["rows"].long(), sent["nodes"])
        if not self._edge_plan():
            if copy:
                self.plan.force_index.view(-1).index_copy_(0, sent["items"].long(), sent["force_index"])
                self.plan.incidences.index_copy_(0, sent["incidence_nodes"].long(), sent["incidences"])
            library.refresh_plan_indices(self.plan)
            if node_graph.tangent_topology_changed(self, cut):  # dropped: built again, captured again
                return True
            return solve.chunk_slots_grew(self)
        if copy:
            grow = tables["edges"].shape[0] - self.edges.shape[0]  # the pool grew with the host's
            self.edges, self.plan.force_index, self.edge_slots = _edge_pool(
                self.edges, self.plan.force_index, self.edge_slots, grow, self.plan.num_slots - 1)
            self.edges.index_copy_(0, sent["edge_rows"].long(), sent["edge_values"])
            self.edge_slots.index_copy_(1, sent["slot_edges"].long(), sent["slot_lists"])
            self.element_edges.index_copy_(0, sent["rows"].long(), sent["element_edges"])
            self.plan.force_index.view(-1).index_copy_(0, sent["items"].long(), sent["force_index"])
            self.plan.incidences.index_copy_(0, sent["incidence_nodes"].long(), sent["incidences"])
        else:  # the tables are the group's own (new tensors where the pool grew)
            self.edge_slots, self.edges = tables["edge_slots"], tables["edges"]
            self.plan.force_index = tables["force_index"]
        self._edge_k_over_edges()
        self.edge_k.index_fill_(0, sent["dead"].long(), 0)
        self.plan.index = self.edges  # the plan (the object kept: its caches follow it) over the grown edges
        topology.refresh_hooke_edges(rest, self.elements, sent["refresh_rows"], self.element_edges, self.edge_slots,
                                     element_row, removed, self.measure, self.young, self.poisson, self.edge_k)
        node_graph.topology_changed(self, sent["graph_edges"], sent["incidence_nodes"])
        return solve.chunk_slots_grew(self, tables["incidences"])

    def stiffness_diagonal(self) -> torch.Tensor:
        """The diagonal ``[V, d]`` of the group's linear stiffness at rest, K = -dF/du at u = 0
        (non-negative; what a Jacobi preconditioner divides by). Exact for hooke; for stvk and
        corotational the rest value, which their tangents leave near it for moderate strain (a
        preconditioner needs only a positive diagonal of the right size). Removed elements hold
        zeros (:meth:`remove_rows`), so they add nothing. Summed in an order that does not depend
        on the run (`mesh.topology.add_at`): the same preconditioner, the same iterates.

        Per node j and axis a, summed over the elements on j (Cotin's K_jj):
        measure ((lam + mu) m_ja^2 + mu |m_j|^2 P_aa), P the identity or the membrane's projector;
        the hooke tensor form's is minus its edges' tensors' diagonals (K_jj = -sum_k K_jk)."""
        rows = self.num_nodes
        if self.form == "tensor" and self.model == "hooke":
            diagonal = -torch.diagonal(self.edge_k, dim1=-2, dim2=-1)  # [Ed, d]
            nodes = self.edges.long()
            values = torch.stack([diagonal, diagonal], dim=1)  # the same at both ends
        else:
            if self.form == "tensor":  # stvk: B = K / 2
                values = 2.0 * torch.einsum("njjaa->nja", self.tensor_b)  # [N, n, d]
            else:
                lam, mu = self.lame()
                m = self.shape_vectors
                plane = (torch.ones_like(m[:, 0]) if self.projector is None
                         else torch.diagonal(self.projector, dim1=-2, dim2=-1))  # [N, d]
                squares = m * m
                values = self.measure[:, None, None] * ((lam + mu)[:, None, None] * squares
                                                        + mu[:, None, None] * squares.sum(-1, keepdim=True)
                                                        * plane[:, None, :])
            nodes = self.elements.long()
        out = values.new_zeros(rows, values.shape[-1])
        return add_at(out, nodes.reshape(-1), values.reshape(-1, values.shape[-1]))

    def rest_stiffness_edges(self):
        """The group's linear stiffness at rest as the node graph's off-diagonal blocks:
        ``(edges [E, 2] int64 (i < j), blocks [E, d, d])`` with K_ij = block, K_ji = block^T
        (K = -dF/du at u = 0); the diagonal blocks follow, K_ii = -sum_j K_ij (translations
        cost nothing). Exact for hooke, the tangent at rest for stvk and corotational: what a
        preconditioner built once per mesh assembles. Removed elements add nothing."""
        if self.form == "tensor" and self.model == "hooke":
            return self.edges.long(), self.edge_k
        if self.form == "tensor":  # stvk: B = K / 2
            return tensor_form.assemble_edges(2.0 * self.tensor_b, self.elements.long(), self.num_nodes)
        lam, mu = self.lame()
        return tensor_form.assemble_hooke_edges(self.shape_vectors, self.measure, lam, mu, self.projector,
                                                self.elements.long(), self.num_nodes)

    def lame(self, young=None, poisson=None):
        """(lam, mu) ``[N]``, plane-stress for membranes and 2-D triangles."""
        young = self.young if young is None else young
        poisson = self.poisson if poisson is None else poisson
        return lame(young, poisson, plane_stress=self.kind == "tri")

    def _apply(self, fn, *args, **kwargs):
        super()._apply(fn, *args, **kwargs)
        # The plan's integer tensors follow the module's device (not its dtype).
        self.plan = self.plan.to(self.elements.device)
        self.__dict__.pop("_cut_tables", None)  # made again from the moved tensors at the next cut
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


def _edge_pool(edges: torch.Tensor, force_index: torch.Tensor, edge_slots: Optional[torch.Tensor], count: int,
               sink: int):
    """A hooke tensor form's edge tables with ``count`` pool rows appended: zero edges (0, 0)
    whose partial forces (0) go to node 0's sink slot ``sink`` and whose lists (``edge_slots``, if
    made) are empty. Returns (edges ``[Ed + count, 2]``, force_index ``[Ed + count, 2]``,
    edge_slots ``[S, Ed + count]`` or None); the tensors themselves where count is 0."""
    if count <= 0:
        return edges, force_index, edge_slots
    edges = torch.cat([edges, edges.new_zeros((count, 2))])
    force_index = torch.cat([force_index, force_index.new_full((count, 2), sink)])
    if edge_slots is not None:
        edge_slots = torch.cat([edge_slots, edge_slots.new_full((edge_slots.shape[0], count), -1)], 1)
    return edges, force_index, edge_slots
