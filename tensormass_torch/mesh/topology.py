"""Topology precomputation for the paper's Algorithm 1.

The element kernel writes the partial force of element e on its local node v to
``PartialForce[ForceIndex[e, v], index[e, v]]``; the node kernel sums ``PartialForce[:, i]``.
``ForceIndex[e, v]`` is the rank of (e, v) among the incidences of node ``index[e, v]`` (in
element order), so every slot is written exactly once: no atomics, and the sum over slots has a
fixed order, hence bitwise-reproducible results.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch


def incidence_slots(targets: torch.Tensor, num_targets: int):
    """Rank of each item among the items with the same target, in item order.

    Args:
        targets: target id of each item ``[M]`` (int64, in ``[0, num_targets)``).
        num_targets: number of targets T.

    Returns:
        slots: ``[M]`` int64, slot of each item in its target's list.
        num_slots: max number of items of one target (the paper's ``N_n``), a Python int.
        counts: items per target ``[T]``.
    """
    counts = torch.bincount(targets, minlength=num_targets)
    # sorted on 32-bit keys where they fit, and the slots written a chunk of the order at a time:
    # the transient memory is the order and the slots, not five [M] int64 temporaries (this
    # runs on every element incidence of a mesh at construction, where the peak is)
    keys = targets.to(torch.int32) if num_targets <= torch.iinfo(torch.int32).max else targets
    order = torch.argsort(keys, stable=True)
    del keys
    starts = torch.cumsum(counts, 0) - counts  # first position of each target in sorted order
    slots = torch.empty_like(targets)
    for begin in range(0, targets.numel(), _SLOT_CHUNK):
        items = order[begin:begin + _SLOT_CHUNK]
        position = torch.arange(begin, begin + items.numel(), device=targets.device)
        slots[items] = (position - starts[targets[items]]).to(slots.dtype)
    num_slots = int(counts.max().item()) if targets.numel() else 0
    return slots, num_slots, counts


_SLOT_CHUNK = 1 << 22  # items a pass of incidence_slots (bounds its temporaries, 4M x 8 B each)


@dataclass
class GatherPlan:
    """How the partial forces of N items with n nodes each are summed onto V nodes.

    Attributes:
        index: item -> global node ids ``[N, n]`` (the paper's ``index``).
        force_index: slot of each (item, local node) in its node's list ``[N, n]`` (``ForceIndex``).
        num_slots: the paper's ``N_n``: max number of incidences of one node.
        num_nodes: V.
        incidences: number of incidences of each node ``[V]``.
    """

    index: torch.Tensor
    force_index: torch.Tensor
    num_slots: int
    num_nodes: int
    incidences: torch.Tensor

    @classmethod
    def build(cls, index: torch.Tensor, num_nodes: int) -> "GatherPlan":
        """Plan for items ``index [N, n]`` over ``num_nodes`` nodes."""
        flat = index.reshape(-1)
        slots, num_slots, counts = incidence_slots(flat, num_nodes)
        return cls(index, slots.view_as(index), num_slots, num_nodes, counts.to(index.dtype))

    def to(self, device) -> "GatherPlan":
        """The same plan with its index tensors on ``device``."""
        return GatherPlan(self.index.to(device), self.force_index.to(device), self.num_slots,
                          self.num_nodes, self.incidences.to(device))

    def partial_force_bytes(self, dim: int, itemsize: int) -> int:
        """Size of the padded PartialForce buffer ``[N_n, V, dim]`` in bytes."""
        return self.num_slots * self.num_nodes * dim * itemsize


def unique_edges(elements: torch.Tensor, num_nodes: int):
    """Unique undirected edges of elements and, for each local node pair, its edge id.

    Args:
        elements: ``[N, n]`` int64 or int32.
        num_nodes: V.

    Returns:
        edges: ``[Ed, 2]`` with ``edges[:, 0] < edges[:, 1]``, sorted lexicographically.
        pairs: local node pairs ``[P, 2]`` (a < b), P = n (n - 1) / 2.
        element_edges: edge id of each (element, pair) ``[N, P]``.
        edges and element_edges have the elements' dtype.
    """
    n = elements.shape[1]
    pairs = torch.tensor([(a, b) for a in range(n) for b in range(a + 1, n)], device=elements.device)
    first = elements[:, pairs[:, 0]]
    second = elements[:, pairs[:, 1]]
    # int64 keys whatever the elements' dtype: V^2 passes 2^31 from 46,341 nodes
    keys = torch.minimum(first, second).long().mul_(num_nodes).add_(torch.maximum(first, second))  # [N, P]
    del first, second  # (temporaries of [N, P] each: this runs at construction, where the peak is)
    shape = keys.shape
    unique_keys, inverse = torch.unique(keys.reshape(-1), sorted=True, return_inverse=True)
    del keys
    edges = torch.stack([unique_keys // num_nodes, unique_keys % num_nodes], dim=1).to(elements.dtype)
    return edges, pairs, inverse.view(shape).to(elements.dtype)


def padded_sum(values: torch.Tensor, targets: torch.Tensor, slots: torch.Tensor, num_slots: int,
               num_targets: int, out: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Deterministic scatter-sum, slot after slot: values ``[M, ...]``, targets ``[M]``, slots
    ``[M]`` (from :func:`incidence_slots`) -> sums ``[T, ...]``, each target's items added in
    slot order (``sum_slots_in_order`` of the padded ``[num_slots, T, ...]`` buffer, bitwise, as
    the kernels add them), so that even precomputation is bitwise reproducible on the GPU. The
    padded buffer itself is never made (num_slots times the result: the peak of a model's
    construction): a slot's items have distinct targets, so each slot is one gather and one write
    without collisions. Used for one-off assembly (masses, edge tensors).

    ``out``: sums ``[T, ...]`` to add onto in place (and return), or None (zeros). Summing the
    items in parts into one ``out``, the parts in item order, gives the sums of all of them at
    once, bitwise: a target's items are still added in slot order."""
    total = values.new_zeros((num_targets,) + tuple(values.shape[1:])) if out is None else out
    if num_slots == 0 or values.shape[0] == 0:
        return total
    order = torch.argsort(slots, stable=True)
    counts = torch.bincount(slots, minlength=num_slots).tolist()
    start = 0
    for count in counts:
        items = order[start:start + count]
        start += count
        at = targets[items]
        total.index_put_((at,), total[at] + values[items])
    return total


def sum_slots_in_order(buffer: torch.Tensor) -> torch.Tensor:
    """``buffer[0] + buffer[1] + ...`` over the first dimension ``[S, T, ...] -> [T, ...]``, added
    slot after slot, as the kernels do: each target's sum then has the same order wherever the
    target sits in the buffer (``buffer.sum(0)`` blocks its reduction by the buffer's size and
    alignment, so an object summed alone and inside a batch could differ in the last bit)."""
    if buffer.shape[0] == 0:
        return buffer.new_zeros(buffer.shape[1:])
    total = buffer[0].clone()
    for slot in buffer[1:]:
        total += slot
    return total


def add_at(out: torch.Tensor, index: torch.Tensor, values: torch.Tensor) -> torch.Tensor:
    """``out[index[i]] += values[i]`` for every i (``index [M]``, ``values [M, ...]``), in place and
    returned, summed in an order that does not change from run to run: on CUDA index_put_'s
    accumulation (it sorts by index, where index_add_ uses atomics); elsewhere index_add_ (the
    CPU's index_put_ accumulation splits the values among its threads, and its sums then change
    with their timing: two runs of one pile parted after 20 steps with 2 threads)."""
    if out.is_cuda:
        return out.index_put_((index,), values, accumulate=True)
    return out.index_add_(0, index, values)


def expand_ranges(first: torch.Tensor, counts: torch.Tensor):
    """The ranges ``first[i] .. first[i] + counts[i] - 1`` (``[N]`` each, int64) packed one after
    the other: (each item's range ``[T]``, the item ``[T]``), T = counts.sum()."""
    owner = torch.repeat_interleave(torch.arange(counts.numel(), device=counts.device), counts)
    start = torch.cumsum(counts, 0) - counts  # where each range's items begin in the packing
    return owner, first[owner] + torch.arange(owner.numel(), device=counts.device) - start[owner]


def node_element_lists(elements: torch.Tensor, num_nodes: int):
    """Node -> incident elements as CSR lists (the alternative to the padded layout).

    Args:
        elements: ``[N, n]``; num_nodes: V.

    Returns:
        ptr: ``[V + 1]`` offsets; incidences of node i are ``ptr[i]:ptr[i+1]``.
        element_ids: ``[N n]`` incident element of each entry, ascending per node.
        local_ids: ``[N n]`` the node's local index in that element.
    """
    n = elements.shape[1]
    flat = elements.reshape(-1)
    order = torch.argsort(flat, stable=True)
    counts = torch.bincount(flat, minlength=num_nodes)
    ptr = torch.cat([counts.new_zeros(1), torch.cumsum(counts, 0)])
    return ptr, order // n, order % n


@dataclass
class EdgeGraph:
    """The unique edges of a mesh's elements, for element data summed onto edges without atomics
    (the tangent on the node graph: kernel 1 per element writes each local pair's block to
    ``[edge_slots[e, p], element_edges[e, p]]``, kernel 2 per edge sums its slots in order,
    kernel 3 per slot of the node graph copies its edge's sum there, through ``slot_edge``).

    Attributes:
        edges: ``[Ed, 2]`` with ``edges[:, 0] < edges[:, 1]``, sorted (:func:`unique_edges`).
        element_edges: the edge of each element's local pair ``[N, P]`` (pairs a < b in the order
            of :func:`unique_edges`).
        edge_slots: the rank of (element, pair) among its edge's elements ``[N, P]``.
        num_edge_slots: the most elements of one edge.
        edge_counts: elements of each edge ``[Ed]``.
        plan: the gather plan over the edges (each node's slots: its edges in edge order).
        slot_edge: the edge in each slot of that node graph ``[N_n, V]``: g where the node is
            ``edges[g, 0]``, ``~g = -g - 1`` where it is ``edges[g, 1]``; 0 in unused slots.
    """

    edges: torch.Tensor
    element_edges: torch.Tensor
    edge_slots: torch.Tensor
    num_edge_slots: int
    edge_counts: torch.Tensor
    plan: GatherPlan
    slot_edge: torch.Tensor

    @classmethod
    def build(cls, elements: torch.Tensor, num_nodes: int) -> "EdgeGraph":
        """The edge graph of ``elements [N, n]`` over ``num_nodes`` nodes."""
        edges, _, element_edges = unique_edges(elements, num_nodes)
        slots, num_edge_slots, counts = incidence_slots(element_edges.reshape(-1), edges.shape[0])
        plan = GatherPlan.build(edges, num_nodes)
        edge_ids = torch.arange(edges.shape[0], device=edges.device)
        slot_edge = edges.new_zeros((plan.num_slots, num_nodes))
        slot_edge[plan.force_index[:, 0], edges[:, 0]] = edge_ids
        slot_edge[plan.force_index[:, 1], edges[:, 1]] = -edge_ids - 1
        return cls(edges, element_edges, slots.view_as(element_edges), num_edge_slots, counts, plan, slot_edge)


def element_pieces(elements: torch.Tensor, num_nodes: int) -> torch.Tensor:
    """The connected piece of each element ``[N]`` (int64, numbered 0, 1, ... in the order of the
    pieces' first elements): elements joined through shared nodes, as cuts and removals leave
    them. Label propagation with pointer jumping, on the elements' device.

    Args:
        elements: ``[N, n]`` node ids; num_nodes: V.
    """
    count = elements.shape[0]
    flat = elements.reshape(-1).long()
    labels = torch.arange(count, device=elements.device)
    while True:
        at_node = torch.full((num_nodes,), count, dtype=torch.long, device=elements.device)
        at_node.scatter_reduce_(0, flat, labels.repeat_interleave(elements.shape[1]), reduce="amin")
        updated = at_node[elements.long()].min(1).values
        updated = updated[updated]  # pointer jumping: each label points at its piece's smallest
        if torch.equal(updated, labels):
            break
        labels = updated
    return torch.unique(labels, return_inverse=True)[1]


def boundary_faces(tets: torch.Tensor) -> torch.Tensor:
    """Boundary triangles ``[F, 3]`` of a tet mesh ``tets [N, 4]``: the faces that belong to one tet only.

    Each face keeps the winding of its tet's outward normal for positively oriented tets.
    """
    tets = torch.as_tensor(tets).long()
    # The faces opposite nodes 0..3, wound so that their normals point away from that node.
    local = torch.tensor([[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]], device=tets.device)
    faces = tets[:, local].reshape(-1, 3)  # [4N, 3]
    keys = torch.sort(faces, dim=1).values
    _, inverse, counts = torch.unique(keys, dim=0, return_inverse=True, return_counts=True)
    return faces[counts[inverse] == 1]
