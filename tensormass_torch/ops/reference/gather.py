"""Kernel 2 of the paper: the per-node sum of partial forces, in tensor ops."""
from __future__ import annotations

from typing import Optional

import torch

from ...mesh.topology import sum_slots_in_order


def scatter_partial_forces(partial: torch.Tensor, index: torch.Tensor, force_index: torch.Tensor,
                           num_slots: int, num_nodes: int) -> torch.Tensor:
    """Kernel 1's write: ``PartialForce[ForceIndex[e, v], index[e, v]] = partial[e, v]``.

    partial ``[N, n, d]`` -> PartialForce ``[N_n, V, d]`` (unused slots hold zeros).
    """
    buffer = partial.new_zeros((num_slots, num_nodes, partial.shape[-1]))
    return buffer.index_put((force_index, index), partial)


def node_gather(partial: torch.Tensor, index: torch.Tensor, force_index: torch.Tensor, num_slots: int,
                num_nodes: int, node_term: Optional[torch.Tensor] = None) -> torch.Tensor:
    """TotalForce[i] = node_term[i] + sum over slots of PartialForce[slot, i].

    partial ``[N, n, d]``, index/force_index ``[N, n]``, node_term ``[V, d]`` or None -> ``[V, d]``.
    Deterministic: every slot is written once and the slot sum has a fixed order.
    """
    total = sum_slots_in_order(scatter_partial_forces(partial, index, force_index, num_slots, num_nodes))
    return total if node_term is None else total + node_term
