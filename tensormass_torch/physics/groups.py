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

from ..errors import MaterialError
from ..mesh import geometry
from ..mesh.topology import GatherPlan, unique_edges
from ..ops import node_graph, topology
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
