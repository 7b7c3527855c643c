"""The topology op family (``csrc/topology/``): element removal in place, the Tensor-Mass way.
Each op's pure-torch reference (the tests' oracle, and the path where the extension does not
serve the device), fake kernel and example, the incidence lists the ops read, and the
group-level calls.

Once elements are flagged removed, each target one of them touched is summed again from the
elements still on it, in the order of its incidence list (``incidence_table``: ``[S, T]`` model
element ids, -1 past the last, in the order the model was assembled in): what a model built from
the remaining elements holds, deterministic, with no atomics, no sort and no host
synchronisation; a target left with no element holds exactly 0.

    topology_refresh_nodes(elements, rows, node_slots, element_share, removed, mass!, node_elements!)
            the lumped masses (and element counts) of the nodes of the elements at ``rows``
    topology_refresh_hooke_edges(rest, elements, rows, element_edges, edge_slots, element_row,
        removed, measure, young, poisson, edge_k!)
            a hooke tensor-form group's edge tensors of the elements at ``rows``, each alive
            element's Cotin tensors formed again from the rest shape

Not differentiable (a removal is a change of topology; the tensor form holds no gradient).
"""
from __future__ import annotations

import torch

from ..mesh import geometry
from ..mesh.topology import incidence_slots, sum_slots_in_order
from . import library
from .library import OpDef
from .reference import tensor_form
from .reference.stress_form import lame

__all__ = ["incidence_table", "list_counts", "remove_from_lists", "append_slots", "upload", "refresh_nodes",
           "refresh_hooke_edges"]


def incidence_table(targets: torch.Tensor, items: torch.Tensor, num_targets: int) -> torch.Tensor:
    """The padded incidence lists ``[S, T]``: slot s of target t holds the s-th of the ``items``
    ``[M]`` (ids) whose target (``targets [M]``) is t, in item order; -1 past the last. Of
    ``items``' dtype and device."""
    slots, num_slots, _ = incidence_slots(targets, num_targets)
    table = torch.full((num_slots, num_targets), -1, dtype=items.dtype, device=items.device)
    table[slots, targets] = items
    return table


def list_counts(table: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """How many ids the lists of ``targets [K]`` hold in ``table [S, T]`` (-1 past the last):
    ``[K]`` int64."""
    return (table[:, targets] >= 0).sum(0)


@torch.no_grad()
def remove_from_lists(table: torch.Tensor, targets: torch.Tensor, items: torch.Tensor):
    """Take ``items[k]`` out of the list of ``targets[k]`` (``[R]`` each; every pair listed, each
    once) in ``table [S, T]`` in place, the lists kept in order and packed from slot 0 (what a
    table made without those items holds). Returns the lists touched: their targets ``[K]``
    (sorted) and columns after ``[S, K]``."""
    num_slots = table.shape[0]
    touched, column = torch.unique(targets, return_inverse=True)
    listed = table[:, touched]  # [S, K]
    slot = (listed[:, column] == items.to(table.dtype)[None, :]).int().argmax(0)  # where each item sits
    gone = torch.zeros_like(listed, dtype=torch.bool)
    gone[slot, column] = True
    keep = (listed >= 0) & ~gone
    position = torch.where(keep, torch.cumsum(keep, 0) - 1, num_slots)  # the rest to a spill row
    packed = torch.full((num_slots + 1, touched.numel()), -1, dtype=table.dtype, device=table.device)
    packed.scatter_(0, position, listed)
    packed = packed[:num_slots]
    table[:, touched] = packed
    return touched, packed


def append_slots(counts: torch.Tensor, targets: torch.Tensor) -> torch.Tensor:
    """The slots of items appended to the lists of ``targets [M]`` that hold ``counts`` items
    (``[M]``, each target's count, given per item) in the order given: ``counts + the item's
    rank among the items of its target`` ``[M]`` int64. Nothing is written (the caller checks the
    capacity first)."""
    order = torch.argsort(targets, stable=True)
    _, inverse, per_target = torch.unique(targets, return_inverse=True, return_counts=True)
    starts = torch.cumsum(per_target, 0) - per_target
    rank = torch.empty_like(order)
    rank[order] = torch.arange(targets.numel(), device=targets.device) - starts[inverse[order]]
    return counts.long() + rank


def upload(tensors: dict, device: torch.device) -> dict:
    """Host integer tensors (name -> tensor) on ``device``, each of its dtype and shape, with one
    copy: packed into one int64 buffer, pinned where the device is CUDA so that the copy is queued
    behind the device's work instead of waiting for it. On the CPU the tensors themselves. What a
    change planned on the host (a cut) sends to the device."""
    device = torch.device(device)
    if device.type == "cpu":
        return dict(tensors)
    names = list(tensors)
    sizes = [tensors[k].numel() for k in names]
    packed = torch.empty(sum(sizes), dtype=torch.int64, pin_memory=device.type == "cuda")
    if names:
        torch.cat([tensors[k].reshape(-1).to(torch.int64) for k in names], out=packed)
    on_device = packed.to(device, non_blocking=True)
    return {k: part.view(tensors[k].shape).to(tensors[k].dtype)
            for k, part in zip(names, on_device.split(sizes))}


# ---------------------------------------------------------------------------------------------
# References
# ---------------------------------------------------------------------------------------------


def _alive_slots(table: torch.Tensor, targets: torch.Tensor, removed: torch.Tensor):
    """The listed ids ``[S, T]`` of ``targets`` (clamped to 0 where empty) and whether each is an
    element not removed."""
    listed = table[:, targets].long()
    ids = listed.clamp(min=0)
    return ids, (listed >= 0) & ~removed[ids]


def _ref_topology_refresh_nodes(elements, rows, node_slots, element_share, removed, mass, node_elements):
    nodes = torch.unique(elements[rows.long()].reshape(-1).long())
    ids, alive = _alive_slots(node_slots, nodes, removed)
    shares = torch.where(alive, element_share[ids], torch.zeros((), dtype=mass.dtype, device=mass.device))
    mass[nodes] = sum_slots_in_order(shares)
    node_elements[nodes] = alive.sum(0).to(node_elements.dtype)


def _ref_topology_refresh_hooke_edges(rest, elements, rows, element_edges, edge_slots, element_row, removed,
                                      measure, young, poisson, edge_k):
    edges = torch.unique(element_edges[rows.long()].reshape(-1).long())
    ids, alive = _alive_slots(edge_slots, edges, removed)  # [S, T]
    element_of = element_row.long()[ids]  # the group row of each listed element
    listed = elements[element_of.reshape(-1)].long()  # [S T, n]
    n, dim = listed.shape[1], rest.shape[1]
    element_rest = rest[listed]
    m, _ = geometry.shape_vectors(element_rest)
    proj = geometry.tangent_projectors(element_rest) if geometry.needs_projector(n, dim) else None
    flat = element_of.reshape(-1)
    lam, mu = lame(young[flat], poisson[flat], plane_stress=n == 3)
    pairs = torch.tensor([(a, b) for a in range(n) for b in range(a + 1, n)], device=rest.device)
    blocks = tensor_form.oriented_blocks(tensor_form.element_stiffness(m, measure[flat], lam, mu, proj), listed,
                                         pairs)  # [S T, P, d, d]
    # the block of the pair on the listed edge
    on_edge = element_edges[flat].long() == edges.repeat(edge_slots.shape[0])[:, None]  # [S T, P]
    block = (blocks * on_edge[:, :, None, None]).sum(1).reshape(*ids.shape, dim, dim)
    block = torch.where(alive[..., None, None], block, torch.zeros((), dtype=block.dtype, device=block.device))
    edge_k[edges] = sum_slots_in_order(block)


# ---------------------------------------------------------------------------------------------
# Fake kernels (none: the ops return nothing) and examples
# ---------------------------------------------------------------------------------------------


def _example(name):
    def example(device, dtype):
        from ..mesh.topology import unique_edges

        ex = library.Example(device, dtype)
        elements = ex.elements
        num_elements = elements.shape[0]
        index = elements.dtype
        rows = torch.tensor([1], dtype=index, device=device)
        removed = torch.tensor([False, True], device=device)
        model_ids = torch.arange(num_elements, dtype=index, device=device)
        if name == "topology_refresh_nodes":
            node_slots = incidence_table(elements.reshape(-1).long(), model_ids.repeat_interleave(elements.shape[1]),
                                         ex.num_nodes)
            share = torch.tensor([0.5, 0.75], dtype=dtype, device=device)
            counts = torch.bincount(elements.reshape(-1).long(), minlength=ex.num_nodes).to(torch.int32)
            return (elements, rows, node_slots, share, removed, ex.mass.clone(), counts), {}
        _, _, element_edges = unique_edges(elements.long(), ex.num_nodes)
        edge_slots = incidence_table(element_edges.reshape(-1), model_ids.repeat_interleave(element_edges.shape[1]),
                                     ex.edges.shape[0])
        young = torch.full_like(ex.vol, 3.0)
        poisson = torch.full_like(ex.vol, 0.3)
        return (ex.rest, elements, rows, element_edges.to(index).contiguous(), edge_slots, model_ids, removed,
                ex.vol.abs().contiguous(), young, poisson, ex.edge_k.clone()), {}

    return example


OPS = (
    OpDef("topology_refresh_nodes", _ref_topology_refresh_nodes, None, differentiable=False, mutates=True,
          example=_example("topology_refresh_nodes")),
    OpDef("topology_refresh_hooke_edges", _ref_topology_refresh_hooke_edges, None, differentiable=False,
          mutates=True, example=_example("topology_refresh_hooke_edges")),
)
library.define(OPS, lambda: library.register(OPS))

# ---------------------------------------------------------------------------------------------
# Group-level calls
# ---------------------------------------------------------------------------------------------


@torch.no_grad()
def refresh_nodes(elements, rows, node_slots, element_share, removed, mass, node_elements, native: bool = True):
    """``topology_refresh_nodes`` through the op or its reference (see the module docstring)."""
    library.op_or_reference("topology_refresh_nodes", mass.device, native)(elements, rows, node_slots, element_share,
                                                                     removed, mass, node_elements)
    # the op writes through data pointers: caches keyed on _version (the solver's, built from the
    # masses) must see the change, as they see an in-place torch op's
    torch.autograd.graph.increment_version((mass, node_elements))


@torch.no_grad()
def refresh_hooke_edges(rest, elements, rows, element_edges, edge_slots, element_row, removed, measure, young, poisson,
                        edge_k, native: bool = True):
    """``topology_refresh_hooke_edges`` through the op or its reference (see the module docstring)."""
    library.op_or_reference("topology_refresh_hooke_edges", rest.device, native)(
        rest, elements, rows, element_edges, edge_slots, element_row, removed, measure, young, poisson, edge_k)
    # (written through data pointers: the caches keyed on edge_k's version, the stiffness diagonal
    # and its blocks among them, must see it)
    torch.autograd.graph.increment_version((edge_k,))
