"""The node-graph op family (``csrc/node_graph/``): the hooke tensor form's CG product in one
kernel over the node graph, that product ending in the CG step length, implicit Euler's
right-hand side in one pass over the nodes, and a stress-form group's tangent written as the
graph's slot tensors. Each op's pure-torch reference, fake kernel and example, and the graphs
themselves (built and cached per group).

The node graph of V nodes with at most N_n neighbours each ("ELL" arrays, stored by row):
``neighbor [N_n, V]`` (slot s of row r: a neighbour of the row's node), ``node_k [N_n, V, d, d]``
(the block of that neighbour: -d f_i / d u_j), ``incidences [V]`` (used slots of each row),
``row_node [V]`` or None (the node of each row; None: row r is node r). Rows are each object's
nodes sorted by slot count within windows (:func:`node_graph_rows`), so a warp's threads walk
as many slots each.

    hooke_node_system(p, graph, mass, free?, c_M, c_K, node_stiffness?) -> (Ap [V, d], p . Ap [V])
        (K p)_i = sum_{s < incidences[r]} -node_k[s][r] (p[neighbor[s][r]] - p_i), i = row_node[r]
    hooke_node_system_alpha(<the same>, ap!, chunk plan, rr, status!, alpha!, scratch!, counter!,
        add?)   Ap (plus another product's rows ``add``, projected likewise) and the step length;
                objects that stopped are skipped
    hooke_node_step_rhs(x, v, rest, graph, mass, external, planes?, h, w_coef, r_M, u!, rhs!,
        node_stiffness!?)   rhs = h (f((x - rest) + w_coef v) + external + contact(x)
                                  - Kc(x) w_coef v - r_M mass v), u = x - rest, Kc
    stress_tangent_node_k(u, <stress inputs>, rotations?, edge graph, node_k!, edge_partial!)
    node_graph_write_edges(edge_ids, edges, force_index, edge_k, node_k!, row_of?)
                            edges whose blocks changed (a removal) written again into a graph

All are solver kernels: no gradient (the group-level calls fall back to the element ops when one
is wanted).
"""
from __future__ import annotations

from typing import Optional

import torch

from .. import _backend
from ..mesh import geometry
from ..mesh.topology import sum_slots_in_order
from . import cg as cg_family
from . import library
from .gather import system_epilogue
from .library import OpDef, contiguous, model_name, plan_indices, slot_mask, supports, unchanged, wants_grad
from .reference import corotational, stress_form, tensor_form
from .stress import stress_args
from .variants import DEFAULT, KernelVariants

__all__ = ["edges_changed", "has_cached_graph", "topology_changed", "hooke_pair_tensors",
           "hooke_node_graph", "hooke_rows_graph", "node_graph_rows", "set_objects", "tangent_graph",
           "tangent_serves", "tangent_node_k", "graph_of_edges", "node_graph_of", "step_rhs_serves", "step_rhs",
           "planes_serve"]

# ---------------------------------------------------------------------------------------------
# References
# ---------------------------------------------------------------------------------------------


def _ref_hooke_node_system(p, neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff,
                           node_stiffness=None):
    """The node-centric hooke matvec: (K p)_i = sum over the used slots s of node i's row r of
    ``-node_k[s, r] (p[neighbor[s, r]] - p_i)`` with i = ``row_node[r]`` (None: i = r) (neighbor
    ``[N_n, V]``, node_k ``[N_n, V, d, d]``, incidences ``[V]``, all by row; unused slots are
    masked, whatever they hold), added slot after slot, then the system epilogue."""
    used = slot_mask(neighbor.shape[0], incidences)  # [N_n, V, 1]
    others = torch.where(used[..., 0], neighbor, neighbor.new_zeros(())).long()
    nodes = torch.arange(p.shape[0], device=p.device) if row_node is None else row_node.long()
    w = p[others] - p[nodes].unsqueeze(0)  # [N_n, V, d]
    terms = -torch.einsum("svab,svb->sva", node_k, w)
    kp_rows = sum_slots_in_order(torch.where(used, terms, terms.new_zeros(())))
    kp = torch.empty_like(kp_rows).index_copy_(0, nodes, kp_rows)
    return system_epilogue(kp, p, mass, free, c_mass, c_stiff, node_stiffness)


def _ref_hooke_node_system_alpha(p, neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff,
                                 node_stiffness, ap, chunk_start, chunk_object, object_chunk, rr, status, alpha,
                                 scratch, counter, add=None):
    product, p_dot_ap = _ref_hooke_node_system(p, neighbor, node_k, incidences, row_node, mass, free, c_mass,
                                               c_stiff, node_stiffness)
    if add is not None:  # another product's rows, projected likewise
        product = product + (add if free is None else add * free[:, None])
        p_dot_ap = (p * product).sum(-1)
    ap.copy_(product)
    cg_family._ref_cg_alpha(p_dot_ap, chunk_start, chunk_object, object_chunk, rr, status, alpha, scratch, counter)


def plane_contact(x, normals, offsets, stiffness):
    """Penalty planes n.x >= offset: the force on each node ``[V, 3]`` (sum of k (offset - n.x) n
    over the planes it is below) and its stiffness -(df/dx) ``[V, 3, 3]`` (sum of k n n^T)."""
    depth = offsets[None, :] - x @ normals.T  # [V, P]
    below = depth > 0
    weight = torch.where(below, stiffness[None, :], torch.zeros_like(depth))
    force = (weight * depth) @ normals
    k = torch.einsum("vp,pa,pb->vab", weight, normals, normals)
    return force, k


def _ref_hooke_node_step_rhs(x, v, rest, neighbor, node_k, incidences, row_node, mass, external, plane_normals,
                             plane_offsets, plane_stiffness, h, w_coef, rayleigh_mass, u, rhs, node_stiffness):
    w = (x - rest) + w_coef * v
    total, _ = _ref_hooke_node_system(w, neighbor, node_k, incidences, row_node, torch.zeros_like(mass), None, 0.0,
                                      -1.0)
    total = total + external
    if plane_normals is not None and x.shape[1] == 3:
        force, k = plane_contact(x, plane_normals, plane_offsets, plane_stiffness)
        total = total + force - torch.einsum("vab,vb->va", k, w_coef * v)
        if node_stiffness is not None:
            node_stiffness.copy_(k)
    u.copy_(x - rest)
    rhs.copy_(h * (total - (rayleigh_mass * mass)[:, None] * v))


def _ref_stress_tangent_node_k(u, elements, m, vol, lam, mu, proj, model, rotations, element_edges, edge_slots,
                               num_edge_slots, edge_counts, slot_edge, incidences, node_k=None, edge_partial=None):
    """stress_tangent_node_k's reference: the element blocks H_ab from the reference element
    dforces along unit displacements (n d of them), summed onto edges in slot order, written to
    the node graph's slots ``[N_n, V, d, d]`` (-H_g where slot_edge = g, -H_g^T where ~g; zeros in
    unused slots)."""
    n, d = elements.shape[1], u.shape[1]
    u_e = u[elements]
    name = model_name(model)
    blocks = u.new_zeros((elements.shape[0], n, n, d, d))  # [N, a, b, x, c] = d f_a[x] / d u_b[c]
    for b in range(n):
        for c in range(d):
            du_e = torch.zeros_like(u_e)
            du_e[:, b, c] = 1
            if name == "corotational":
                f = corotational.dforces(du_e, m, vol, lam, mu, rotations, proj)
            else:
                f = stress_form.DFORCES[name](u_e, du_e, m, vol, lam, mu, proj)
            blocks[:, :, b, :, c] = f
    pairs = [(a, b) for a in range(n) for b in range(a + 1, n)]
    pair_blocks = torch.stack([blocks[:, a, b] for a, b in pairs], dim=1)  # [N, P, d, d]
    low_first = torch.stack([elements[:, a] < elements[:, b] for a, b in pairs], dim=1)
    pair_blocks = torch.where(low_first[..., None, None], pair_blocks, pair_blocks.transpose(-1, -2))
    buffer = u.new_zeros((num_edge_slots, edge_counts.shape[0], d, d))
    buffer[edge_slots.long().reshape(-1), element_edges.long().reshape(-1)] = pair_blocks.reshape(-1, d, d)
    h = sum_slots_in_order(buffer)  # [Ed, d, d]
    code = slot_edge.long()
    used = torch.arange(code.shape[0], device=code.device)[:, None] < incidences.long()[None, :]
    first = code >= 0
    g = torch.where(first, code, -code - 1)
    blocks = torch.where(first[..., None, None], h[g], h[g].transpose(-1, -2))
    value = torch.where(used[..., None, None], -blocks, torch.zeros_like(blocks))  # [N_n, V, d, d]
    if node_k is not None:
        node_k.copy_(value)
    return value


# ---------------------------------------------------------------------------------------------
# Fake kernels, examples
# ---------------------------------------------------------------------------------------------


def _ref_node_graph_write_edges(edge_ids, edges, force_index, edge_k, node_k, row_of):
    """The blocks of the edges ``edge_ids [M]`` written again into ``node_k`` (see the op's schema)."""
    ids = edge_ids.long()
    first, second = edges[ids].long().unbind(1)
    slot_first, slot_second = force_index[ids].long().unbind(1)
    if row_of is not None:
        first, second = row_of.long()[first], row_of.long()[second]
    blocks = edge_k[ids]
    node_k[slot_first, first] = blocks
    node_k[slot_second, second] = blocks.transpose(1, 2)


def _ref_node_graph_rebuild_hooke_rows(pair_k, elements, node_slots, alive, touched, row_of, max_slots, neighbor,
                                       node_k, incidences, status, firsts):
    """Each touched node's row summed again from its alive elements in list order, each element's
    pair tensor (a < b locally) oriented from the lower global node, read from the row's node:
    neighbours in the order first met (elements in order, then their other local nodes in order).
    (``firsts [S, V]`` is the op's scratch: the reference leaves it.)"""
    n = elements.shape[1]
    pair_of = {(a, b): k for k, (a, b) in enumerate((a, b) for a in range(n) for b in range(a + 1, n))}
    for p in torch.nonzero(touched).flatten().tolist():
        ids = node_slots[:, p].long()
        ids = ids[ids >= 0]
        ids = ids[alive[ids]]
        rows = elements[ids].long()  # [k, n]
        others, blocks = [], []
        for j in range(rows.shape[0]):
            mine = int(torch.nonzero(rows[j] == p)[0])
            for b in range(n):
                if b == mine:
                    continue
                lo, hi = min(mine, b), max(mine, b)
                block = pair_k[ids[j], pair_of[(lo, hi)]]
                stored = block if rows[j, lo] < rows[j, hi] else block.t()  # lower -> higher node
                q = int(rows[j, b])
                if q not in others:
                    others.append(q)
                    blocks.append(torch.zeros_like(block))
                blocks[others.index(q)] += stored if p < q else stored.t()
        if len(others) > max_slots:  # (the op may also write the row's blocks: not to be used)
            status[0] = 1
            continue
        row = p if row_of is None else int(row_of[p])
        if others:
            neighbor[:len(others), row] = torch.tensor(others, dtype=neighbor.dtype, device=neighbor.device)
            node_k[:len(others), row] = torch.stack(blocks)
        incidences[row] = len(others)


def hooke_pair_tensors(rest: torch.Tensor, elements: torch.Tensor, measure: torch.Tensor, young: torch.Tensor,
                       poisson: torch.Tensor, chunk: int = 1 << 16) -> torch.Tensor:
    """Cotin's tensor K_ab of each local pair a < b of each element ``[N, P, d, d]`` (pairs in the
    order (0, 1), (0, 2), ...; of rest's dtype and device), formed from the rest shape ``rest
    [V, d]``, ``measure``, ``young`` and ``poisson`` ``[N]`` (plane stress for triangles), in chunks
    of ``chunk`` elements: what ``node_graph_rebuild_hooke_rows`` sums."""
    n, dim = elements.shape[1], rest.shape[1]
    pairs = torch.tensor([(a, b) for a in range(n) for b in range(a + 1, n)], device=rest.device)
    out = rest.new_empty((elements.shape[0], pairs.shape[0], dim, dim))
    for begin in range(0, elements.shape[0], chunk):
        rows = elements[begin:begin + chunk].long()
        element_rest = rest[rows]
        m, _ = geometry.shape_vectors(element_rest)
        proj = geometry.tangent_projectors(element_rest) if geometry.needs_projector(n, dim) else None
        lam, mu = stress_form.lame(young[begin:begin + chunk], poisson[begin:begin + chunk], plane_stress=n == 3)
        k = tensor_form.element_stiffness(m, measure[begin:begin + chunk], lam, mu, proj)
        out[begin:begin + chunk] = k[:, pairs[:, 0], pairs[:, 1]]
    return out


def _fake_hooke_node_system(p, neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff,
                            node_stiffness=None):
    return p.new_empty(p.shape), p.new_empty((p.shape[0],))


def _example(name):
    def example(device, dtype):
        ex = library.Example(device, dtype)
        neighbor, node_k = graph_of_edges(ex.edges, ex.edge_force_index, ex.edge_slots, ex.num_nodes, ex.edge_k)
        # rows keep to the objects of the cg family's example (nodes 0-2 and 3-4)
        rows = node_graph_rows(ex.edge_incidences, (0, 3, ex.num_nodes), 4).to(torch.int32)
        by_row = rows.long()
        graph = (neighbor[:, by_row].contiguous(), node_k[:, by_row].contiguous(),
                 ex.edge_incidences[by_row].contiguous(), rows)
        system = (ex.du, *graph, ex.mass, ex.free, 1.5, 0.25, None)
        if name == "hooke_node_system":
            return system, {}
        if name == "hooke_node_system_alpha":
            alpha_args, _ = cg_family.OPS[0].example(device, dtype)
            (_, *plan, rr, status, alpha, scratch, counter) = alpha_args
            # (with another product's rows added: the contact pairs' in a step with body contact)
            return (*system, torch.zeros_like(ex.du), *plan, rr, status, alpha, scratch, counter), {
                "add": 0.5 * ex.du.flip(0)}
        if name == "node_graph_write_edges":
            changed = 2.0 * ex.edge_k  # the edges' new blocks
            edge_ids = torch.tensor([3, 0, 3], device=device)
            row_of = torch.empty_like(rows)
            row_of[by_row] = torch.arange(rows.shape[0], device=device, dtype=rows.dtype)
            return (edge_ids, ex.edges, ex.edge_force_index, changed, graph[1].clone(), row_of), {}
        if name == "node_graph_rebuild_hooke_rows":
            from .topology import incidence_table

            elements = ex.elements.to(neighbor.dtype)
            node_slots = incidence_table(elements.reshape(-1).long(), torch.arange(
                elements.shape[0], dtype=elements.dtype, device=device).repeat_interleave(elements.shape[1]),
                ex.num_nodes)
            alive = torch.ones(elements.shape[0], dtype=torch.bool, device=device)
            touched = torch.zeros(ex.num_nodes, dtype=torch.uint8, device=device)
            touched[elements[0].long()] = 1
            row_of = torch.empty_like(rows)
            row_of[by_row] = torch.arange(rows.shape[0], device=device, dtype=rows.dtype)
            status = torch.zeros(1, dtype=torch.int32, device=device)
            # the example's lam = 2, mu = 1.5: E = 27 / 7, nu = 2 / 7
            pair_k = hooke_pair_tensors(ex.rest, elements, ex.vol, torch.full_like(ex.vol, 27 / 7),
                                        torch.full_like(ex.vol, 2 / 7))
            firsts = torch.zeros(node_slots.shape, dtype=torch.int32, device=device)
            return (pair_k, elements, node_slots, alive, touched, row_of.to(neighbor.dtype), neighbor.shape[0],
                    graph[0].clone(), graph[1].clone(), graph[2].clone(), status, firsts), {}
        if name == "hooke_node_step_rhs":
            x = ex.rest + ex.u
            normals = torch.tensor([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0]], device=device, dtype=dtype)
            offsets = torch.tensor([0.02, 0.01], device=device, dtype=dtype)
            stiffness = torch.tensor([50.0, 20.0], device=device, dtype=dtype)
            return (x, ex.du, ex.rest, *graph, ex.mass, 9.8 * ex.du, normals, offsets, stiffness, 0.01, 0.02, 0.1,
                    torch.empty_like(x), torch.empty_like(x), x.new_empty((ex.num_nodes, 3, 3))), {}
        from ..mesh.topology import EdgeGraph

        edge_graph = EdgeGraph.build(ex.elements.long(), ex.num_nodes)

        def i(t):
            return t.to(device=device, dtype=torch.int32).contiguous()

        plan = edge_graph.plan
        node_k = torch.zeros((plan.num_slots, ex.num_nodes, 3, 3), device=device, dtype=dtype)
        work = torch.zeros((edge_graph.num_edge_slots, edge_graph.edges.shape[0], 12), device=device, dtype=dtype)
        return (ex.u, ex.elements, *ex.stress("stvk")[:6], None, i(edge_graph.element_edges), i(edge_graph.edge_slots),
                edge_graph.num_edge_slots, i(edge_graph.edge_counts), i(edge_graph.slot_edge), i(plan.incidences),
                node_k, work), {}

    return example


OPS = (
    OpDef("hooke_node_system", _ref_hooke_node_system, _fake_hooke_node_system, differentiable=False,
          example=_example("hooke_node_system")),
    OpDef("hooke_node_system_alpha", _ref_hooke_node_system_alpha, None, differentiable=False, mutates=True,
          example=_example("hooke_node_system_alpha"), scratch=("scratch", "counter")),
    OpDef("hooke_node_step_rhs", _ref_hooke_node_step_rhs, None, differentiable=False, mutates=True,
          example=_example("hooke_node_step_rhs")),
    OpDef("node_graph_write_edges", _ref_node_graph_write_edges, None, differentiable=False, mutates=True,
          example=_example("node_graph_write_edges")),
    OpDef("node_graph_rebuild_hooke_rows", _ref_node_graph_rebuild_hooke_rows, None, differentiable=False,
          mutates=True, example=_example("node_graph_rebuild_hooke_rows"), scratch=("firsts",)),
    OpDef("stress_tangent_node_k", _ref_stress_tangent_node_k, None, differentiable=False, mutates=True,
          example=_example("stress_tangent_node_k"), scratch=("edge_partial",)),
)
library.define(OPS, lambda: library.register(OPS))

# ---------------------------------------------------------------------------------------------
# The graphs of a group (cached on it)
# ---------------------------------------------------------------------------------------------


def _stamped(tensors, *value):
    """A cache entry (tensors, their versions now, *value), as :func:`library.unchanged` reads it."""
    return (tuple(tensors), tuple(t._version for t in tensors), *value)


def _zeros_like_nodes(group, u: torch.Tensor) -> torch.Tensor:
    """Zeros ``[V]`` of u's dtype and device, kept on the group (a mass term of 0)."""
    cached = group.__dict__.get("_node_zeros")
    if cached is None or cached.dtype != u.dtype or cached.device != u.device or cached.shape[0] != u.shape[0]:
        cached = group.__dict__["_node_zeros"] = torch.zeros(u.shape[0], dtype=u.dtype, device=u.device)
    return cached


def _edge_columns(edges: torch.Tensor, row_of: Optional[torch.Tensor] = None):
    """The columns (int64 ``[k]`` each) of the two ends of edges ``[k, 2]`` in a node graph's
    arrays: the nodes themselves (node order), or their rows where ``row_of [V]`` is given."""
    first, second = edges[:, 0].long(), edges[:, 1].long()
    if row_of is None:
        return first, second
    row_of = row_of.long()
    return row_of[first], row_of[second]


def _write_neighbors(neighbor: torch.Tensor, edges: torch.Tensor, force_index: torch.Tensor, columns) -> None:
    """Each end of edges ``[k, 2]`` lists the other in its slot (``force_index [k, 2]``) of
    ``neighbor [N_n, V]``, at the ends' ``columns`` (:func:`_edge_columns`); in place."""
    neighbor[force_index[:, 0].long(), columns[0]] = edges[:, 1].to(neighbor.dtype)
    neighbor[force_index[:, 1].long(), columns[1]] = edges[:, 0].to(neighbor.dtype)


def _edge_neighbors(edges: torch.Tensor, force_index: torch.Tensor, num_slots: int, num_nodes: int,
                    columns=None) -> torch.Tensor:
    """The node graph's neighbours ``[N_n, V]`` of edges ``[Ed, 2]`` with their slots
    ``force_index [Ed, 2]``: slot ``force_index[e, 0]`` of ``edges[e, 0]`` holds ``edges[e, 1]`` and
    the other way round; unused slots 0 (never read). edges' dtype. ``columns``: the ends'
    columns (:func:`_edge_columns`; default: node order); the values are nodes either way."""
    neighbor = edges.new_zeros((num_slots, num_nodes))
    _write_neighbors(neighbor, edges, force_index, _edge_columns(edges) if columns is None else columns)
    return neighbor


def set_objects(model, object_starts) -> None:
    """Tells the node graphs of ``model``'s groups (``model.groups``) where its objects start
    (``object_starts``: the first node of each object and the node count, ``[B + 1]``, a sequence
    or tensor; the solver's segments): their rows (:func:`node_graph_rows`) never mix two objects,
    whose CG scalars differ. Without it a group's nodes are one object. A model serves one set of
    objects: telling it other ones raises (a solver of the first would get rows that mix them)."""
    starts = tuple(int(v) for v in (object_starts.tolist() if torch.is_tensor(object_starts) else object_starts))
    for group in model.groups:
        known = group.__dict__.get("_native_objects")
        if known is not None and known != starts:
            raise ValueError(f"this model's node graphs already serve objects starting at nodes {list(known[:-1])}; "
                             f"objects starting at {list(starts[:-1])} need a model of their own")
    for group in model.groups:
        group.__dict__["_native_objects"] = starts


def _objects_of(group):
    return group.__dict__.get("_native_objects") or (0, group.num_nodes)


def node_graph_rows(incidences: torch.Tensor, object_starts, window: int) -> Optional[torch.Tensor]:
    """The rows of a node graph: ``row_node [V]`` (int64, on incidences' device), the node of each
    row: each object's nodes (``object_starts`` ``[B + 1]``) cut into windows of ``window`` nodes
    from its first, and within a window sorted by slot count (``incidences [V]``), most first, ties
    in node order. None (rows in node order) where ``window`` <= 1."""
    if window <= 1:
        return None
    counts = incidences.detach().cpu().long()
    num_nodes = counts.numel()
    starts = torch.tensor(object_starts, dtype=torch.long)
    nodes = torch.arange(num_nodes)
    obj = torch.searchsorted(starts[1:], nodes, right=True).clamp_(max=max(starts.numel() - 2, 0))
    window_index = obj * (num_nodes // window + 2) + (nodes - starts[obj]) // window  # increasing in the node
    by_count = torch.sort(-counts, stable=True).indices
    rows = by_count[torch.sort(window_index[by_count], stable=True).indices]
    return rows.to(incidences.device)


def _graph_rows(group, name: str, incidences: torch.Tensor, index_dtype, window: int) -> Optional[torch.Tensor]:
    """The row_node of the group's graph ``name`` of these (node-ordered) slot counts in windows
    of ``window`` nodes (:func:`node_graph_rows`), cached on the group."""
    key = (_objects_of(group), int(window), index_dtype)
    cache = group.__dict__.get("_native_rows_" + name)
    if unchanged(cache, (incidences,)) and cache[3] == key:
        return cache[2]
    rows = node_graph_rows(incidences, key[0], key[1])
    if rows is not None:
        rows = rows.to(index_dtype)
    group.__dict__["_native_rows_" + name] = _stamped((incidences,), rows, key)
    return rows


def _by_rows(group, name: str, incidences: torch.Tensor, tensors, window: int):
    """The node-ordered arrays ``tensors`` of the group's graph ``name`` (node along dim 1 for 2-D
    and more, else dim 0; ``incidences [V]``: its slot counts) reordered by its rows, and the rows
    (:func:`_graph_rows`); cached on the group while the tensors are unchanged and the rows the same."""
    rows = _graph_rows(group, name, incidences, tensors[0].dtype, window)
    cache = group.__dict__.get("_native_by_rows_" + name)
    if unchanged(cache, tensors) and cache[3] is rows:
        return cache[2], rows
    index = None if rows is None else rows.long()
    value = tuple(t if index is None else t.index_select(1 if t.dim() >= 2 else 0, index).contiguous()
                  for t in tensors)
    group.__dict__["_native_by_rows_" + name] = _stamped(tensors, value, rows)
    return value, rows


def hooke_rows_graph(group, window: int = DEFAULT.node_graph_window):
    """The hooke tensor form's node graph by rows, as the ``hooke_node_*`` ops take it: (neighbor
    ``[N_n, V]``, node_k ``[N_n, V, d, d]``, incidences ``[V]``, row_node ``[V]`` or None): the
    graph of :func:`hooke_node_graph` with its columns in the order of :func:`node_graph_rows`
    (windows of ``window`` nodes; ``window`` <= 1: node order, row_node None).

    Built straight into the rows' order and kept once on the group (a graph of another window
    replaces it), while the group's edge_k and its plan's indices are the same unmodified
    tensors; topology changes write into it in place (:func:`edges_changed`,
    :func:`topology_changed`). neighbor has the plan's native index dtype (that of
    :func:`_plan_indices`), node_k edge_k's dtype and device."""
    index, force_index, incidences = plan_indices(group.plan)
    edge_k = group.edge_k
    rows = _graph_rows(group, "hooke", incidences, index.dtype, window)
    tensors = (edge_k, index, force_index, incidences)
    cache = group.__dict__.get("_native_hooke_graph")
    if unchanged(cache, tensors) and cache[3] is rows:
        return (*cache[2], rows)
    group.__dict__.pop("_native_hooke_graph", None)  # the old graph's memory back before the new one
    row_of = None if rows is None else _row_of(group, rows)
    neighbor, node_k = graph_of_edges(index, force_index, group.plan.num_slots, group.plan.num_nodes, edge_k,
                                      row_of)
    row_incidences = incidences if rows is None else incidences.index_select(0, rows.long()).contiguous()
    value = (neighbor, node_k, row_incidences)
    group.__dict__["_native_hooke_graph"] = _stamped(tensors, value, rows)
    return (*value, rows)


def row_nodes_of(group, incidences: torch.Tensor) -> Optional[torch.Tensor]:
    """The node of each row ``[V]`` where ``incidences`` is the hooke graph's by rows
    (:func:`hooke_rows_graph`, in the rows' order); None where it is in node order."""
    cache = group.__dict__.get("_native_hooke_graph")
    if cache is not None and cache[3] is not None and cache[2][2] is incidences:
        return cache[3]
    return None


def graph_of_edges(edges: torch.Tensor, force_index: torch.Tensor, num_slots: int, num_nodes: int,
                   edge_k: torch.Tensor, row_of: Optional[torch.Tensor] = None):
    """The node graph of edges ``[Ed, 2]`` with their slots ``force_index [Ed, 2]`` and blocks
    ``edge_k [Ed, d, d]``: (neighbor ``[N_n, V]`` of edges' dtype, node_k ``[N_n, V, d, d]``); see
    :func:`hooke_node_graph`. ``row_of [V]``: each node's column (a graph by rows), or None (node
    order)."""
    dim = edge_k.shape[-1]
    first, second = columns = _edge_columns(edges, row_of)
    slot_first, slot_second = force_index[:, 0].long(), force_index[:, 1].long()
    neighbor = _edge_neighbors(edges, force_index, num_slots, num_nodes, columns)
    node_k = edge_k.new_zeros((num_slots, num_nodes, dim, dim))
    with torch.no_grad():
        node_k[slot_first, first] = edge_k
        node_k[slot_second, second] = edge_k.transpose(1, 2)
    return neighbor, node_k


def hooke_node_graph(group):
    """The node graph of a hooke tensor-form group in slot-major ("ELL") arrays, in node order:
    (neighbor ``[N_n, V]``, node_k ``[N_n, V, d, d]``), :func:`hooke_rows_graph` with window 1.

    Slot s of node i is the slot the group's plan gives it (``force_index``): for edge e = (i, j)
    (i = ``edges[e, 0]``), ``neighbor[fi[e, 0], i] = j`` with ``node_k = K_e`` and
    ``neighbor[fi[e, 1], j] = i`` with ``node_k = K_e^T``. Unused slots hold zeros (never read)."""
    neighbor, node_k, _, _ = hooke_rows_graph(group, window=1)
    return neighbor, node_k


def has_cached_graph(group) -> bool:
    """Whether a node graph of the hooke tensor-form ``group`` is cached (:func:`edges_changed`
    has something to write)."""
    cache = group.__dict__.get("_native_hooke_graph")
    return cache is not None and cache[0][0] is group.edge_k


def _write_edges_op(device):
    native = _backend.use_extension(device) and hasattr(torch.ops.tensormass, "node_graph_write_edges")
    return torch.ops.tensormass.node_graph_write_edges if native else _ref_node_graph_write_edges


@torch.no_grad()
def edges_changed(group, edge_ids: torch.Tensor) -> None:
    """A hooke tensor-form group's blocks ``edge_k`` changed in place at ``edge_ids [k]`` (a
    topology change, repeats allowed; its edges and plan the same): write them into the node graph
    cached on the group (:func:`hooke_rows_graph`) in place (``node_graph_write_edges``), since
    captured CUDA graphs and packed solves read its storage, and keep the cache current. A graph
    not built yet is built later from the new blocks."""
    if not has_cached_graph(group):
        return
    cache = group.__dict__["_native_hooke_graph"]
    edge_k, index, force_index, _ = cache[0]
    rows = cache[3]
    _write_edges_op(edge_k.device)(edge_ids, index, force_index, edge_k, cache[2][1],
                                   None if rows is None else _row_of(group, rows))
    stamp_again(group)


def stamp_again(group) -> None:
    """The node graph cached on ``group`` (if any) stamped with its tensors' versions now: after
    a write the caller made through their storage and told torch of (a replayed removal, whose
    eager run :func:`edges_changed` stamps the same way), the cache stays current."""
    if has_cached_graph(group):
        cache = group.__dict__["_native_hooke_graph"]
        group.__dict__["_native_hooke_graph"] = _stamped(cache[0], *cache[2:])


@torch.no_grad()
def topology_changed(group, edge_ids: torch.Tensor, nodes: torch.Tensor) -> None:
    """A hooke tensor-form group's edges changed or grew in place (a cut: its plan's ``num_slots``
    and node count the same): the edges ``edge_ids [k]`` (their ends, slots or blocks; new and
    emptied edges included) and the nodes ``nodes [m]`` (their ``incidences``). The native copies
    of its plan (``library.refresh_plan_indices``) and the node graph cached on the group (the
    same rows) are written in place at those edges and nodes (an emptied edge writes its zero
    block into node 0's sink slot), since captured CUDA graphs read their storage; the caches kept
    current. Slots past a node's ``incidences`` may keep what was there: nothing reads them. A
    graph not built yet is built later from the new data."""
    index, force_index, incidences = library.refresh_plan_indices(group.plan)
    cache = group.__dict__.get("_native_hooke_graph")
    if cache is None:
        return
    neighbor, node_k, row_incidences = cache[2]
    rows = cache[3]
    row_of = None if rows is None else _row_of(group, rows)
    edge_k = group.edge_k
    ids = edge_ids.long()
    ends = index[ids]
    _write_neighbors(neighbor, ends, force_index[ids], _edge_columns(ends, row_of))
    _write_edges_op(edge_k.device)(edge_ids, index, force_index, edge_k, node_k, row_of)
    if rows is not None:  # incidences of its own, in the rows' order
        row_incidences[row_of[nodes.long()].long()] = incidences[nodes.long()]
    else:  # the plan's, refreshed above (in place where its shape stayed)
        row_incidences = incidences
    rows_cache = group.__dict__.get("_native_rows_hooke")
    if rows_cache is not None and rows_cache[0][0] is incidences:  # the same rows: captured graphs read them
        group.__dict__["_native_rows_hooke"] = _stamped((incidences,), *rows_cache[2:])
    group.__dict__["_native_hooke_graph"] = _stamped((edge_k, index, force_index, incidences),
                                                     (neighbor, node_k, row_incidences), rows)


def _row_of(group, rows: torch.Tensor) -> torch.Tensor:
    """The row of each node ``[V]`` (the inverse of a graph's ``row_node``), cached on the group."""
    cache = group.__dict__.get("_row_of")
    if cache is not None and cache[0] is rows:
        return cache[1]
    row_of = torch.empty_like(rows)
    row_of[rows.long()] = torch.arange(rows.shape[0], device=rows.device, dtype=rows.dtype)
    group.__dict__["_row_of"] = (rows, row_of)
    return row_of


def tangent_graph(group, window: int = DEFAULT.node_graph_window):
    """The node graph of a stress-form group's tangent: (EdgeGraph with native index tensors, and
    by the rows of :func:`node_graph_rows`: neighbor ``[N_n, V]``, incidences ``[V]``, row_node
    ``[V]`` or None, slot_edge ``[N_n, V]``), the graph's index dtype that of :func:`_plan_indices`
    of the group's plan. Cached on the group while its elements are the same unmodified tensor
    (the first call synchronises with the device: build it before a capture)."""
    graph, neighbor, incidences = _tangent_edge_graph(group)
    (neighbor, row_incidences, slot_edge), rows = _by_rows(group, "tangent", incidences,
                                                          (neighbor, incidences, graph.slot_edge), window)
    return graph, neighbor, row_incidences, rows, slot_edge


def _tangent_edge_graph(group):
    """tangent_graph's (EdgeGraph, neighbor, incidences) in node order, cached on the group (with
    the room of ``group.reserved_slots`` and ``reserved_edges``: :func:`_padded_edge_graph`)."""
    elements = group.elements
    cache = group.__dict__.get("_native_tangent_graph")
    if unchanged(cache, (elements,)):
        return cache[2]
    graph = _built_tangent_graph(group)
    if group.reserved_slots:  # room for cuts, written in place (tangent_topology_changed)
        graph = _padded_edge_graph(graph, graph.plan.num_slots + group.reserved_slots,
                                   graph.edges.shape[0] + group.reserved_edges, graph.num_edge_slots)
    plan = graph.plan
    value = (graph, _edge_neighbors(plan.index, plan.force_index, plan.num_slots, plan.num_nodes),
             plan.incidences)
    group.__dict__["_native_tangent_graph"] = _stamped((elements,), value)
    return value


def _built_tangent_graph(group):
    """The EdgeGraph of the group's elements, its index tensors of the plan's native dtype."""
    from ..mesh.topology import EdgeGraph

    dtype = plan_indices(group.plan)[0].dtype  # the elements' (every index tensor of the op has one dtype)
    graph = EdgeGraph.build(group.elements.long(), group.num_nodes)
    plan = graph.plan

    def native(t):
        return t.to(dtype).contiguous()

    return type(graph)(native(graph.edges), native(graph.element_edges), native(graph.edge_slots),
                       graph.num_edge_slots, native(graph.edge_counts),
                       type(plan)(native(plan.index), native(plan.force_index), plan.num_slots, plan.num_nodes,
                                  native(plan.incidences)), native(graph.slot_edge))


def _padded_edge_graph(graph, num_slots: int, num_edges: int, num_edge_slots: int):
    """``graph`` (an EdgeGraph) with room: ``num_slots`` slots a node (the last a sink), ``num_edges``
    edge rows (the rows past its edges: zero edges (0, 0) with no element, in node 0's sink slot)
    and ``num_edge_slots`` elements an edge; None where it does not fit (a node with no free
    slot before the sink, more edges or elements an edge than that)."""
    plan = graph.plan
    extra_edges, extra_slots = num_edges - graph.edges.shape[0], num_slots - plan.num_slots
    if extra_edges < 0 or extra_slots < 1 or graph.num_edge_slots > num_edge_slots:
        return None

    def rows_after(t, count, value):
        return torch.cat([t, t.new_full((count,) + tuple(t.shape[1:]), value)])

    padded = type(plan)(rows_after(plan.index, extra_edges, 0),
                        rows_after(plan.force_index, extra_edges, num_slots - 1), num_slots, plan.num_nodes,
                        plan.incidences)
    return type(graph)(rows_after(graph.edges, extra_edges, 0), graph.element_edges, graph.edge_slots, num_edge_slots,
                       rows_after(graph.edge_counts, extra_edges, 0), padded,
                       rows_after(graph.slot_edge, extra_slots, 0))


def _tangent_members(group, graph) -> dict:
    """What a cut's edit of the cached tangent ``graph`` keeps besides the graph, made at the first
    cut: ``members [S_e, Ed]`` (each edge's (row * P + pair) ids by rank, -1 past its count) and
    ``used``, the first row of the pool of edge rows (past the last edge with members: a row an
    edit emptied is a zero row like the pool's, (0, 0) in node 0's sink slot)."""
    state = group.__dict__.get("_tangent_members")
    if state is not None and state["graph"] is graph:
        return state
    members = torch.full((graph.num_edge_slots, graph.edges.shape[0]), -1, dtype=torch.long)
    members[graph.edge_slots.reshape(-1).long(), graph.element_edges.reshape(-1).long()] = \
        torch.arange(graph.element_edges.numel())
    listed = torch.nonzero(graph.edge_counts).flatten()
    state = {"graph": graph, "members": members, "used": int(listed[-1]) + 1 if listed.numel() else 0}
    group.__dict__["_tangent_members"] = state
    return state


def _edit_tangent_graph(group, graph, neighbor, cut) -> Optional[torch.Tensor]:
    """The cached tangent ``graph`` on the CPU (and its ``neighbor [N_n, V]``, node order) edited
    in place for the cut ``(rows [M] ascending, old nodes [M, n], new nodes [M, n])`` (the group's
    elements already re-pointed; :func:`_tangent_members` keeps the edges' member lists).
    Where a pair of a row changes nodes, it leaves its edge (the members after it move down a
    rank, as a build from the new elements ranks them) and joins a new edge from the pool (a
    changed pair holds a new node, which had no edge: the members of a new edge are ranked in
    (row, pair) order, as a build ranks them); an edge left with no member leaves its nodes'
    lists and becomes a pool-like zero row (0, 0) in node 0's sink slot. The lists of the nodes
    those edges touch are written again: kept edges in their order, then the new ones. Per-edge
    sums are then a build's, bitwise; the node lists hold the same edges in another order (the
    products agree to rounding). Returns the nodes whose lists were written (int64), or None,
    having changed nothing, where there is no room (edge rows, slots a node, elements an edge) or
    a new edge's nodes already have one."""
    rows, old, new = cut
    state = _tangent_members(group, graph)
    plan = graph.plan
    n = old.shape[1]
    pairs = [(a, b) for a in range(n) for b in range(a + 1, n)]  # unique_edges' local pairs
    num_pairs = len(pairs)
    first, second = (torch.tensor([p[k] for p in pairs]) for k in (0, 1))
    old_low, old_high = torch.minimum(old[:, first], old[:, second]).long(), torch.maximum(old[:, first],
                                                                                            old[:, second]).long()
    new_low, new_high = torch.minimum(new[:, first], new[:, second]).long(), torch.maximum(new[:, first],
                                                                                            new[:, second]).long()
    moved = (old_low != new_low) | (old_high != new_high)  # [M, P]
    at_row, at_pair = torch.nonzero(moved, as_tuple=True)  # in (row, pair) order: rows ascend
    if at_row.numel() == 0:
        return torch.zeros(0, dtype=torch.long)
    flat = rows.long()[at_row] * num_pairs + at_pair  # the moved members, ascending
    element_edges, edge_slots = graph.element_edges.view(-1), graph.edge_slots.view(-1)
    members, index = state["members"], plan.index
    num_slots, num_nodes, sink = plan.num_slots, plan.num_nodes, plan.num_slots - 1

    # leave: the old edges' members that stay, compacted in rank order
    left = torch.unique(element_edges[flat].long())
    columns = members[:, left]  # [S_e, L]
    leaving = torch.zeros(element_edges.numel() + 1, dtype=torch.bool)
    leaving[flat] = True
    keep = (columns >= 0) & ~leaving[columns]  # (-1 reads the last flag: False)
    kept_rank = keep.long().cumsum(0) - 1
    left_counts = keep.sum(0)
    emptied = left[left_counts == 0]

    # join: the new edges, keyed (low, high), numbered from the pool in key order
    keys = new_low[at_row, at_pair] * num_nodes + new_high[at_row, at_pair]
    unique_keys, which, new_counts = torch.unique(keys, return_inverse=True, return_counts=True)
    used = state["used"]
    new_ids = used + torch.arange(unique_keys.numel())
    if used + unique_keys.numel() > index.shape[0] or int(new_counts.max()) > graph.num_edge_slots:
        return None
    ends = torch.stack([unique_keys // num_nodes, unique_keys % num_nodes], 1)  # [K, 2]
    order = torch.sort(which, stable=True).indices
    new_rank = torch.empty_like(which)
    new_rank[order] = torch.arange(which.numel()) - (new_counts.cumsum(0) - new_counts)[which[order]]

    # the lists of the nodes those edges touch: kept edges in slot order, then the new ones
    nodes = torch.unique(torch.cat([index[emptied].reshape(-1).long(), ends.reshape(-1)]))
    codes = graph.slot_edge[:, nodes].long()  # [N_n, A]
    counts = plan.incidences[nodes].long()
    listed = torch.arange(num_slots)[:, None] < counts[None, :]
    edge_of = torch.where(codes >= 0, codes, -codes - 1)
    # a new edge's nodes must have no edge between them yet (a node reused, not a fresh one)
    other = torch.where(codes >= 0, index[edge_of, 1].long(), index[edge_of, 0].long())
    column = torch.searchsorted(nodes, ends)  # [K, 2]
    for end in (0, 1):
        if bool((listed[:, column[:, end]] & (other[:, column[:, end]] == ends[:, 1 - end][None, :])).any()):
            return None
    stays = listed & ~torch.isin(edge_of, emptied)
    slot_of_kept = stays.long().cumsum(0) - 1
    kept_per_node = stays.sum(0)
    joined = torch.cat([column[:, 0], column[:, 1]])  # the new edges' ends: their nodes' columns
    joined_codes = torch.cat([new_ids, -new_ids - 1])
    num_new = unique_keys.numel()
    by_column = torch.argsort(joined * num_new + torch.arange(num_new).repeat(2))  # per node, in id order
    joined_per_node = torch.bincount(joined, minlength=nodes.numel())
    start = joined_per_node.cumsum(0) - joined_per_node
    joined_slot = torch.empty_like(joined)
    joined_slot[by_column] = (kept_per_node[joined[by_column]]
                              + torch.arange(joined.numel()) - start[joined[by_column]])
    new_incidences = kept_per_node + joined_per_node
    if int(new_incidences.max()) > num_slots - 1:  # node 0's last slot is the sink
        return None

    # every check passed: write the tables
    dtype = index.dtype
    members[:, left] = -1
    kr, kc = torch.nonzero(keep, as_tuple=True)
    members[kept_rank[kr, kc], left[kc]] = columns[kr, kc]
    edge_slots[columns[kr, kc]] = kept_rank[kr, kc].to(dtype)
    members[new_rank, new_ids[which]] = flat
    edge_slots[flat] = new_rank.to(dtype)
    element_edges[flat] = new_ids[which].to(dtype)
    graph.edge_counts[left] = left_counts.to(dtype)
    graph.edge_counts[new_ids] = new_counts.to(dtype)
    for table in (index, graph.edges):  # (the graph's edges and its plan's items: one copy each)
        table[new_ids] = ends.to(dtype)
        table[emptied] = 0
    plan.force_index[emptied] = sink
    new_codes = torch.zeros_like(codes)
    sr, sc = torch.nonzero(stays, as_tuple=True)
    new_codes[slot_of_kept[sr, sc], sc] = codes[sr, sc]
    new_codes[joined_slot, joined] = joined_codes
    now_listed = torch.arange(num_slots)[:, None] < new_incidences[None, :]
    lr, lc = torch.nonzero(now_listed, as_tuple=True)
    code = new_codes[lr, lc]
    edge = torch.where(code >= 0, code, -code - 1)
    plan.force_index[edge, (code < 0).long()] = lr.to(dtype)
    plan.incidences[nodes] = new_incidences.to(dtype)
    graph.slot_edge[:, nodes] = new_codes.to(dtype)
    state["used"] = used + unique_keys.numel()
    neighbor_columns = torch.zeros_like(codes)
    neighbor_columns[lr, lc] = torch.where(code >= 0, index[edge, 1].long(), index[edge, 0].long())

    neighbor.index_copy_(1, nodes, neighbor_columns.to(neighbor.dtype))
    return nodes


def _tangent_rows_changed(group, cached, neighbor, incidences, slot_edge, nodes: torch.Tensor) -> None:
    """The tangent graph's arrays by rows (``_native_by_rows_tangent``) written again from the
    node-order ones at the columns of ``nodes`` (those whose lists changed), the rows kept (a
    layout for speed: a node's row stays where its count changed), and the caches stamped again
    (captured CUDA graphs read this storage)."""
    rows_cache, by_rows_cache = cached
    if rows_cache is None or by_rows_cache is None:
        return
    rows, by_rows = rows_cache[2], by_rows_cache[2]
    tensors = (neighbor, incidences, slot_edge)
    if rows is None:  # node order: the by-rows arrays are the tensors themselves
        group.__dict__["_native_rows_tangent"] = _stamped((incidences,), *rows_cache[2:])
        group.__dict__["_native_by_rows_tangent"] = _stamped(tensors, *by_rows_cache[2:])
        return
    columns = _row_of(group, rows)[nodes].long()
    for old, new in zip(by_rows, tensors):
        dim = 1 if new.dim() >= 2 else 0
        old.index_copy_(dim, columns, new.index_select(dim, nodes))
    group.__dict__["_native_rows_tangent"] = _stamped((incidences,), *rows_cache[2:])
    group.__dict__["_native_by_rows_tangent"] = _stamped(tensors, *by_rows_cache[2:])


@torch.no_grad()
def tangent_topology_changed(group, cut=None) -> bool:
    """A stress-form group's elements changed in place (a cut): its tangent graph cached on the
    group (:func:`tangent_graph`), where there is one: on the CPU edited in place for the cut
    ``(rows, old nodes, new nodes)`` (host tensors; :func:`_edit_tangent_graph`); on an
    accelerator, or where the edit cannot be (``cut`` None, no room), built again from the
    elements and written into the storage of the one cached (every tensor by node and by rows,
    the rows too). Captured CUDA graphs read that storage. Its sizes (slots a node, edge rows,
    elements an edge: launch parameters) are kept. Where the new graph does not fit them (no room
    reserved, ``reserved_slots``, or more than it), the caches are dropped: built again at the
    next use. Returns whether they were dropped (solves captured over them must be captured
    again)."""
    names = ("_native_tangent_graph", "_native_rows_tangent", "_native_by_rows_tangent")
    cached = [group.__dict__.get(name) for name in names]
    if cached[0] is None:
        return False
    graph, neighbor, incidences = cached[0][2]
    # edited on the CPU; on an accelerator built again: there a build is a few dozen fast
    # launches, and the edit's hundred small host ops cost more (docs/topology-changes.md)
    edit = cut is not None and graph.edges.device.type == "cpu"
    nodes = _edit_tangent_graph(group, graph, neighbor, cut) if edit else None
    if nodes is not None:
        group.__dict__[names[0]] = _stamped((group.elements,), cached[0][2])
        _tangent_rows_changed(group, cached[1:], neighbor, incidences, graph.slot_edge, nodes)
        return False
    group.__dict__.pop("_tangent_members", None)  # (made again from the graph written below)
    fresh = _padded_edge_graph(_built_tangent_graph(group), graph.plan.num_slots, graph.edges.shape[0],
                               graph.num_edge_slots)
    if fresh is None:
        for name in names:
            group.__dict__.pop(name, None)
        return True
    plan, new_plan = graph.plan, fresh.plan
    for old, new in ((graph.edges, fresh.edges), (graph.element_edges, fresh.element_edges),
                     (graph.edge_slots, fresh.edge_slots), (graph.edge_counts, fresh.edge_counts),
                     (plan.index, new_plan.index), (plan.force_index, new_plan.force_index),
                     (plan.incidences, new_plan.incidences), (graph.slot_edge, fresh.slot_edge)):
        old.copy_(new)
    neighbor.copy_(_edge_neighbors(plan.index, plan.force_index, plan.num_slots, plan.num_nodes))
    group.__dict__[names[0]] = _stamped((group.elements,), cached[0][2])
    if cached[2] is not None and cached[1] is not None:  # by rows: the rows and arrays again, in place
        key, rows_before, by_rows_before = cached[1][3], cached[1][2], cached[2][2]
        for name in names[1:]:  # made again below from the graph written above
            del group.__dict__[name]
        tensors = (neighbor, incidences, graph.slot_edge)
        by_rows, rows = _by_rows(group, "tangent", incidences, tensors, key[1])
        if rows_before is not None:
            rows_before.copy_(rows)
            for old, new in zip(by_rows_before, by_rows):
                old.copy_(new)
            group.__dict__.pop("_row_of", None)
            group.__dict__[names[1]] = _stamped((incidences,), rows_before, key)
            group.__dict__[names[2]] = _stamped(tensors, by_rows_before, rows_before)
    return False


def tangent_serves(group, u: torch.Tensor, inputs=(), variants: KernelVariants = DEFAULT) -> bool:
    """Whether :func:`tangent_node_k` serves ``group`` at ``u``: ``variants.node_tangent``, a
    stress-form stvk or corotational group the ops support, the op compiled, and no gradient wanted
    through ``u``, ``inputs`` or the group's data (the node graph's products are not differentiable)."""
    return (variants.node_tangent and group.form == "stress" and group.model != "hooke"
            and hasattr(torch.ops.tensormass, "stress_tangent_node_k") and supports(group, u)
            and not wants_grad((u, *inputs, group.shape_vectors, group.measure, group.young, group.poisson)))


def tangent_node_k(group, u: torch.Tensor, rotations: Optional[torch.Tensor] = None,
                   out: Optional[torch.Tensor] = None, variants: KernelVariants = DEFAULT) -> torch.Tensor:
    """The force differential of a stress-form group at displacements ``u [V, d]`` as the slot
    tensors of its node graph (:func:`tangent_graph`): node_k ``[N_n, V, d, d]`` by the graph's
    rows, with -H_ij in the slot of (i -> j), H_ij = d f_i / d u_j summed over the elements of the
    edge, so that ``hooke_node_system`` over (neighbor, node_k, incidences, row_node) is
    :func:`system_matvec`'s product
    at u. ``rotations``: the corotational rotations of the linearisation (computed at u when None).
    Into ``out`` when it has the shape, dtype and device (the step's buffer: CUDA graphs replay
    into it), else a new tensor. The graph's rows: ``variants.node_graph_window``. Requires
    :func:`tangent_serves`."""
    graph, _, incidences, _, slot_edge = tangent_graph(group, variants.node_graph_window)
    plan = graph.plan
    d = u.shape[1]
    shape = (plan.num_slots, u.shape[0], d, d)
    if out is None or tuple(out.shape) != shape or out.dtype != u.dtype or out.device != u.device:
        out = u.new_zeros(shape)
    work_shape = (graph.num_edge_slots, graph.edges.shape[0], 12 if d == 3 else 4)  # blocks padded to 16 bytes
    work = group.__dict__.get("_native_tangent_work")
    if work is None or tuple(work.shape) != work_shape or work.dtype != u.dtype or work.device != u.device:
        work = group.__dict__["_native_tangent_work"] = u.new_empty(work_shape)
    index, _, _ = plan_indices(group.plan)
    m, vol, lam, mu, proj, model, _, rotations = stress_args(group, u, rotations)
    torch.ops.tensormass.stress_tangent_node_k(
        u.contiguous(), index, m, vol, lam, mu, proj, model, rotations, graph.element_edges, graph.edge_slots,
        graph.num_edge_slots, graph.edge_counts, slot_edge, incidences, out, work)
    return out


def _node_layout(group, layout: str, inputs, op: str) -> bool:
    """Whether the hooke tensor form's product runs over the node graph (op ``op``): layout
    "node", the op compiled, no gradient wanted through ``inputs`` or the edge tensors."""
    return (group.form == "tensor" and group.model == "hooke" and layout == "node"
            and hasattr(torch.ops.tensormass, op) and not wants_grad((*inputs, group.edge_k)))


def node_graph_of(group, variants: KernelVariants, inputs, op: str, node_k: Optional[torch.Tensor] = None):
    """(neighbor ``[N_n, V]``, node_k ``[N_n, V, d, d]``, incidences ``[V]``, row_node ``[V]`` or
    None: by rows, :func:`node_graph_rows` in windows of ``variants.node_graph_window``) of the
    group's CG product over the node graph (op ``op``) where it runs there: a stress-form group's
    tangent graph with ``node_k`` given (:func:`tangent_node_k` at the linearisation), or the hooke
    tensor form's own graph (``variants.hooke_matvec`` "node"); no gradient wanted through
    ``inputs``. None otherwise."""
    window = variants.node_graph_window
    if node_k is not None:
        if not hasattr(torch.ops.tensormass, op) or wants_grad((*inputs, node_k)):
            return None
        _, neighbor, incidences, rows, _ = tangent_graph(group, window)
        return neighbor, node_k, incidences, rows
    if not _node_layout(group, variants.hooke_matvec, inputs, op):
        return None
    return hooke_rows_graph(group, window)


def planes_serve(planes, x: torch.Tensor, node_stiffness: Optional[torch.Tensor]) -> bool:
    """Whether the right-hand side's kernels take these contact ``planes`` (a ``contact.Planes``
    or None) for positions ``x [V, d]``: none, or 3-D positions, a contact stiffness buffer and
    planes of x's dtype and device."""
    return planes is None or (x.shape[1] == 3 and node_stiffness is not None and planes.normals.dtype == x.dtype
                              and planes.normals.device == x.device)


def step_rhs_serves(group, inputs=(), variants: KernelVariants = DEFAULT) -> bool:
    """Whether :func:`step_rhs` computes ``group``'s step right-hand side in one op: the hooke
    tensor form over the node graph (``variants.hooke_matvec`` "node"), ``hooke_node_step_rhs``
    compiled, no gradient wanted through ``inputs``."""
    return _node_layout(group, variants.hooke_matvec, tuple(inputs), "hooke_node_step_rhs")


def step_rhs(group, x: torch.Tensor, v: torch.Tensor, rest: torch.Tensor, mass: torch.Tensor,
             external: torch.Tensor, planes, h: float, w_coef: float, rayleigh_mass: float, u: torch.Tensor,
             rhs: torch.Tensor, node_stiffness: Optional[torch.Tensor], variants: KernelVariants = DEFAULT) -> bool:
    """Implicit Euler's right-hand side for the hooke tensor form in one pass over the nodes
    (``hooke_node_step_rhs``): into ``rhs [V, d]``, ``h (f((x - rest) + w_coef v) + external +
    contact(x) - Kc(x) (w_coef v) - r_M mass v)``, with ``u = x - rest`` into ``u [V, d]`` and,
    with ``planes`` (``contact.Planes``, 3-D), the contact stiffness into ``node_stiffness
    [V, 3, 3]``. ``mass`` ``[V]``. Returns False, having done nothing, where the op does not serve
    the group (see :func:`step_rhs_serves`)."""
    if not step_rhs_serves(group, (x, v, rest, mass, external), variants):
        return False
    x, v, rest, mass, external = contiguous(x, v, rest, mass, external)
    graph = hooke_rows_graph(group, variants.node_graph_window)
    normals = offsets = stiffness = None
    if planes is not None:
        normals, offsets, stiffness = contiguous(planes.normals, planes.offsets, planes.stiffness)
    torch.ops.tensormass.hooke_node_step_rhs(x, v, rest, *graph, mass, external, normals,
                                             offsets, stiffness, float(h), float(w_coef), float(rayleigh_mass), u,
                                             rhs, node_stiffness)
    return True
