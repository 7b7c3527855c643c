"""The gather op family (``csrc/gather/``): kernel 2, the per-node sums of PartialForce, alone
and with the implicit-Euler system's epilogue (the CG matvec), and that matvec ending in the CG
step length. Each op's pure-torch reference, fake kernel and autograd, and the group-level
wrapper of ``node_gather``.

    gather_partial(PartialForce [N_n, V, d], incidences [V], node_term?) -> [V, d]
    node_gather(partial [N, n, d], index, force_index, num_slots, incidences, node_term?) -> [V, d]
    gather_system(PartialForce, incidences, p, mass, free?, c_M, c_K, node_stiffness?)
        -> (Ap = free (c_M mass p - c_K (K p - node_stiffness p)) [V, d], p . Ap per node [V])
    gather_system_alpha(<gather_system's inputs>, ap!, chunk plan, rr, status!, alpha!, scratch!,
        counter!) -> ()   Ap into ap, then the step length per object as cg_alpha sets it

Autograd: the gathers' transposes, exactly; the system ops are solver kernels (no gradient).
"""
from __future__ import annotations

from typing import Optional

import torch

from ..mesh.topology import sum_slots_in_order
from . import cg as cg_family
from . import library
from .library import OpDef, gather, plan_indices, slot_mask

__all__ = ["node_gather", "system_epilogue"]


def _ref_gather_partial(partial, incidences, node_term):
    total = sum_slots_in_order(torch.where(slot_mask(partial.shape[0], incidences), partial, partial.new_zeros(())))
    return total if node_term is None else total + node_term


def _ref_node_gather(partial, index, force_index, num_slots, incidences, node_term):
    return gather(partial, index, force_index, num_slots, incidences, node_term)


def system_epilogue(kp, p, mass, free, c_mass, c_stiff, node_stiffness=None):
    """Ap = free (c_mass mass p - c_stiff (kp - node_stiffness p)) ``[V, d]``, p . Ap per node ``[V]``."""
    if node_stiffness is not None:
        kp = kp - torch.einsum("vab,vb->va", node_stiffness, p)
    ap = (c_mass * mass.unsqueeze(-1)) * p - c_stiff * kp
    if free is not None:
        ap = ap * free.unsqueeze(-1)
    return ap, (p * ap).sum(-1)


def _ref_gather_system(partial, incidences, p, mass, free, c_mass, c_stiff, node_stiffness=None):
    """Kernel 2 + the implicit-Euler epilogue (see ``system_epilogue``)."""
    return system_epilogue(_ref_gather_partial(partial, incidences, None), p, mass, free, c_mass, c_stiff,
                            node_stiffness)


def _ref_gather_system_alpha(partial, incidences, p, mass, free, c_mass, c_stiff, node_stiffness, ap, chunk_start,
                             chunk_object, object_chunk, rr, status, alpha, scratch, counter):
    product, p_dot_ap = _ref_gather_system(partial, incidences, p, mass, free, c_mass, c_stiff, node_stiffness)
    ap.copy_(product)
    cg_family._ref_cg_alpha(p_dot_ap, chunk_start, chunk_object, object_chunk, rr, status, alpha, scratch, counter)


def _fake_gather_partial(partial, incidences, node_term):
    return partial.new_empty((partial.shape[1], partial.shape[2]))


def _fake_node_gather(partial, index, force_index, num_slots, incidences, node_term):
    return partial.new_empty((incidences.shape[0], partial.shape[2]))


def _fake_gather_system(partial, incidences, p, mass, free, c_mass, c_stiff, node_stiffness=None):
    return (partial.new_empty((partial.shape[1], partial.shape[2])), partial.new_empty((partial.shape[1],)))


def _gather_partial_gradients(inputs, g, needs):
    partial, incidences = inputs[0], inputs[1]
    fast = {}
    if needs[0]:
        fast[0] = torch.where(slot_mask(partial.shape[0], incidences), g.unsqueeze(0), g.new_zeros(()))
    if needs[2]:
        fast[2] = g
    return fast


def _node_gather_gradients(inputs, g, needs):
    fast = {}
    if needs[0]:
        fast[0] = g[inputs[1]]
    if needs[5]:
        fast[5] = g
    return fast


def _example(name):
    def example(device, dtype):
        ex = library.Example(device, dtype)
        gen = torch.Generator().manual_seed(5)
        compact = torch.randn((ex.elements.shape[0], ex.elements.shape[1], ex.dim), generator=gen)
        compact = compact.to(device=device, dtype=dtype)
        partial = library.scatter(compact, ex.elements.long(), ex.force_index.long(), ex.num_slots, ex.num_nodes)
        system = (partial, ex.incidences, ex.du, ex.mass, ex.free, 1.5, 0.25)
        if name == "gather_partial":
            return (partial, ex.incidences, None), {}
        if name == "node_gather":
            return (compact, ex.elements, ex.force_index, ex.num_slots, ex.incidences, ex.u), {}
        if name == "gather_system":
            return system, {}
        alpha_args, _ = cg_family.OPS[0].example(device, dtype)  # cg_alpha's: [5] nodes, two objects
        (_, *plan, rr, status, alpha, scratch, counter) = alpha_args
        return (*system, None, torch.zeros_like(ex.du), *plan, rr, status, alpha, scratch, counter), {}

    return example


OPS = (
    OpDef("gather_partial", _ref_gather_partial, _fake_gather_partial, _gather_partial_gradients,
          example=_example("gather_partial")),
    OpDef("node_gather", _ref_node_gather, _fake_node_gather, _node_gather_gradients, example=_example("node_gather")),
    OpDef("gather_system", _ref_gather_system, _fake_gather_system, differentiable=False,
          example=_example("gather_system")),
    OpDef("gather_system_alpha", _ref_gather_system_alpha, None, differentiable=False, mutates=True,
          example=_example("gather_system_alpha"), scratch=("scratch", "counter")),
)
library.define(OPS, lambda: library.register(OPS))


def node_gather(partial: torch.Tensor, plan, node_term: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Kernel 2 on compact partial forces ``[N, n, d]`` -> ``[V, d]`` (+ node_term)."""
    index, force_index, incidences = plan_indices(plan)
    if node_term is not None:
        node_term = node_term.contiguous()
    return torch.ops.tensormass.node_gather(partial.contiguous(), index, force_index, plan.num_slots,
                                            incidences, node_term)
