"""The cutting op family (``csrc/cutting/``): :func:`mesh.cutting.cut <tensormass_torch.mesh.cutting.cut>`
in one native call on the host, and the edits a cut in place makes to the integer tables
(``TensorMass.repoint_elements``) in another.

The pure-torch cut costs hundreds of small tensor ops and several host synchronisations per call,
on whatever device the mesh is on; the op is one host algorithm (a pass over the elements, then
hash tables and union-find over the few elements near the blade), so it runs on the CPU only
(``OpDef.devices``): :func:`cut_mesh` copies the mesh and positions there and the results back.

    cutting_cut_mesh(elements, alive, x, blade_vertices, blade_triangles, slit)
        -> (elements, parents, first, second, slit)
            the cut of ``elements [N, n]`` (alive ones only) at positions ``x [V, 3]`` along the
            blade: the elements re-pointed, every node's parent ``[V_new]``, the element pairs
            whose face the blade crossed ``[C]`` each, and the pairs still joined ``[S', 2]``
    cut_mesh(elements, num_nodes, x, blade, removed, slit) -> mesh.cutting.CutResult
            the op on any device (results on the elements' device), or mesh.cutting.cut where
            the extension is not available; ``alive=`` restricts its host pass
    near_elements(elements, x, blade, slit) -> [N] bool
            where the positions are (a GPU): a superset of the elements a cut looks at, so that
            the host pass reads only those

The op computes what ``mesh.cutting.cut`` computes, bit for bit (its reference below is ``cut``'s
steps with the op's signature), with three differences in what is defined: with no face crossed it
returns the mesh unchanged (``first``, ``second`` empty) where ``cut`` raises (:func:`cut_mesh`
raises the same ``MeshError``); pairs that share no face are ignored (``cut`` passes them to
``split_nodes``, whose lookup of the parted faces can then take one of them for another pair: the
reference here leaves them out first); and int32 elements stay int32 (``split_nodes`` writes int64
ids into them and fails: the reference here splits an int64 copy).

A cut in place re-points a few elements of one group to new nodes; the host tables it edits (the
group's ``ElementGroup.cut_tables`` and the model's ``node_slots``) change only in the lists of the
nodes and edges those elements leave and join. In torch that is about 150 small ops; each op below
is one call that edits the tables in place and returns what the device needs (their schemas say
what, in which order):

    cutting_edit_element_tables(elements!, force_index!, incidences!, node_items!, node_slots!,
        rows, ids, nodes) -> (incidence_nodes, incidences, items, force_index, slot_nodes,
        node_slot_lists, both)
            a group whose plan's items are its elements (the stress forms, the stvk tensor form)
    cutting_edit_edge_tables(..., edges!, edge_slots!, element_edges!, rows, ids, nodes,
        element_row, removed, edge_rows_used) -> (status, refresh_rows, dead, graph_edges, ...)
            a hooke tensor-form group, whose items are edges: the new edges from the pool of edge
            rows, the room checked first (``status``: nothing written where there is none)
    edit_cut_tables(tables, node_slots, rows, ids, nodes, ...) -> (results by name, edge rows used)
            the op where the extension serves the CPU, else its reference; raises CapacityError
            where the plan has no room, grows the edge pool where it is short

Their references are the Python that planned cuts before them (bit for bit: same tables, same
results), the fallback where the extension is not built.

Not differentiable (a change of topology).
"""
from __future__ import annotations

from typing import Callable, Optional, Tuple

import torch

from .. import _backend
from ..errors import CapacityError, MeshError
from ..mesh import cutting as mesh_cutting
from ..mesh.topology import sum_slots_in_order
from . import library, solve, topology
from .library import OpDef

__all__ = ["cut_mesh", "near_elements", "edit_cut_tables", "face_table", "cut_on_device", "ELEMENT_RESULTS",
           "EDGE_RESULTS"]

NAME = "cutting_cut_mesh"
ELEMENT_TABLES = "cutting_edit_element_tables"
EDGE_TABLES = "cutting_edit_edge_tables"
CROSS_FACES = "cutting_cross_faces"
SPLIT_STARS = "cutting_split_stars"
REPOINT_STARS = "cutting_repoint_stars"
MOVE_LISTS = "cutting_move_lists"
COPY_ROWS = "cutting_copy_rows"
COUNT_NEW_NODES = "cutting_count_new_nodes"
CLOSE_CUT = "cutting_close_cut"
#: The results of the table edits by name, in the ops' order.
ELEMENT_RESULTS = ("incidence_nodes", "incidences", "items", "force_index", "slot_nodes", "node_slot_lists", "both")
EDGE_RESULTS = ("status", "refresh_rows", "dead", "graph_edges", "incidence_nodes", "incidences", "items",
                "force_index", "slot_edges", "edge_slot_lists", "edge_rows", "edge_values", "element_edges",
                "slot_nodes", "node_slot_lists", "both")


# ---------------------------------------------------------------------------------------------
# Reference, fake kernel, example
# ---------------------------------------------------------------------------------------------


def _ref_cutting_cut_mesh(elements, alive, x, blade_vertices, blade_triangles, slit):
    """``mesh.cutting.cut``'s steps in the op's signature (see the module docstring)."""
    num_nodes = x.shape[0]
    ids = torch.nonzero(alive).flatten()
    blade = mesh_cutting.Blade(blade_vertices, blade_triangles)
    first, second, _ = mesh_cutting.cut_faces(elements[ids], x, blade)
    first, second = ids[first], ids[second]
    pairs = torch.cat([torch.stack([first, second], 1), slit[alive[slit].all(1)]])
    parents = torch.arange(num_nodes, device=elements.device)
    out = elements.clone()
    if first.numel():
        parting = pairs[mesh_cutting.still_joined(elements, pairs)]  # the pairs that share a face
        # split_nodes writes int64 ids into the elements: it takes int64 ones
        live, parents = mesh_cutting.split_nodes(elements[ids].long(), num_nodes,
                                                 torch.searchsorted(ids, parting[:, 0].contiguous()),
                                                 torch.searchsorted(ids, parting[:, 1].contiguous()))
        out[ids] = live.to(elements.dtype)
    return out, parents, first, second, pairs[mesh_cutting.still_joined(out, pairs)]


def _fake_cutting_cut_mesh(elements, alive, x, blade_vertices, blade_triangles, slit):
    ctx = torch.library.get_ctx()
    num_nodes, num_crossed, num_slit = ctx.new_dynamic_size(), ctx.new_dynamic_size(), ctx.new_dynamic_size()
    index = dict(dtype=torch.int64, device=elements.device)
    return (elements.new_empty(elements.shape), torch.empty((num_nodes,), **index),
            torch.empty((num_crossed,), **index), torch.empty((num_crossed,), **index),
            torch.empty((num_slit, 2), **index))


def _example(device, dtype):
    """A 4 x 2 x 1 beam of tetrahedra (int32) with one element removed, a slit row from an earlier
    cut, and a blade that cuts half of the section at x = 0.51 (a slit of its own)."""
    from ..mesh.beams import beam_mesh

    mesh = beam_mesh(4, 2, 1, size=(1.0, 0.5, 0.25), dtype=torch.float64)
    elements = mesh.elements.to(device=device, dtype=torch.int32)
    alive = torch.ones(elements.shape[0], dtype=torch.bool, device=device)
    alive[-1] = False
    blade = mesh_cutting.Blade.swept((0.51, -1, -1), (0.51, 0.2, -1), (0.51, -1, 2), (0.51, 0.2, 2))
    first, second, _ = mesh_cutting.interior_faces(mesh.elements)
    slit = torch.stack([first, second], 1)[:1].to(device)
    x = mesh.vertices.to(device=device, dtype=dtype)
    return (elements, alive, x, blade.vertices.to(x), blade.triangles.to(device), slit), {}


# ---------------------------------------------------------------------------------------------
# The cut's table edits: references (the Python TensorMass and ElementGroup ran), fake kernels,
# examples
# ---------------------------------------------------------------------------------------------


def _pairs(n: int) -> torch.Tensor:
    """The local node pairs a < b of an element of ``n`` nodes ``[P, 2]``, in the order of
    ``element_edges``' columns."""
    return torch.tensor([(a, b) for a in range(n) for b in range(a + 1, n)])


def _edit_node_lists(node_slots, ids, old, nodes, changed):
    """The model's lists ``node_slots [S', V]`` edited: the element of each changed entry
    (``changed [M, n]`` of the rows' nodes ``old`` and ``nodes`` ``[M, n]``; ``ids [M]`` their
    model ids) leaves its old node's list (packed in order) and joins its new node's after the
    elements there. Returns the columns changed (sorted) and their lists now ``[S', C]``."""
    moved = ids[:, None].expand_as(changed)[changed].to(node_slots.dtype)
    touched, _ = topology.remove_from_lists(node_slots, old[changed].long(), moved)
    targets = nodes[changed].long()
    slots = topology.append_slots(topology.list_counts(node_slots, targets), targets)
    node_slots[slots, targets] = moved
    columns = torch.unique(torch.cat([touched, targets]))
    return columns, node_slots[:, columns]


def _edit_plan_lists(node_items, force_index, incidences, gone_items, gone_nodes, new_items, new_nodes):
    """A gather plan's lists ``node_items [S, V]`` edited in place: items ``gone_items [R]`` (``row
    * w + a``) leave their nodes ``gone_nodes [R]`` (each list packed in order), ``new_items [A]``
    join ``new_nodes [A]`` after the items there (in the order given); ``force_index`` and
    ``incidences`` follow. Returns the nodes whose ``incidences`` changed and the (flat) items
    whose ``force_index`` did."""
    force_index = force_index.view(-1)
    nodes, items = [new_nodes], [new_items]
    if gone_items.numel():
        touched, lists = topology.remove_from_lists(node_items, gone_nodes, gone_items)
        used = lists >= 0
        slot_of = torch.arange(lists.shape[0])[:, None].expand_as(lists)
        force_index[lists[used].long()] = slot_of[used].to(force_index.dtype)
        incidences[touched] = used.sum(0).to(incidences.dtype)
        nodes.append(touched)
        items.append(lists[used].long())
    if new_items.numel():
        slots = topology.append_slots(incidences[new_nodes], new_nodes)
        node_items[slots, new_nodes] = new_items.to(node_items.dtype)
        force_index[new_items.long()] = slots.to(force_index.dtype)
        incidences.index_add_(0, new_nodes, torch.ones_like(new_nodes, dtype=incidences.dtype))
    return torch.unique(torch.cat(nodes)), torch.unique(torch.cat(items).long())


def _ref_cutting_edit_element_tables(elements, force_index, incidences, node_items, node_slots, rows, ids, nodes):
    """Each moved incidence leaves its node's lists (packed in order) and joins the new node's (in
    element order): the slots of a group built from the new elements."""
    n = elements.shape[1]
    old = elements[rows]
    changed = old != nodes
    slot_nodes, node_slot_lists = _edit_node_lists(node_slots, ids, old, nodes, changed)
    items = (rows.long()[:, None] * n + torch.arange(n))[changed]
    elements[rows] = nodes
    changed_nodes, changed_items = _edit_plan_lists(node_items, force_index, incidences, items, old[changed].long(),
                                                    items, nodes[changed].long())
    return (changed_nodes, incidences[changed_nodes], changed_items, force_index.view(-1)[changed_items], slot_nodes,
            node_slot_lists, torch.cat([old, nodes]))


def _unedited(status, elements, node_slots, edge_slots, pairs):
    """The edge op's results where it writes nothing: the status, and empty tensors."""
    index, wide = dict(dtype=elements.dtype), dict(dtype=torch.int64)
    empty = torch.empty((0,), **index)
    return (status, empty, torch.empty((0,), **wide), empty.clone(), torch.empty((0,), **wide), empty.clone(),
            torch.empty((0,), **wide), empty.clone(), torch.empty((0,), **wide),
            torch.empty((edge_slots.shape[0], 0), **index), torch.empty((0,), **wide), torch.empty((0, 2), **index),
            torch.empty((0, pairs), **index), torch.empty((0,), **wide), torch.empty((node_slots.shape[0], 0), **index),
            torch.empty((0, elements.shape[1]), **index))


def _ref_cutting_edit_edge_tables(elements, force_index, incidences, node_items, node_slots, edges, edge_slots,
                                  element_edges, rows, ids, nodes, element_row, removed, edge_rows_used):
    """An edge that gains a new node is a new edge row (its elements listed in id order, its slots
    appended at both ends); an old edge keeps the elements that stay, and one left with none
    leaves its nodes' lists (its row stays, a zero edge (0, 0) in node 0's sink slot, the plan's
    last). First the room: nothing is written where the plan or the pool has too little."""
    num_nodes = incidences.shape[0]
    old = elements[rows]
    changed = old != nodes
    pairs = _pairs(elements.shape[1])
    moved = changed[:, pairs[:, 0]] | changed[:, pairs[:, 1]]  # [M, P]: the pair's edge changes
    a, b = nodes[:, pairs[:, 0]][moved].long(), nodes[:, pairs[:, 1]][moved].long()
    keys = torch.minimum(a, b) * num_nodes + torch.maximum(a, b)
    unique_keys, edge_of = torch.unique(keys, return_inverse=True)
    new_edges = torch.stack([unique_keys // num_nodes, unique_keys % num_nodes], 1)  # [E', 2]
    # the old edges the moved pairs leave, and those of them no alive element is left on
    old_edges = element_edges[rows]
    left, moving = torch.unique(old_edges[moved].long(), return_counts=True)
    listed = edge_slots[:, left].long()
    alive = ((listed >= 0) & ~removed[listed.clamp(min=0)]).sum(0)
    dead = left[alive == moving]
    change = torch.zeros_like(incidences)
    change.index_add_(0, new_edges.reshape(-1), torch.ones_like(new_edges.reshape(-1), dtype=change.dtype))
    dead_ends = edges[dead].reshape(-1).long()
    change.index_add_(0, dead_ends, torch.full_like(dead_ends, -1, dtype=change.dtype))
    need = int((incidences + change).max()) if num_nodes else 0
    # the new edges take the pool's first rows
    first_new, count, sink = int(edge_rows_used), new_edges.shape[0], node_items.shape[0] - 1
    status = torch.tensor([need, count, 0])
    if need > sink or first_new + count > edges.shape[0]:
        return _unedited(status, elements, node_slots, edge_slots, pairs.shape[0])
    slot_nodes, node_slot_lists = _edit_node_lists(node_slots, ids, old, nodes, changed)
    moved_ids = ids.to(edge_slots.dtype)[:, None].expand_as(moved)[moved]
    left, _ = topology.remove_from_lists(edge_slots, old_edges[moved].long(), moved_ids)
    new_rows = torch.arange(first_new, first_new + count)
    # each new edge's elements in id order (ids ascending, an element once per edge)
    lists = edge_slots[:, first_new:first_new + count]
    lists[topology.append_slots(torch.zeros_like(edge_of), edge_of), edge_of] = moved_ids
    edges[first_new:first_new + count] = new_edges.to(edges.dtype)
    rows_edges = old_edges.clone()
    rows_edges[moved] = (edge_of + first_new).to(old_edges.dtype)
    element_edges[rows] = rows_edges
    dead_items = (dead[:, None] * 2 + torch.arange(2)).reshape(-1)
    new_items = torch.arange(2 * first_new, 2 * (first_new + count))
    changed_nodes, changed_items = _edit_plan_lists(node_items, force_index, incidences, dead_items,
                                                    edges[dead].reshape(-1).long(), new_items, new_edges.reshape(-1))
    edges[dead] = 0  # a zero edge (0, 0) in node 0's sink slot: its partial forces, 0, never read
    force_index[dead] = sink
    elements[rows] = nodes
    # the rows whose edges are summed again: the cut's, and for each old edge the moved pairs
    # left that keeps an alive element, one such element (its row names the edge)
    listed = edge_slots[:, left].long()
    alive = (listed >= 0) & ~removed[listed.clamp(min=0)]
    witness = listed.gather(0, alive.int().argmax(0, keepdim=True))[0][alive.any(0)]
    refresh_rows = torch.unique(torch.cat([rows.long(), element_row[witness].long()])).to(rows.dtype)
    changed_items = torch.unique(torch.cat([changed_items, dead_items]))
    # the edges the node graphs take again: those whose slots moved (new and emptied ones
    # included) and those summed again
    graph_edges = torch.unique(torch.cat([changed_items // 2, element_edges[refresh_rows.long()].reshape(-1).long()]))
    slot_edges = torch.cat([left, new_rows])
    edge_rows = torch.cat([new_rows, dead.long()])
    status[2] = 1
    return (status, refresh_rows, dead, graph_edges.to(rows.dtype), changed_nodes, incidences[changed_nodes],
            changed_items, force_index.view(-1)[changed_items], slot_edges, edge_slots[:, slot_edges], edge_rows,
            edges[edge_rows], rows_edges, slot_nodes, node_slot_lists, torch.cat([old, nodes]))


def _fake_cutting_edit_element_tables(elements, force_index, incidences, node_items, node_slots, rows, ids, nodes):
    ctx = torch.library.get_ctx()
    num_changed_nodes, num_items, num_columns = (ctx.new_dynamic_size() for _ in range(3))
    index, wide = dict(dtype=elements.dtype, device=elements.device), dict(dtype=torch.int64, device=elements.device)
    return (torch.empty((num_changed_nodes,), **wide), torch.empty((num_changed_nodes,), **index),
            torch.empty((num_items,), **wide), torch.empty((num_items,), **index), torch.empty((num_columns,), **wide),
            torch.empty((node_slots.shape[0], num_columns), **index),
            torch.empty((2 * rows.shape[0], elements.shape[1]), **index))


def _fake_cutting_edit_edge_tables(elements, force_index, incidences, node_items, node_slots, edges, edge_slots,
                                   element_edges, rows, ids, nodes, element_row, removed, edge_rows_used):
    ctx = torch.library.get_ctx()
    refresh, dead, graph, changed_nodes, items, edge_columns, edge_rows, edited_rows, columns = (
        ctx.new_dynamic_size() for _ in range(9))
    index, wide = dict(dtype=elements.dtype, device=elements.device), dict(dtype=torch.int64, device=elements.device)
    return (torch.empty((3,), **wide), torch.empty((refresh,), **index), torch.empty((dead,), **wide),
            torch.empty((graph,), **index), torch.empty((changed_nodes,), **wide),
            torch.empty((changed_nodes,), **index), torch.empty((items,), **wide), torch.empty((items,), **index),
            torch.empty((edge_columns,), **wide), torch.empty((edge_slots.shape[0], edge_columns), **index),
            torch.empty((edge_rows,), **wide), torch.empty((edge_rows, 2), **index),
            torch.empty((edited_rows, element_edges.shape[1]), **index), torch.empty((columns,), **wide),
            torch.empty((node_slots.shape[0], columns), **index),
            torch.empty((2 * edited_rows, elements.shape[1]), **index))


def _table_example(model_name: str):
    """A 3 x 2 x 1 beam of tetrahedra (a ``model_name`` model, its tables int32) with spare rows
    and room for cuts, one element removed, and the cut of a blade at x = 0.51 through half of
    its section: the tables the model plans that cut on and the elements it re-points."""

    def example(device, dtype):
        from ..mesh.beams import beam_mesh
        from ..physics.materials import Material
        from ..physics.tensor_mass import TensorMass

        mesh = beam_mesh(3, 2, 1, size=(1.0, 0.5, 0.25), dtype=torch.float64)
        spare = 12
        rest = torch.cat([mesh.vertices, mesh.vertices[:1].expand(spare, 3)])
        material = Material(young=1e3, poisson=0.3, density=1.0, model=model_name)
        model = TensorMass.packed(rest, [(mesh.elements, material, "tet")], form="tensor")
        model.reserve_slots(spare_nodes=spare)
        model.remove_elements([3])
        blade = mesh_cutting.Blade.swept((0.51, -1, -1), (0.51, 0.3, -1), (0.51, -1, 2), (0.51, 0.3, 2))
        removed = model.removed_host()
        result = mesh_cutting.cut(mesh.elements, mesh.num_vertices, mesh.vertices, blade, removed)
        ids = torch.nonzero((result.elements != mesh.elements).any(1)).flatten()
        group, model_tables = model.groups[0], model._cut_tables()
        tables = group.cut_tables()

        def index(t):
            return t.to(device=device, dtype=torch.int32).contiguous()

        head = [index(tables[k]) for k in ("elements", "force_index", "incidences", "node_items")]
        head.append(index(model_tables["node_slots"]))
        rows, nodes = index(model_tables["element_row"][ids]), index(result.elements[ids])
        if model_name != "hooke":
            return (*head, rows, ids.to(device), nodes), {}
        edge_tables = [index(tables[k]) for k in ("edges", "edge_slots", "element_edges")]
        return (*head, *edge_tables, rows, ids.to(device), nodes, index(model_tables["element_row"]),
                removed.to(device), group.edge_rows_used), {}

    return example


# ---------------------------------------------------------------------------------------------
# The cut on the device: references, examples (the ops return nothing: no fake kernels)
# ---------------------------------------------------------------------------------------------


def _ref_cutting_cross_faces(x, elements, face_elements, alive, blade_vertices, blade_triangles, parted, crossed):
    first, second = face_elements[:, 0].long(), face_elements[:, 1].long()
    a, b = elements[first].long(), elements[second].long()
    shared = mesh_cutting.still_joined(elements.long(), face_elements.long())
    p, q = x[a].mean(1), x[b].mean(1)
    low, high = blade_vertices.amin(0), blade_vertices.amax(0)
    close = ((torch.minimum(p, q) <= high) & (torch.maximum(p, q) >= low)).all(1)
    tested = alive[first] & alive[second] & shared & close
    hit = torch.zeros_like(tested)
    if bool(tested.any()):
        blade = mesh_cutting.Blade(blade_vertices, blade_triangles)
        hit[tested] = mesh_cutting._segments_cross(p[tested], q[tested], blade)
    crossed.copy_(hit)
    parted |= hit


def _ref_cutting_split_stars(elements, node_slots, alive, element_faces, face_elements, parted, crossed, recheck,
                             group, new_count, on_cut):
    num_slots, num_nodes = node_slots.shape
    n = elements.shape[1]
    device = elements.device
    ids = node_slots.long()  # [S, V]
    element = ids.clamp(min=0)
    rows = elements[element].long()  # [S, V, n]
    holds = rows == torch.arange(num_nodes, device=device)[None, :, None]
    local = holds.int().argmax(-1)  # [S, V]
    member = (ids >= 0) & alive[element] & holds.any(-1)
    faces = element_faces[element].long()  # [S, V, n]: the face opposite each local node
    ends = face_elements[faces.clamp(min=0)].long()  # [S, V, n, 2]
    other = torch.where(ends[..., 0] == element[..., None], ends[..., 1], ends[..., 0])
    # the other element's slot in the node's star: [S, V, n, S]
    same = (other[..., None] == ids.t()[None, :, None, :]) & member.t()[None, :, None, :]
    found, slot = same.any(-1), same.int().argmax(-1)
    other_rows = elements[other].long()  # [S, V, n, n]
    shared = (rows[:, :, None, :, None] == other_rows[:, :, :, None, :]).sum((-1, -2)) == n - 1
    link = (member[..., None] & (faces >= 0) & (torch.arange(n, device=device) != local[..., None]) & found
            & shared)
    cut = link & parted[faces.clamp(min=0)]
    joined = link & ~cut
    examined = (crossed | recheck)[faces.clamp(min=0)]
    marked = (cut & examined).any(-1).any(0)  # [V]
    recheck.zero_()
    big = torch.iinfo(torch.int64).max
    labels = torch.where(member, element, torch.full_like(element, big))
    s_idx, v_idx, _ = torch.nonzero(joined, as_tuple=True)
    s_other = slot[joined]
    while True:  # each joined pair takes its smaller label, until nothing changes
        low = torch.minimum(labels[s_idx, v_idx], labels[s_other, v_idx])
        updated = labels.clone()
        flat = updated.reshape(-1)
        flat.scatter_reduce_(0, s_idx * num_nodes + v_idx, low, reduce="amin")
        flat.scatter_reduce_(0, s_other * num_nodes + v_idx, low, reduce="amin")
        if torch.equal(updated, labels):
            break
        labels = updated
    least = member & (labels == element)  # the entry of its group's smallest element
    rank = ((labels[None, :, :] < labels[:, None, :]) & least[None, :, :]).sum(1)  # [S, V]
    groups = least.sum(0)
    group.copy_(torch.where(member & marked[None, :], rank * n + local, torch.full_like(rank, -1)).to(group.dtype))
    new_count.copy_(torch.where(marked & (groups > 1), groups - 1, torch.zeros_like(groups)).to(new_count.dtype))
    on_cut.copy_(marked.to(on_cut.dtype))


def _ref_cutting_repoint_stars(node_slots, group, new_count, offset, limits, elements, parents):
    n = elements.shape[1]
    total = int(offset[-1]) + int(new_count[-1])
    first_new, room = int(limits[0]), int(limits[1])
    if total > room or first_new + total > parents.shape[0]:
        return
    ids, g = node_slots.long(), group.long()
    s, i = torch.nonzero((ids >= 0) & (g >= n), as_tuple=True)
    elements[ids[s, i], g[s, i] % n] = (first_new + offset[i] + g[s, i] // n - 1).to(elements.dtype)
    nodes = torch.repeat_interleave(torch.arange(node_slots.shape[1], device=elements.device), new_count.long())
    parents[first_new:first_new + total] = nodes


def _ref_cutting_move_lists(elements, group, new_count, offset, limits, parents, element_share, alive, node_slots,
                            mass, node_elements, touched):
    n = elements.shape[1]
    total = int(offset[-1]) + int(new_count[-1])
    first_new, room = int(limits[0]), int(limits[1])
    if total > room or first_new + total > parents.shape[0]:
        return
    for i in torch.nonzero(new_count).flatten().tolist():
        column = node_slots[:, i].clone()
        listed = column >= 0
        ids, ranks = column[listed], group[:, i][listed].long()
        ranks = torch.where(ranks < 0, torch.zeros_like(ranks), ranks // n)
        touched[elements[ids.long()].reshape(-1).long()] = 1
        base = first_new + int(offset[i])
        for r in range(int(new_count[i]) + 1):
            node = i if r == 0 else base + r - 1
            mine = ids[ranks == r]
            node_slots[:, node] = -1
            node_slots[:mine.shape[0], node] = mine
            living = mine.long()[alive[mine.long()]]
            mass[node] = sum_slots_in_order(element_share[living][:, None])[0]
            node_elements[node] = living.shape[0]


def _ref_cutting_copy_rows(rows, parents, max_rows, values):
    first, count = int(rows[0]), int(rows[1])
    if count:
        nodes = torch.arange(first, first + count, device=values.device)
        values[nodes] = values[parents[nodes]]


def _copy_rows_example(device, dtype):
    """Nodes 5 and 6 of 8, copies of 1 and 3: their rows of a [8, 3] float tensor."""
    parents = torch.arange(8, device=device)
    parents[5], parents[6] = 1, 3
    values = torch.arange(24, dtype=dtype, device=device).view(8, 3)
    return (torch.tensor([5, 2], device=device), parents, 3, values), {}


def _ref_cutting_count_new_nodes(ends, limits, rows, status):
    total = ends[-1]
    fits = total <= limits[1]
    rows.copy_(torch.stack([limits[0], torch.where(fits, total, torch.zeros_like(total))]))
    status.copy_(torch.where(fits, status, torch.ones_like(status)))


def _count_new_nodes_example(device, dtype):
    """7 new nodes numbered (after nodes holding 2, 0, 1, 4) against a room of 6: they do not fit."""
    ends = torch.tensor([0, 2, 2, 3, 7], device=device)
    return (ends, torch.tensor([20, 6], device=device), torch.zeros(2, dtype=torch.int64, device=device),
            torch.zeros(1, dtype=torch.int32, device=device)), {}


def _ref_cutting_close_cut(rows, incidences, chunk_start, chunk_slots, limits, status, outcome):
    if chunk_start.numel() > 1:  # (no chunk: nothing to check)
        over = solve.most_chunk_slots(incidences, chunk_start) > chunk_slots
        status.copy_(torch.where(over, torch.ones_like(status), status))
    limits.copy_(torch.stack([limits[0] + rows[1], limits[1] - rows[1]]))
    outcome.copy_(torch.cat([limits[:1], status.long()]))


def _close_cut_example(device, dtype):
    """3 new nodes taken from a room of 10; chunks of 3 and 2 nodes holding 9 and 11 slots, given 10."""
    incidences = torch.tensor([3, 4, 2, 5, 6], dtype=torch.int32, device=device)
    return (torch.tensor([20, 3], device=device), incidences, torch.tensor([0, 3, 5], device=device), 10,
            torch.tensor([20, 10], device=device), torch.zeros(1, dtype=torch.int32, device=device),
            torch.zeros(2, dtype=torch.int64, device=device)), {}


@torch.no_grad()
def face_table(elements: torch.Tensor, slit: Optional[torch.Tensor] = None):
    """The interior faces of ``elements [N, n]`` (tetrahedra or membrane triangles), for the cut on
    the device: ``face_elements [F, 2]`` (the two elements of each face, first < second, faces in
    the order of their sorted node ids), ``element_faces [N, n]`` (the face opposite each local
    node, -1 on the boundary), both of the elements' index type, and ``parted [F]`` bool: the
    faces of the element pairs ``slit [S, 2]`` (an earlier cut's slit), False elsewhere. Made once
    per mesh (it is what the cut reads; it is never resized). A face held by more than two elements
    (a mesh that is not a manifold) pairs its holders in order, as the reference does."""
    n = elements.shape[1]
    device = elements.device
    first, second, _ = mesh_cutting.shared_face_incidences(elements)  # incidences (element n + k)
    num_faces = first.shape[0]
    element_faces = torch.full((elements.shape[0] * n,), -1, dtype=elements.dtype, device=device)
    faces = torch.arange(num_faces, dtype=elements.dtype, device=device)
    element_faces[second] = faces
    element_faces[first] = faces
    face_elements = torch.stack([first // n, second // n], 1).to(elements.dtype)
    parted = torch.zeros(num_faces, dtype=torch.bool, device=device)
    if slit is not None and slit.numel():
        pairs = slit.to(device=device, dtype=torch.int64)
        pairs = torch.stack([pairs.amin(1), pairs.amax(1)], 1)
        keys_faces = face_elements[:, 0].long() * elements.shape[0] + face_elements[:, 1].long()
        parted = torch.isin(keys_faces, pairs[:, 0] * elements.shape[0] + pairs[:, 1])
    return face_elements.contiguous(), element_faces.view(-1, n).contiguous(), parted


@torch.no_grad()
def cut_on_device(x: torch.Tensor, elements: torch.Tensor, node_slots: torch.Tensor, alive: torch.Tensor,
                  faces: Tuple[torch.Tensor, torch.Tensor, torch.Tensor], blade_vertices: torch.Tensor,
                  blade_triangles: torch.Tensor, limits: torch.Tensor, parents: torch.Tensor,
                  scratch: Optional[dict] = None, *, native: bool = True) -> Tuple[torch.Tensor, torch.Tensor]:
    """The cut of ``elements [N, n]`` (written in place) at ``x [V', 3]`` along a blade
    (``blade_vertices [B, 3]``, ``blade_triangles [T, 3]`` int64, on x's device), on whatever
    device they are: the three passes (``cutting_cross_faces``, ``cutting_split_stars``,
    ``cutting_repoint_stars``) and a prefix sum, with no host synchronisation (a CUDA graph can
    hold it where ``scratch`` is given). ``faces``: :func:`face_table`'s ``(face_elements,
    element_faces, parted)``, parted updated in place; ``node_slots [S, V']``: each node's elements
    (ids into elements, in any order); ``limits [2]`` int64: the first new node's id and how many
    new nodes fit; ``parents [P]`` int64: each new node's parent written there. ``scratch``: a
    dict that keeps the passes' buffers between calls (made on the first; ``offset``, the new
    nodes' numbering, is left there for ``cutting_move_lists``, and ``ends [V + 1]``: 0, then the
    inclusive prefix sum of the new nodes, for ``cutting_count_new_nodes``). The first call with a
    scratch examines the nodes of every parted face; later ones only those of the faces their blade
    crosses (no other node's star changed). A cut that did not fit leaves its faces parted but its
    nodes unsplit: cut again with a new scratch.

    Returns ``(crossed [F] bool, total [] int64)``: the faces this blade crossed, and how many
    nodes the cut adds (made only where they fit: total <= limits[1]; else nothing changes but
    ``parted``, which the caller restores, or keeps where it cuts again with more room)."""
    face_elements, element_faces, parted = faces
    scratch = {} if scratch is None else scratch
    if scratch.get("group") is None or scratch["group"].shape != node_slots.shape:
        scratch["group"] = torch.empty(node_slots.shape, dtype=torch.int32, device=x.device)
        scratch["new_count"] = torch.empty(node_slots.shape[1], dtype=torch.int32, device=x.device)
        scratch["on_cut"] = torch.empty(node_slots.shape[1], dtype=torch.uint8, device=x.device)
        scratch["crossed"] = torch.empty(parted.shape, dtype=torch.bool, device=x.device)
        scratch["ends"] = torch.zeros(node_slots.shape[1] + 1, dtype=torch.int64, device=x.device)
        scratch["offset"] = scratch["ends"][:-1]
    if scratch.get("recheck") is None:  # the first cut examines the nodes of every parted face
        scratch["recheck"] = parted.clone()
    group, new_count, crossed = scratch["group"], scratch["new_count"], scratch["crossed"]
    library.op_or_reference(CROSS_FACES, x.device, native)(x, elements, face_elements, alive, blade_vertices,
                                                             blade_triangles, parted, crossed)
    library.op_or_reference(SPLIT_STARS, x.device, native)(elements, node_slots, alive, element_faces, face_elements,
                                                           parted, crossed, scratch["recheck"], group, new_count,
                                                           scratch["on_cut"])
    ends = scratch["ends"]  # 0, then the inclusive prefix sum: offset is its first V entries
    torch.cumsum(new_count, 0, dtype=torch.int64, out=ends[1:])
    library.op_or_reference(REPOINT_STARS, x.device, native)(node_slots, group, new_count, scratch["offset"], limits,
                                                           elements, parents)
    return crossed, ends[-1]


def _device_example(name: str):
    """A 4 x 2 x 1 beam of tetrahedra (int32) with room for 24 new nodes, one element removed, an
    earlier slit, and the cut of a blade at x = 0.51 through half of its section: the arguments of
    the pass ``name`` (the earlier passes made by their references)."""

    def example(device, dtype):
        from ..mesh.beams import beam_mesh

        mesh = beam_mesh(4, 2, 1, size=(1.0, 0.5, 0.25), dtype=torch.float64)
        spare = 24
        nodes = mesh.num_vertices + spare
        elements = mesh.elements.to(device=device, dtype=torch.int32)
        alive = torch.ones(elements.shape[0], dtype=torch.bool, device=device)
        alive[-1] = False
        first, second, _ = mesh_cutting.interior_faces(mesh.elements)
        face_elements, element_faces, parted = face_table(elements, torch.stack([first, second], 1)[:1])
        slit = parted.clone()
        x = torch.cat([mesh.vertices, mesh.vertices[:1].expand(spare, 3)]).to(device=device, dtype=dtype)
        blade = mesh_cutting.Blade.swept((0.51, -1, -1), (0.51, 0.2, -1), (0.51, -1, 2), (0.51, 0.2, 2))
        blade_vertices, blade_triangles = blade.vertices.to(x), blade.triangles.to(device)
        crossed = torch.zeros_like(parted)
        if name == "cutting_cross_faces":
            return (x, elements, face_elements, alive, blade_vertices, blade_triangles, parted, crossed), {}
        _ref_cutting_cross_faces(x, elements, face_elements, alive, blade_vertices, blade_triangles, parted, crossed)
        node_slots = topology.incidence_table(elements.reshape(-1).long(), torch.arange(
            elements.shape[0], dtype=torch.int32, device=device).repeat_interleave(elements.shape[1]), nodes)
        group = torch.zeros(node_slots.shape, dtype=torch.int32, device=device)
        new_count = torch.zeros(nodes, dtype=torch.int32, device=device)
        on_cut = torch.zeros(nodes, dtype=torch.uint8, device=device)
        recheck = slit.clone()  # the earlier slit: its nodes examined again
        if name == "cutting_split_stars":
            return (elements, node_slots, alive, element_faces, face_elements, parted, crossed, recheck, group,
                    new_count, on_cut), {}
        _ref_cutting_split_stars(elements, node_slots, alive, element_faces, face_elements, parted, crossed, recheck,
                                 group, new_count, on_cut)
        offset = torch.cumsum(new_count.long(), 0) - new_count.long()
        limits = torch.tensor([mesh.num_vertices, spare], dtype=torch.int64, device=device)
        parents = torch.arange(nodes, dtype=torch.int64, device=device)
        if name == "cutting_repoint_stars":
            return (node_slots, group, new_count, offset, limits, elements.clone(), parents), {}
        _ref_cutting_repoint_stars(node_slots, group, new_count, offset, limits, elements, parents)
        share = torch.linspace(0.5, 1.5, elements.shape[0], dtype=dtype, device=device)
        mass = torch.zeros(nodes, dtype=dtype, device=device)
        counts = torch.zeros(nodes, dtype=torch.int32, device=device)
        touched = torch.zeros(nodes, dtype=torch.uint8, device=device)
        return (elements, group, new_count, offset, limits, parents, share, alive, node_slots, mass, counts,
                touched), {}

    return example


OPS = (OpDef(NAME, _ref_cutting_cut_mesh, _fake_cutting_cut_mesh, differentiable=False, example=_example,
             devices=("cpu",)),
       OpDef(ELEMENT_TABLES, _ref_cutting_edit_element_tables, _fake_cutting_edit_element_tables,
             differentiable=False, mutates=True, example=_table_example("stvk"), devices=("cpu",)),
       OpDef(EDGE_TABLES, _ref_cutting_edit_edge_tables, _fake_cutting_edit_edge_tables, differentiable=False,
             mutates=True, example=_table_example("hooke"), devices=("cpu",)),
       OpDef(CROSS_FACES, _ref_cutting_cross_faces, None, differentiable=False, mutates=True,
             example=_device_example(CROSS_FACES)),
       OpDef(SPLIT_STARS, _ref_cutting_split_stars, None, differentiable=False, mutates=True,
             example=_device_example(SPLIT_STARS)),
       OpDef(REPOINT_STARS, _ref_cutting_repoint_stars, None, differentiable=False, mutates=True,
             example=_device_example(REPOINT_STARS)),
       OpDef(MOVE_LISTS, _ref_cutting_move_lists, None, differentiable=False, mutates=True,
             example=_device_example(MOVE_LISTS)),
       OpDef(COPY_ROWS, _ref_cutting_copy_rows, None, differentiable=False, mutates=True,
             example=_copy_rows_example),
       OpDef(COUNT_NEW_NODES, _ref_cutting_count_new_nodes, None, differentiable=False, mutates=True,
             example=_count_new_nodes_example),
       OpDef(CLOSE_CUT, _ref_cutting_close_cut, None, differentiable=False, mutates=True,
             example=_close_cut_example))
library.define(OPS, lambda: library.register(OPS))


# ---------------------------------------------------------------------------------------------
# The call
# ---------------------------------------------------------------------------------------------


def _native_available(name: str = NAME) -> bool:
    """Whether the op ``name`` can run: the extension serves the CPU (where the op runs, whatever
    the mesh's device) and has it."""
    return (_backend.use_extension("cpu") and library.ensure_registered()
            and hasattr(torch.ops.tensormass, name))


#: The relative margin by which :func:`near_elements` grows its bounds: far above the few units in
#: the last place by which its centroids and reach, summed in another order than the op's (on a
#: GPU), can differ from the op's; it only adds elements.
NEAR_MARGIN = 1e-5


@torch.no_grad()
def near_elements(elements: torch.Tensor, x: torch.Tensor, blade: mesh_cutting.Blade,
                  slit: Optional[torch.Tensor] = None) -> torch.Tensor:
    """``[N]`` bool, where the positions are: a superset of the elements a cut of ``elements
    [N, n]`` at ``x [V, 3]`` along ``blade`` looks at, with ``slit [S, 2]`` (element pairs, or
    None) the earlier cuts' slit. An element outside it is as far from the cut as a removed one:
    :func:`cut_mesh` with ``alive=`` this mask (and the elements not removed) returns the cut
    of the whole mesh, while its host pass reads no position of the others. Made of a few tensor
    ops over every element, for a mesh on a GPU: there they cost microseconds where the host
    pass over every element costs milliseconds.

    What it holds, and why that is enough (``cutting_cut_mesh``'s reasoning, ``csrc/cutting/
    ops.h``): with R_k the largest distance along axis k from an element's centroid to one of its
    nodes, every element whose centroid lies in the blade's box grown by 2 R (the elements whose
    faces the blade can cross, and the stars of those faces' nodes), with a margin
    (``NEAR_MARGIN``); and every element holding a node of a slit pair's elements (the stars of
    the slit's nodes, which the cut splits again). The op run on such a subset measures a reach
    no larger than R over it, and its own bounds then keep what this one keeps."""
    nodes = x[elements.long()]  # [N, n, 3]
    centroids = nodes.mean(1)
    reach = (nodes - centroids[:, None]).abs().amax((0, 1)) if elements.shape[0] else centroids.new_zeros(3)
    vertices = blade.vertices.to(x)
    low, high = vertices.amin(0), vertices.amax(0)
    grow = 2 * reach * (1 + NEAR_MARGIN) + NEAR_MARGIN * (low.abs() + high.abs() + reach)
    near = ((centroids >= low - grow) & (centroids <= high + grow)).all(1)
    if slit is not None and slit.numel():
        held = torch.zeros(x.shape[0], dtype=torch.bool, device=x.device)
        held[elements[slit.to(elements.device).reshape(-1)].reshape(-1).long()] = True
        near |= held[elements.long()].any(1)
    return near


@torch.no_grad()
def cut_mesh(elements: torch.Tensor, num_nodes: int, x: torch.Tensor, blade: mesh_cutting.Blade,
             removed: Optional[torch.Tensor] = None, slit: Optional[torch.Tensor] = None, *,
             alive: Optional[torch.Tensor] = None, native: bool = True) -> mesh_cutting.CutResult:
    """:func:`mesh.cutting.cut <tensormass_torch.mesh.cutting.cut>` (same arguments, result and
    errors) through ``cutting_cut_mesh`` where the extension is available (and ``native``): the
    inputs are copied to the CPU, the results back to ``elements.device``. Else ``cut`` itself.

    ``alive``: ``[N]`` bool (host), the elements to look at, in place of ``~removed``: those not
    removed and :func:`near_elements` (computed where the positions are), so that the host pass
    skips the others; the result is the same.

    Raises:
        MeshError: ``x`` is not ``[num_nodes, 3]``; the blade crosses no interior face.
    """
    if x.shape != (num_nodes, 3):
        raise MeshError(f"positions must be [{num_nodes}, 3] to cut along a 3-D blade, got {tuple(x.shape)}")
    if alive is not None and alive.shape != (elements.shape[0],):
        raise MeshError(f"alive must be [{elements.shape[0]}] (one flag per element), got {tuple(alive.shape)}")
    if not (native and x.dtype in (torch.float32, torch.float64) and _native_available()):
        if alive is not None:
            removed = ~alive.to(device=elements.device, dtype=torch.bool)
        return mesh_cutting.cut(elements, num_nodes, x, blade, removed, slit)
    device, host = elements.device, torch.device("cpu")
    index = elements.dtype if elements.dtype in (torch.int32, torch.int64) else torch.int64
    host_elements = elements.to(device=host, dtype=index).contiguous()
    if alive is not None:
        alive = alive.to(device=host, dtype=torch.bool)
    elif removed is None:
        alive = torch.ones(elements.shape[0], dtype=torch.bool)
    else:
        alive = ~removed.to(device=host, dtype=torch.bool)
    if slit is None or slit.numel() == 0:
        slit = torch.zeros((0, 2), dtype=torch.int64)
    out, parents, first, second, joined = library.op(NAME)(
        host_elements, alive.contiguous(), x.detach().to(host).contiguous(),
        blade.vertices.to(device=host, dtype=x.dtype).contiguous(), blade.triangles.to(host, torch.int64).contiguous(),
        slit.to(device=host, dtype=torch.int64).contiguous())
    if first.numel() == 0:
        raise MeshError("the blade crosses no interior face of the body: nothing to cut")
    return mesh_cutting.CutResult(out.to(device=device, dtype=elements.dtype), parents.to(device), first.to(device),
                                  second.to(device), num_nodes, joined.to(device))


def _table_op(name: str, tables, native: bool):
    """The op ``name`` where it can take these index ``tables`` (the extension serves the CPU and
    has it; every table on the CPU, contiguous, of the first one's int32 or int64 type), and
    whether it is the op; else its reference."""
    index = tables[0].dtype
    if (native and index in (torch.int32, torch.int64) and _native_available(name)
            and all(t.device.type == "cpu" and t.dtype == index and t.is_contiguous() for t in tables)):
        return library.op(name), True
    return library.REGISTRY[name].reference, False


@torch.no_grad()
def edit_cut_tables(tables: dict, node_slots: torch.Tensor, rows: torch.Tensor, ids: torch.Tensor,
                    nodes: torch.Tensor, element_row: Optional[torch.Tensor] = None,
                    removed: Optional[torch.Tensor] = None, edge_rows_used: int = 0,
                    grow_pool: Optional[Callable[[int], None]] = None, *, native: bool = True) -> Tuple[dict, int]:
    """The host tables of one group (``tables``: ``ElementGroup.cut_tables``, edited in place,
    entries replaced where the edge pool grows) and the model's lists ``node_slots [S', V]``
    edited for the elements at ``rows [M]`` (the group's rows of the model ids ``ids [M]``,
    int64, ascending) re-pointed to ``nodes [M, n]``, through ``cutting_edit_element_tables``
    (or ``cutting_edit_edge_tables`` where the tables have ``edges``: a hooke tensor-form group;
    ``element_row``, ``removed``: the model's, on the host; ``edge_rows_used``: the group's edge
    rows in use, the pool past them) where the extension serves the CPU and takes the tables,
    else its reference. Where the pool holds fewer rows than the cut's new edges, ``grow_pool(rows)``
    grows ``tables``' edges, force_index and edge_slots to at least that many rows first.

    Returns:
        the ops' results by name (``ELEMENT_RESULTS`` or ``EDGE_RESULTS`` but ``status``), and the
        edge rows in use after the cut (``edge_rows_used`` itself for an element plan).

    Raises:
        CapacityError: a node would have more edges than the plan has slots but its sink (nothing
            changed).
    """
    nodes = nodes.to(tables["elements"].dtype).contiguous()
    ids = ids.to("cpu", torch.int64).contiguous()
    written = [tables[k] for k in ("elements", "force_index", "incidences", "node_items")] + [node_slots]
    if "edges" not in tables:
        call, is_native = _table_op(ELEMENT_TABLES, written + [rows, nodes], native)
        results = dict(zip(ELEMENT_RESULTS, call(*written, rows, ids, nodes)))
        if is_native:  # the op writes through data pointers: caches keyed on _version must see it
            torch.autograd.graph.increment_version(written)
        return results, edge_rows_used
    while True:
        written = ([tables[k] for k in ("elements", "force_index", "incidences", "node_items")] + [node_slots]
                   + [tables[k] for k in ("edges", "edge_slots", "element_edges")])
        call, is_native = _table_op(EDGE_TABLES, written + [rows, nodes, element_row], native)
        results = dict(zip(EDGE_RESULTS, call(*written, rows, ids, nodes, element_row, removed.contiguous(),
                                              int(edge_rows_used))))
        need, count, edited = results.pop("status").tolist()
        if edited:
            break
        room = tables["node_items"].shape[0] - 1
        if need > room:
            raise CapacityError(f"a node would have {need} edges; the plan has room for {room}")
        if grow_pool is None:
            raise ValueError(f"the edge pool has {tables['edges'].shape[0] - edge_rows_used} rows for the cut's "
                             f"{count} new edges: pass grow_pool")
        grow_pool(edge_rows_used + count)
        if tables["edges"].shape[0] < edge_rows_used + count:
            raise RuntimeError(f"grow_pool left {tables['edges'].shape[0]} edge rows; the cut needs "
                               f"{edge_rows_used + count}")
    if is_native:
        torch.autograd.graph.increment_version(written)
    return results, edge_rows_used + count
