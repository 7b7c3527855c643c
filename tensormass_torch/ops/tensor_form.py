"""The tensor-form op family (``csrc/tensor_form/``): kernel 1 of the Tensor-Mass tensor form,
hooke over edges (``edge_k [Ed, d, d]``, linear: dforces(du) = forces(du)) and stvk over
elements (Picinbono's tensors B, C, D), at element level, into PartialForce, and fused with
kernel 2. Each op's pure-torch reference, fake kernel and autograd.

    tensor_hooke_element_forces          [Ed, 2, d]
    tensor_hooke_partial_forces          PartialForce [N_n, V, d]
    tensor_hooke_forces                  [V, d]
    tensor_stvk_element_forces / _dforces, tensor_stvk_partial_forces / _dforces,
    tensor_stvk_forces / _dforces        as the stress form's

Autograd: the fused forces and dforces compute their u (du) gradient with the ops (the stiffness
is symmetric); every other gradient (the tensors, u in the element-level and padded ops and in
stvk dforces) is the reference's vjp.
"""
from __future__ import annotations

from . import library
from .library import OpDef, fake_element, fake_element_d, fake_nodes, fake_partial, fake_partial_d, gather, op, scatter
from .reference import tensor_form

__all__ = ["stvk_tensors"]

# ---------------------------------------------------------------------------------------------
# References
# ---------------------------------------------------------------------------------------------


def _ref_tensor_hooke_element_forces(u, edges, edge_k):
    return tensor_form.hooke_edge_partial_forces(u, edges, edge_k)


def _ref_tensor_hooke_partial_forces(u, edges, force_index, num_slots, edge_k):
    return scatter(tensor_form.hooke_edge_partial_forces(u, edges, edge_k), edges, force_index, num_slots,
                    u.shape[0])


def _ref_tensor_hooke_forces(u, edges, force_index, num_slots, incidences, edge_k):
    return gather(tensor_form.hooke_edge_partial_forces(u, edges, edge_k), edges, force_index, num_slots,
                   incidences, None)


def _ref_tensor_stvk_element_forces(u, elements, b, c, d):
    return tensor_form.stvk_forces(u[elements], b, c, d)


def _ref_tensor_stvk_element_dforces(u, du, elements, b, c, d):
    return tensor_form.stvk_dforces(u[elements], du[elements], b, c, d)


def _ref_tensor_stvk_partial_forces(u, elements, force_index, num_slots, b, c, d):
    return scatter(_ref_tensor_stvk_element_forces(u, elements, b, c, d), elements, force_index, num_slots,
                    u.shape[0])


def _ref_tensor_stvk_partial_dforces(u, du, elements, force_index, num_slots, b, c, d):
    return scatter(_ref_tensor_stvk_element_dforces(u, du, elements, b, c, d), elements, force_index,
                    num_slots, u.shape[0])


def _ref_tensor_stvk_forces(u, elements, force_index, num_slots, incidences, b, c, d):
    return gather(_ref_tensor_stvk_element_forces(u, elements, b, c, d), elements, force_index, num_slots,
                   incidences)


def _ref_tensor_stvk_dforces(u, du, elements, force_index, num_slots, incidences, b, c, d):
    return gather(_ref_tensor_stvk_element_dforces(u, du, elements, b, c, d), elements, force_index, num_slots,
                   incidences)


# ---------------------------------------------------------------------------------------------
# Fake kernels, autograd, examples
# ---------------------------------------------------------------------------------------------


def _fake_tensor_hooke_element(u, edges, edge_k):
    return u.new_empty((edges.shape[0], 2, u.shape[1]))


def _fast_gradients(name):
    """The u (du) gradient of the fused ops: K(u) g (K symmetric; hooke: linear in u)."""
    if name == "tensor_hooke_forces":
        def fast_gradients(inputs, g, needs):
            if not needs[0]:
                return {}
            args = list(inputs)
            args[0] = g
            return {0: op(name)(*args)}

        return fast_gradients
    if name not in ("tensor_stvk_forces", "tensor_stvk_dforces"):
        return None
    dforce = name.endswith("dforces")

    def fast_gradients(inputs, g, needs):
        target = 1 if dforce else 0  # d/du of f(u) and d/d(du) of K(u) du: both K(u) g
        if not needs[target]:
            return {}
        args = list(inputs)
        if dforce:
            args[1] = g
        else:
            args.insert(1, g)
        return {target: op("tensor_stvk_dforces")(*args)}

    return fast_gradients


def _example(name):
    def example(device, dtype):
        ex = library.Example(device, dtype, uniform="_partial_" in name)
        edge_plan = (ex.edge_force_index, ex.edge_slots)
        plan = (ex.force_index, ex.num_slots)
        stvk = (ex.tensor_b, ex.tensor_c, ex.tensor_d)
        args = {
            "tensor_hooke_element_forces": (ex.u, ex.edges, ex.edge_k),
            "tensor_hooke_partial_forces": (ex.u, ex.edges, *edge_plan, ex.edge_k),
            "tensor_hooke_forces": (ex.u, ex.edges, *edge_plan, ex.edge_incidences, ex.edge_k),
            "tensor_stvk_element_forces": (ex.u, ex.elements, *stvk),
            "tensor_stvk_element_dforces": (ex.u, ex.du, ex.elements, *stvk),
            "tensor_stvk_partial_forces": (ex.u, ex.elements, *plan, *stvk),
            "tensor_stvk_partial_dforces": (ex.u, ex.du, ex.elements, *plan, *stvk),
            "tensor_stvk_forces": (ex.u, ex.elements, *plan, ex.incidences, *stvk),
            "tensor_stvk_dforces": (ex.u, ex.du, ex.elements, *plan, ex.incidences, *stvk),
        }[name]
        return args, {}

    return example


_OPS = {
    "tensor_hooke_element_forces": (_ref_tensor_hooke_element_forces, _fake_tensor_hooke_element),
    "tensor_hooke_partial_forces": (_ref_tensor_hooke_partial_forces, fake_partial),
    "tensor_hooke_forces": (_ref_tensor_hooke_forces, fake_nodes),
    "tensor_stvk_element_forces": (_ref_tensor_stvk_element_forces, fake_element),
    "tensor_stvk_element_dforces": (_ref_tensor_stvk_element_dforces, fake_element_d),
    "tensor_stvk_partial_forces": (_ref_tensor_stvk_partial_forces, fake_partial),
    "tensor_stvk_partial_dforces": (_ref_tensor_stvk_partial_dforces, fake_partial_d),
    "tensor_stvk_forces": (_ref_tensor_stvk_forces, fake_nodes),
    "tensor_stvk_dforces": (_ref_tensor_stvk_dforces, fake_nodes),
}
_DEFINED = {"tensor_hooke_partial_forces": library.partial_defined(1),
            "tensor_stvk_partial_forces": library.partial_defined(1),
            "tensor_stvk_partial_dforces": library.partial_defined(2)}
OPS = tuple(OpDef(name, ref, fake, _fast_gradients(name), example=_example(name), defined=_DEFINED.get(name))
            for name, (ref, fake) in _OPS.items())
library.define(OPS, lambda: library.register(OPS))


def stvk_tensors(group):
    """(tensor_b, tensor_c, tensor_d) of a stvk tensor-form group, contiguous, as the ops take them."""
    return group.tensor_b.contiguous(), group.tensor_c.contiguous(), group.tensor_d.contiguous()
