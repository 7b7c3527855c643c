"""The compiled ops ``torch.ops.tensormass.*``: fake kernels, autograd, and the group-level calls.

The ops are defined in C++ (``csrc/ops.cpp``, CPU and CUDA implementations from one element-math
header). This module gives them what torch needs on the Python side:

* a fake (meta) kernel for each op (``torch.library.register_fake``), for torch.compile/export;
* autograd (``torch.library.register_autograd``). Fast paths use the ops themselves:
    - forces:  d(g . f(u))/du = dforces(u, g) (the stiffness is symmetric: f = -grad W), except
      for the corotational model with R recomputed inside the op (f is not an energy gradient
      through R(u): reference vjp); with ``rotations`` given, R is an input: the u-gradient is
      dforces(u, g, R) and R gets the reference vjp;
    - dforces: d(g . K(u) du)/d du = dforces(u, g);
    - lam, mu: the forces are linear in (lam, mu), so the gradient per element is the dot of
      the element's cotangent with its forces evaluated at (lam, mu) = (1, 0) and (0, 1);
    - kernel 2 (gathers): the transposed gathers, exactly.
  Every other gradient (to u in the element-level and padded ops, to u in stvk dforces, to the
  geometry and to the Tensor-Mass tensors) goes through ``torch.func.vjp`` of the op's pure-torch
  reference (``REFERENCE``, built from ``tensormass_torch.ops.reference``), so every input that
  requires grad gets a correct gradient. Backward formulas are made of differentiable ops, so
  double backward works where the reference path does.
* group-level functions (:func:`forces`, :func:`dforces`, ...) that ``tensormass_torch.ops``
  calls when ``_backend.use_extension(device)`` says so.

``REFERENCE[name]`` has the op's signature and computes the same output in tensor ops (the
padded ``*_partial_*`` ops: the same values in the used slots, zeros elsewhere where the
op leaves them uninitialised).
"""
from __future__ import annotations

import dataclasses
import os
import threading
from typing import Optional

import torch

from ..mesh.topology import sum_slots_in_order
from .reference import corotational, stress_form, tensor_form
from .reference import gather as ref_gather

__all__ = ["MODEL_IDS", "ROTATION_IDS", "OPS", "REFERENCE", "available", "ensure_registered", "corotational_rotations",
           "element_forces", "element_dforces", "node_gather", "forces", "dforces", "system_fusable",
           "system_matvec", "system_matvec_alpha", "system_cg", "system_cg_serves", "persistent_cg_fits",
           "PERSISTENT_BLOCKS_PER_SM", "hooke_node_graph", "system_solve", "solve_plan", "chunk_slots", "StepEnd",
           "FUSED_STEP_END",
           "PIPELINED_SOLVE", "PIPELINED_LAYOUTS", "SOLVE_CHUNK_NODES", "STREAM_CHUNK_NODES", "HOOKE_MATVEC_LAYOUTS",
           "HOOKE_MATVEC_LAYOUT", "NODE_TANGENT", "tangent_graph", "tangent_serves", "tangent_node_k",
           "NODE_GRAPH_WINDOW", "set_objects", "node_graph_rows", "hooke_rows_graph", "StepRhs", "SOLVE_STEP_RHS",
           "steps_serve"]

#: The ``model`` integer of the op schemas ("stvk_definite": stvk with ``tangent="definite"``,
#: see ``reference.stress_form.kernel_model``).
MODEL_IDS = {"hooke": 0, "stvk": 1, "corotational": 2, "stvk_definite": 3}
MODEL_NAMES = {v: k for k, v in MODEL_IDS.items()}
#: The ``method`` integer of ``corotational_rotations``.
ROTATION_IDS = {"qr": 0, "polar": 1}

# ----------------------------------------------------------------------------------------------
# Pure-torch reference of every op (same signature): the oracle of the tests and the path of
# the non-fast gradients.
# ----------------------------------------------------------------------------------------------


def _model_name(model: int) -> str:
    try:
        return MODEL_NAMES[int(model)]
    except KeyError:
        raise ValueError(f"unknown model id {model!r} (0 = hooke, 1 = stvk, 2 = corotational, "
                         "3 = stvk with a definite tangent)") from None


def _qr_rotations(u_e, rest):
    if rest is None:
        raise ValueError("the corotational model (model 2) needs rest_elements [N, n, 3]")
    return corotational.qr_rotations(rest + u_e, rest)


def _ref_corotational_rotations(u, elements, m, proj, rest, method):
    """Element rotations ``[N, d, d]`` at u: method 0 = SOFA's QR frame, 1 = polar (membranes map
    their rest normal onto the current one first, as ``ops.linearize``)."""
    u_e = u[elements]
    if int(method) == ROTATION_IDS["qr"]:
        return _qr_rotations(u_e, rest)
    if int(method) != ROTATION_IDS["polar"]:
        raise ValueError(f"unknown rotation method {method!r} (0 = qr, 1 = polar)")
    F = corotational.deformation_gradient(u_e, m, proj)
    if proj is None:
        return corotational.polar_rotations(F)
    x_e = rest + u_e

    def unit_normal(p):
        n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        return n / torch.linalg.vector_norm(n, dim=1, keepdim=True)

    return corotational.polar_rotations(F, unit_normal(rest), unit_normal(x_e))


def _element_rotations(u_e, rest, rotations):
    """The rotations the corotational stress ops use: those given, else SOFA's QR frame at u."""
    return rotations if rotations is not None else _qr_rotations(u_e, rest)


def _ref_stress_element_forces(u, elements, m, vol, lam, mu, proj, model, rest=None, rotations=None):
    name = _model_name(model)
    if name == "corotational":
        u_e = u[elements]
        return corotational.forces(u_e, m, vol, lam, mu, _element_rotations(u_e, rest, rotations), proj)
    return stress_form.FORCES[name](u[elements], m, vol, lam, mu, proj)


def _ref_stress_element_dforces(u, du, elements, m, vol, lam, mu, proj, model, rest=None, rotations=None):
    name = _model_name(model)
    if name == "corotational":
        return corotational.dforces(du[elements], m, vol, lam, mu,
                                    _element_rotations(u[elements], rest, rotations), proj)
    return stress_form.DFORCES[name](u[elements], du[elements], m, vol, lam, mu, proj)


def _scatter(partial, index, force_index, num_slots, num_nodes):
    return ref_gather.scatter_partial_forces(partial, index, force_index, num_slots, num_nodes)


def _gather(partial, index, force_index, num_slots, incidences, node_term=None):
    return ref_gather.node_gather(partial, index, force_index, num_slots, incidences.shape[0], node_term)


def _ref_stress_partial_forces(u, elements, force_index, num_slots, m, vol, lam, mu, proj, model, rest=None,
                               rotations=None):
    f = _ref_stress_element_forces(u, elements, m, vol, lam, mu, proj, model, rest, rotations)
    return _scatter(f, elements, force_index, num_slots, u.shape[0])


def _ref_stress_partial_dforces(u, du, elements, force_index, num_slots, m, vol, lam, mu, proj, model,
                                rest=None, rotations=None):
    f = _ref_stress_element_dforces(u, du, elements, m, vol, lam, mu, proj, model, rest, rotations)
    return _scatter(f, elements, force_index, num_slots, u.shape[0])


def _ref_stress_forces(u, elements, force_index, num_slots, incidences, m, vol, lam, mu, proj, model, rest=None,
                       rotations=None):
    f = _ref_stress_element_forces(u, elements, m, vol, lam, mu, proj, model, rest, rotations)
    return _gather(f, elements, force_index, num_slots, incidences)


def _ref_stress_dforces(u, du, elements, force_index, num_slots, incidences, m, vol, lam, mu, proj, model,
                       rest=None, rotations=None):
    f = _ref_stress_element_dforces(u, du, elements, m, vol, lam, mu, proj, model, rest, rotations)
    return _gather(f, elements, force_index, num_slots, incidences)


def _ref_tensor_hooke_element_forces(u, edges, edge_k):
    return tensor_form.hooke_edge_partial_forces(u, edges, edge_k)


def _ref_tensor_hooke_partial_forces(u, edges, force_index, num_slots, edge_k):
    return _scatter(tensor_form.hooke_edge_partial_forces(u, edges, edge_k), edges, force_index, num_slots,
                    u.shape[0])


def _ref_tensor_hooke_forces(u, edges, force_index, num_slots, incidences, edge_k):
    return _gather(tensor_form.hooke_edge_partial_forces(u, edges, edge_k), edges, force_index, num_slots,
                   incidences, None)


def _ref_tensor_stvk_element_forces(u, elements, b, c, d):
    return tensor_form.stvk_forces(u[elements], b, c, d)


def _ref_tensor_stvk_element_dforces(u, du, elements, b, c, d):
    return tensor_form.stvk_dforces(u[elements], du[elements], b, c, d)


def _ref_tensor_stvk_partial_forces(u, elements, force_index, num_slots, b, c, d):
    return _scatter(_ref_tensor_stvk_element_forces(u, elements, b, c, d), elements, force_index, num_slots,
                    u.shape[0])


def _ref_tensor_stvk_partial_dforces(u, du, elements, force_index, num_slots, b, c, d):
    return _scatter(_ref_tensor_stvk_element_dforces(u, du, elements, b, c, d), elements, force_index,
                    num_slots, u.shape[0])


def _ref_tensor_stvk_forces(u, elements, force_index, num_slots, incidences, b, c, d):
    return _gather(_ref_tensor_stvk_element_forces(u, elements, b, c, d), elements, force_index, num_slots,
                   incidences)


def _ref_tensor_stvk_dforces(u, du, elements, force_index, num_slots, incidences, b, c, d):
    return _gather(_ref_tensor_stvk_element_dforces(u, du, elements, b, c, d), elements, force_index, num_slots,
                   incidences)


def _slot_mask(num_slots, incidences):
    """``[N_n, V, 1]``: whether slot s of node i is used (s < incidences[i])."""
    slots = torch.arange(num_slots, device=incidences.device)
    return (slots[:, None] < incidences[None, :])[:, :, None]


def _ref_gather_partial(partial, incidences, node_term):
    total = sum_slots_in_order(torch.where(_slot_mask(partial.shape[0], incidences), partial, partial.new_zeros(())))
    return total if node_term is None else total + node_term


def _ref_node_gather(partial, index, force_index, num_slots, incidences, node_term):
    return _gather(partial, index, force_index, num_slots, incidences, node_term)


def _system_epilogue(kp, p, mass, free, c_mass, c_stiff, node_stiffness=None):
    """Ap = free (c_mass mass p - c_stiff (kp - node_stiffness p)) ``[V, d]``, p . Ap per node ``[V]``."""
    if node_stiffness is not None:
        kp = kp - torch.einsum("vab,vb->va", node_stiffness, p)
    ap = (c_mass * mass.unsqueeze(-1)) * p - c_stiff * kp
    if free is not None:
        ap = ap * free.unsqueeze(-1)
    return ap, (p * ap).sum(-1)


def _ref_gather_system(partial, incidences, p, mass, free, c_mass, c_stiff, node_stiffness=None):
    """Kernel 2 + the implicit-Euler epilogue (see ``_system_epilogue``)."""
    return _system_epilogue(_ref_gather_partial(partial, incidences, None), p, mass, free, c_mass, c_stiff,
                            node_stiffness)


def _ref_hooke_node_system(p, neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff,
                           node_stiffness=None):
    """The node-centric hooke matvec: (K p)_i = sum over the used slots s of node i's row r of
    ``-node_k[s, r] (p[neighbor[s, r]] - p_i)`` with i = ``row_node[r]`` (None: i = r) (neighbor
    ``[N_n, V]``, node_k ``[N_n, V, d, d]``, incidences ``[V]``, all by row; unused slots are
    masked, whatever they hold), added slot after slot, then the system epilogue."""
    used = _slot_mask(neighbor.shape[0], incidences)  # [N_n, V, 1]
    others = torch.where(used[..., 0], neighbor, neighbor.new_zeros(())).long()
    nodes = torch.arange(p.shape[0], device=p.device) if row_node is None else row_node.long()
    w = p[others] - p[nodes].unsqueeze(0)  # [N_n, V, d]
    terms = -torch.einsum("svab,svb->sva", node_k, w)
    kp_rows = sum_slots_in_order(torch.where(used, terms, terms.new_zeros(())))
    kp = torch.empty_like(kp_rows).index_copy_(0, nodes, kp_rows)
    return _system_epilogue(kp, p, mass, free, c_mass, c_stiff, node_stiffness)


REFERENCE = {
    "stress_element_forces": _ref_stress_element_forces,
    "stress_element_dforces": _ref_stress_element_dforces,
    "stress_partial_forces": _ref_stress_partial_forces,
    "stress_partial_dforces": _ref_stress_partial_dforces,
    "stress_forces": _ref_stress_forces,
    "stress_dforces": _ref_stress_dforces,
    "corotational_rotations": _ref_corotational_rotations,
    "tensor_hooke_element_forces": _ref_tensor_hooke_element_forces,
    "tensor_hooke_partial_forces": _ref_tensor_hooke_partial_forces,
    "tensor_hooke_forces": _ref_tensor_hooke_forces,
    "tensor_stvk_element_forces": _ref_tensor_stvk_element_forces,
    "tensor_stvk_element_dforces": _ref_tensor_stvk_element_dforces,
    "tensor_stvk_partial_forces": _ref_tensor_stvk_partial_forces,
    "tensor_stvk_partial_dforces": _ref_tensor_stvk_partial_dforces,
    "tensor_stvk_forces": _ref_tensor_stvk_forces,
    "tensor_stvk_dforces": _ref_tensor_stvk_dforces,
    "gather_partial": _ref_gather_partial,
    "node_gather": _ref_node_gather,
    "gather_system": _ref_gather_system,
    "hooke_node_system": _ref_hooke_node_system,
}

#: Every op of the library ``tensormass``.
OPS = tuple(REFERENCE)

# ----------------------------------------------------------------------------------------------
# Fake kernels: output metadata only.
# ----------------------------------------------------------------------------------------------


def _fake_element(u, items, *_):
    return u.new_empty((items.shape[0], items.shape[1], u.shape[1]))


def _fake_element_d(u, du, items, *_):
    return u.new_empty((items.shape[0], items.shape[1], u.shape[1]))


def _fake_partial(u, items, force_index, num_slots, *_):
    return u.new_empty((num_slots, u.shape[0], u.shape[1]))


def _fake_partial_d(u, du, items, force_index, num_slots, *_):
    return u.new_empty((num_slots, u.shape[0], u.shape[1]))


def _fake_nodes(u, *_):
    return u.new_empty(u.shape)


def _fake_rotations(u, elements, *_):
    return u.new_empty((elements.shape[0], u.shape[1], u.shape[1]))


def _fake_tensor_hooke_element(u, edges, edge_k):
    return u.new_empty((edges.shape[0], 2, u.shape[1]))


def _fake_gather_partial(partial, incidences, node_term):
    return partial.new_empty((partial.shape[1], partial.shape[2]))


def _fake_node_gather(partial, index, force_index, num_slots, incidences, node_term):
    return partial.new_empty((incidences.shape[0], partial.shape[2]))


def _fake_gather_system(partial, incidences, p, mass, free, c_mass, c_stiff, node_stiffness=None):
    return (partial.new_empty((partial.shape[1], partial.shape[2])), partial.new_empty((partial.shape[1],)))


def _fake_hooke_node_system(p, neighbor, node_k, incidences, row_node, mass, free, c_mass, c_stiff,
                            node_stiffness=None):
    return p.new_empty(p.shape), p.new_empty((p.shape[0],))


FAKE = {
    "stress_element_forces": _fake_element,
    "stress_element_dforces": _fake_element_d,
    "stress_partial_forces": _fake_partial,
    "stress_partial_dforces": _fake_partial_d,
    "stress_forces": _fake_nodes,
    "stress_dforces": _fake_nodes,
    "corotational_rotations": _fake_rotations,
    "tensor_hooke_element_forces": _fake_tensor_hooke_element,
    "tensor_hooke_partial_forces": _fake_partial,
    "tensor_hooke_forces": _fake_nodes,
    "tensor_stvk_element_forces": _fake_element,
    "tensor_stvk_element_dforces": _fake_element_d,
    "tensor_stvk_partial_forces": _fake_partial,
    "tensor_stvk_partial_dforces": _fake_partial_d,
    "tensor_stvk_forces": _fake_nodes,
    "tensor_stvk_dforces": _fake_nodes,
    "gather_partial": _fake_gather_partial,
    "node_gather": _fake_node_gather,
    "gather_system": _fake_gather_system,
    "hooke_node_system": _fake_hooke_node_system,
}

# ----------------------------------------------------------------------------------------------
# Autograd
# ----------------------------------------------------------------------------------------------


def _op(name):
    return getattr(torch.ops.tensormass, name).default


def _is_float(x) -> bool:
    return isinstance(x, torch.Tensor) and x.is_floating_point()


def _setup_context(ctx, inputs, output):
    ctx.save_for_backward(*[x if isinstance(x, torch.Tensor) else None for x in inputs])
    ctx.plain = [None if isinstance(x, torch.Tensor) else x for x in inputs]


def _inputs(ctx):
    return [t if t is not None else p for t, p in zip(ctx.saved_tensors, ctx.plain)]


def _reference_vjp(name, inputs, wanted, cotangent):
    """Gradients of ``REFERENCE[name]`` at ``inputs`` for the input positions ``wanted``."""
    if not wanted:
        return {}
    ref = REFERENCE[name]

    def fn(*diff):
        args = list(inputs)
        for pos, value in zip(wanted, diff):
            args[pos] = value
        return ref(*args)

    _, vjp_fn = torch.func.vjp(fn, *[inputs[i] for i in wanted])
    return dict(zip(wanted, vjp_fn(cotangent)))


def _element_cotangent(name, inputs, grad):
    """The cotangent of the element-level output ``[N, n, d]`` (the ops linear in (lam, mu))."""
    if "_element_" in name:
        return grad
    elements = inputs[2] if "dforces" in name else inputs[1]
    if "_partial_" in name:
        force_index = inputs[3] if "dforces" in name else inputs[2]
        return grad[force_index, elements]
    return grad[elements]


def _lame_gradients(name, inputs, grad, need_lam, need_mu):
    """d(grad . out)/d(lam, mu) ``[N]`` for the stress ops: out is linear in (lam, mu), so the
    gradient per element is the dot of its cotangent with its output at (1, 0) and at (0, 1)."""
    m, vol, lam, mu, proj, model, rest, rotations = inputs[-8:]
    g_e = _element_cotangent(name, inputs, grad)
    ones, zeros = torch.ones_like(lam), torch.zeros_like(lam)
    # the rotations are an input here: held at their values (their own gradient is separate)
    rotations = None if rotations is None else rotations.detach()

    def at(a, b):
        if "dforces" in name:
            u, du, elements = inputs[0], inputs[1], inputs[2]
            f = _op("stress_element_dforces")(u, du, elements, m, vol, a, b, proj, model, rest, rotations)
        else:
            u, elements = inputs[0], inputs[1]
            f = _op("stress_element_forces")(u, elements, m, vol, a, b, proj, model, rest, rotations)
        return (g_e * f).sum((1, 2))

    return (at(ones, zeros) if need_lam else None), (at(zeros, ones) if need_mu else None)


def _fast_gradients(name, inputs, grad, needs):
    """The gradients computed by the ops themselves: {input position: gradient}."""
    fast = {}
    g = grad.contiguous()
    # The stress ops end with (..., proj, model, rest_elements, rotations).
    corot = name.startswith("stress_") and int(inputs[-3]) == MODEL_IDS["corotational"]
    # R recomputed inside the op from u (no rotations given) makes the forces depend on u through R
    r_of_u = corot and inputs[-1] is None
    if name in ("stress_forces", "stress_dforces", "tensor_stvk_forces", "tensor_stvk_dforces"):
        dforce = name.endswith("dforces")
        u_pos, du_pos = 0, 1
        target = du_pos if dforce else u_pos  # d/du of f(u) and d/d(du) of K(u) du: both K(u) g
        # corotational with R recomputed from u: f(u) = -R(u) K (R(u)^T x - X) is not the gradient
        # of an energy through R, so df/du != dforces (R fixed): its u-gradient goes through the
        # reference (qr_rotations differentiated). With R given, df/du is dforces(u, ., R), and R's
        # own gradient is the reference vjp below. dforces is linear in du with R fixed and K
        # symmetric: d/d(du) is fast.
        if needs[target] and not (r_of_u and not dforce):
            dname = name if dforce else name.replace("forces", "dforces")
            args = list(inputs)
            if not dforce:
                args.insert(1, g)
                if name == "stress_forces" and int(inputs[-3]) == MODEL_IDS["stvk_definite"]:
                    args[-3] = MODEL_IDS["stvk"]  # the forces' Jacobian is the exact tangent
            else:
                args[1] = g
            fast[target] = _op(dname)(*args)
        if dforce and needs[u_pos] and name == "stress_dforces" and (
                int(inputs[-3]) == MODEL_IDS["hooke"] or (corot and not r_of_u)):
            fast[u_pos] = None  # K does not depend on u: hooke, corotational with R given
    elif name == "tensor_hooke_forces":
        if needs[0]:
            args = list(inputs)
            args[0] = g
            fast[0] = _op(name)(*args)  # linear, K symmetric
    elif name == "gather_partial":
        partial, incidences = inputs[0], inputs[1]
        if needs[0]:
            mask = _slot_mask(partial.shape[0], incidences)
            fast[0] = torch.where(mask, g.unsqueeze(0), g.new_zeros(()))
        if needs[2]:
            fast[2] = g
    elif name == "node_gather":
        index = inputs[1]
        if needs[0]:
            fast[0] = g[index]
        if needs[5]:
            fast[5] = g
    if name.startswith("stress_"):
        lam_pos, mu_pos = len(inputs) - 6, len(inputs) - 5
        if needs[lam_pos] or needs[mu_pos]:
            fast[lam_pos], fast[mu_pos] = _lame_gradients(name, inputs, g, needs[lam_pos], needs[mu_pos])
    return fast


#: Ops without gradients (solver kernels, run under no grad): their backward raises.
NOT_DIFFERENTIABLE = ("gather_system", "hooke_node_system")


def _not_differentiable(name):
    def backward(ctx, *grads):
        raise RuntimeError(f"tensormass::{name} is not differentiable (a solver kernel): use the composed "
                           "path (tensormass_torch.ops.system_matvec falls back to it when gradients are needed)")

    return backward


def _make_backward(name):
    if name in NOT_DIFFERENTIABLE:
        return _not_differentiable(name)
    def backward(ctx, grad):
        inputs = _inputs(ctx)
        # the dispatcher drops trailing arguments equal to their defaults (rest_elements=None)
        # from the autograd inputs, while setup_context sees them filled in
        passed = len(ctx.needs_input_grad)
        needs = list(ctx.needs_input_grad) + [False] * (len(inputs) - passed)
        fast = _fast_gradients(name, inputs, grad, needs)
        wanted = [i for i, x in enumerate(inputs) if needs[i] and _is_float(x) and i not in fast]
        slow = _reference_vjp(name, inputs, wanted, grad)
        grads = []
        for i in range(len(inputs)):
            g = fast.get(i, slow.get(i))
            grads.append(g if needs[i] else None)
        return tuple(grads[:passed])

    return backward


# ----------------------------------------------------------------------------------------------
# Registration
# ----------------------------------------------------------------------------------------------

_lock = threading.Lock()
_registered = False


def _ops_defined() -> bool:
    try:
        torch.ops.tensormass.stress_forces  # noqa: B018
    except (AttributeError, RuntimeError):
        return False
    return True


def _register():
    global _registered
    with _lock:
        if _registered:
            return
        for name in OPS:
            if not hasattr(torch.ops.tensormass, name):  # an extension built before this op existed
                continue
            qualname = "tensormass::" + name
            torch.library.register_fake(qualname, FAKE[name])
            torch.library.register_autograd(qualname, _make_backward(name), setup_context=_setup_context)
        _registered = True


def available() -> bool:
    """Whether the ops are defined (the extension is loaded) and registered here."""
    if not _registered and _ops_defined():
        _register()
    return _registered


def ensure_registered() -> bool:
    """Load the extension (unless forced off) and register fake kernels and autograd once."""
    from .. import _backend

    if _registered:
        return True
    if _backend.load_extension() is None:
        return False
    return available()


# Imported by torch (set_python_module) or after _C: register now if the ops exist.
if _ops_defined():
    _register()

# ----------------------------------------------------------------------------------------------
# Group-level calls (tensormass_torch.ops dispatches here)
# ----------------------------------------------------------------------------------------------

_INT32_MAX = 2**31 - 1


def _unchanged(cache, tensors) -> bool:
    """Whether ``cache`` (tensors, versions, value) was made from these very tensors, unmodified."""
    return (cache is not None and len(cache[0]) == len(tensors)
            and all(a is b for a, b in zip(cache[0], tensors))
            and cache[1] == tuple(t._version for t in tensors))


def _plan_indices(plan):
    """(index, force_index, incidences) of a GatherPlan, as int32 when every value fits (half
    the index bytes the kernels read), cached on the plan while its tensors are unchanged."""
    tensors = (plan.index, plan.force_index, plan.incidences)
    cache = getattr(plan, "_native_indices", None)
    if _unchanged(cache, tensors):
        return cache[2]
    small = (plan.num_nodes <= _INT32_MAX and plan.num_slots <= _INT32_MAX
             and plan.index.numel() <= _INT32_MAX)
    dtype = torch.int32 if small else torch.int64
    value = tuple(t.to(dtype).contiguous() for t in tensors)
    try:
        plan._native_indices = (tensors, tuple(t._version for t in tensors), value)
    except AttributeError:  # a plan type without a __dict__: no cache
        pass
    return value


def _lame(group):
    """(lam, mu) of a stress-form group; cached on the group while young/poisson are the same
    unmodified tensors and need no gradient (then recomputed at every call, for autograd)."""
    tensors = (group.young, group.poisson)
    if any(t.requires_grad for t in tensors):
        return group.lame()
    cache = group.__dict__.get("_native_lame")
    if _unchanged(cache, tensors):
        return cache[2]
    lam, mu = group.lame()
    value = (lam.contiguous(), mu.contiguous())
    group.__dict__["_native_lame"] = (tensors, tuple(t._version for t in tensors), value)
    return value


def _stress_args(group, u: Optional[torch.Tensor] = None, rotations: Optional[torch.Tensor] = None):
    """The trailing arguments of the stress ops for ``group``. Corotational: the ``rotations``
    ``[N, d, d]`` of the linearisation (computed at ``u`` when None), so no kernel recomputes R;
    with neither, the rest nodes (the kernels then recompute SOFA's QR frame from u per call)."""
    lam, mu = _lame(group)
    proj = group.projector
    rest = None
    if group.model == "corotational":
        if rotations is None and u is not None:
            rotations = corotational_rotations(group, u)
        if rotations is None:
            rest = group.rest_elements.contiguous()
        else:
            rotations = rotations.contiguous()
    else:
        rotations = None
    return (group.shape_vectors.contiguous(), group.measure.contiguous(), lam.contiguous(), mu.contiguous(),
            None if proj is None else proj.contiguous(), MODEL_IDS[stress_form.kernel_model(group)], rest, rotations)


def _stvk_tensors(group):
    return group.tensor_b.contiguous(), group.tensor_c.contiguous(), group.tensor_d.contiguous()


def supports(group, u: torch.Tensor) -> bool:
    """Whether the ops can evaluate ``group`` at ``u`` (dtype and device of the group's data)."""
    if u.dtype not in (torch.float32, torch.float64) or u.dim() != 2:
        return False
    if group.measure.dtype != u.dtype or group.measure.device != u.device:
        return False
    if group.model == "corotational":
        # both rotation methods (qr: 3-D; polar: tets, 2-D triangles, membranes)
        return (group.rotation in ROTATION_IDS and group.form == "stress"
                and (group.rotation == "polar" or u.shape[1] == 3))
    return group.model in MODEL_IDS and group.form in ("stress", "tensor")


def corotational_rotations(group, u: torch.Tensor) -> torch.Tensor:
    """The element rotations ``[N, d, d]`` of a corotational group at displacements ``u [V, d]``
    (``group.rotation``: "qr" or "polar"), computed once per linearisation."""
    index, _, _ = _plan_indices(group.plan)
    rest = getattr(group, "rest_elements", None)
    proj = group.projector
    return torch.ops.tensormass.corotational_rotations(
        u.contiguous(), index, group.shape_vectors.contiguous(), None if proj is None else proj.contiguous(),
        None if rest is None else rest.contiguous(), ROTATION_IDS[group.rotation])


def element_forces(group, u: torch.Tensor, rotations: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Kernel 1 at element level: ``[N, n, d]`` (edges ``[Ed, 2, d]`` for the hooke tensor form).

    ``rotations``: the corotational rotations at ``u`` ``[N, d, d]`` (computed here when None).
    """
    u = u.contiguous()
    index, _, _ = _plan_indices(group.plan)
    if group.form == "stress":
        return torch.ops.tensormass.stress_element_forces(u, index, *_stress_args(group, u, rotations))
    if group.model == "hooke":
        return torch.ops.tensormass.tensor_hooke_element_forces(u, index, group.edge_k.contiguous())
    return torch.ops.tensormass.tensor_stvk_element_forces(u, index, *_stvk_tensors(group))


def element_dforces(group, u: torch.Tensor, du: torch.Tensor, rotations: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Kernel 1 with DForce() at element level: ``[N, n, d]``; ``rotations`` as in :func:`element_forces`."""
    u, du = u.contiguous(), du.contiguous()
    index, _, _ = _plan_indices(group.plan)
    if group.form == "stress":
        return torch.ops.tensormass.stress_element_dforces(u, du, index, *_stress_args(group, u, rotations))
    if group.model == "hooke":
        return torch.ops.tensormass.tensor_hooke_element_forces(du, index, group.edge_k.contiguous())
    return torch.ops.tensormass.tensor_stvk_element_dforces(u, du, index, *_stvk_tensors(group))


def node_gather(partial: torch.Tensor, plan, node_term: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Kernel 2 on compact partial forces ``[N, n, d]`` -> ``[V, d]`` (+ node_term)."""
    index, force_index, incidences = _plan_indices(plan)
    if node_term is not None:
        node_term = node_term.contiguous()
    return torch.ops.tensormass.node_gather(partial.contiguous(), index, force_index, plan.num_slots,
                                            incidences, node_term)


def forces(group, u: torch.Tensor, rotations: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Fused kernels 1 + 2: elastic forces ``[V, d]``; ``rotations`` as in :func:`element_forces`."""
    u = u.contiguous()
    plan = group.plan
    index, force_index, incidences = _plan_indices(plan)
    if group.form == "stress":
        return torch.ops.tensormass.stress_forces(u, index, force_index, plan.num_slots, incidences,
                                                  *_stress_args(group, u, rotations))
    if group.model == "hooke":
        if _node_layout(group, HOOKE_MATVEC_LAYOUT, (u,), "hooke_node_system"):
            # one kernel over the node graph (the system op with c_M = 0, c_K = -1 returns K u = the
            # forces, bitwise the padded gather's sums); not differentiable, hence the condition
            no_mass = _zeros_like_nodes(group, u)
            return torch.ops.tensormass.hooke_node_system(u, *hooke_rows_graph(group), no_mass, None, 0.0, -1.0,
                                                          None)[0]
        return torch.ops.tensormass.tensor_hooke_forces(u, index, force_index, plan.num_slots, incidences,
                                                        group.edge_k.contiguous())
    return torch.ops.tensormass.tensor_stvk_forces(u, index, force_index, plan.num_slots, incidences,
                                                   *_stvk_tensors(group))


def dforces(group, u: torch.Tensor, du: torch.Tensor, rotations: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Fused kernels 1 + 2 with DForce(): (dF/du) du ``[V, d]``; ``rotations``: the corotational
    rotations of the linearisation at ``u`` ``[N, d, d]`` (computed here when None)."""
    u, du = u.contiguous(), du.contiguous()
    plan = group.plan
    index, force_index, incidences = _plan_indices(plan)
    if group.form == "stress":
        return torch.ops.tensormass.stress_dforces(u, du, index, force_index, plan.num_slots,
                                                   incidences, *_stress_args(group, u, rotations))
    if group.model == "hooke":
        return torch.ops.tensormass.tensor_hooke_forces(du, index, force_index, plan.num_slots, incidences,
                                                        group.edge_k.contiguous())
    return torch.ops.tensormass.tensor_stvk_dforces(u, du, index, force_index, plan.num_slots,
                                                    incidences, *_stvk_tensors(group))


def _zeros_like_nodes(group, u: torch.Tensor) -> torch.Tensor:
    """Zeros ``[V]`` of u's dtype and device, kept on the group (a mass term of 0)."""
    cached = group.__dict__.get("_node_zeros")
    if cached is None or cached.dtype != u.dtype or cached.device != u.device or cached.shape[0] != u.shape[0]:
        cached = group.__dict__["_node_zeros"] = torch.zeros(u.shape[0], dtype=u.dtype, device=u.device)
    return cached


def _edge_neighbors(edges: torch.Tensor, force_index: torch.Tensor, num_slots: int, num_nodes: int) -> torch.Tensor:
    """The node graph's neighbours ``[N_n, V]`` of edges ``[Ed, 2]`` with their slots
    ``force_index [Ed, 2]``: slot ``force_index[e, 0]`` of ``edges[e, 0]`` holds ``edges[e, 1]`` and
    the other way round; unused slots 0 (never read). edges' dtype."""
    neighbor = edges.new_zeros((num_slots, num_nodes))
    neighbor[force_index[:, 0].long(), edges[:, 0].long()] = edges[:, 1]
    neighbor[force_index[:, 1].long(), edges[:, 1].long()] = edges[:, 0]
    return neighbor


#: The node graphs' rows (HookeNodeGraph, csrc/kernels.h): each object's nodes sorted by slot
#: count, most first, within windows of this many nodes from the object's first node, so that a
#: warp's threads (consecutive rows) walk as many slots each. 0 or 1: rows in node order.
#: Benchmarks switch it (``TENSORMASS_NODE_GRAPH_WINDOW`` in the environment, or this flag).
NODE_GRAPH_WINDOW = int(os.environ.get("TENSORMASS_NODE_GRAPH_WINDOW", "128"))


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


def _graph_rows(group, name: str, incidences: torch.Tensor, index_dtype) -> Optional[torch.Tensor]:
    """The row_node of the group's graph ``name`` of these (node-ordered) slot counts, cached on
    the group."""
    key = (_objects_of(group), NODE_GRAPH_WINDOW, index_dtype)
    cache = group.__dict__.get("_native_rows_" + name)
    if _unchanged(cache, (incidences,)) and cache[3] == key:
        return cache[2]
    rows = node_graph_rows(incidences, key[0], key[1])
    if rows is not None:
        rows = rows.to(index_dtype)
    group.__dict__["_native_rows_" + name] = ((incidences,), (incidences._version,), rows, key)
    return rows


def _by_rows(group, name: str, incidences: torch.Tensor, tensors):
    """The node-ordered arrays ``tensors`` of the group's graph ``name`` (node along dim 1 for 2-D
    and more, else dim 0; ``incidences [V]``: its slot counts) reordered by its rows, and the rows
    (:func:`_graph_rows`); cached on the group while the tensors are unchanged and the rows the same."""
    rows = _graph_rows(group, name, incidences, tensors[0].dtype)
    cache = group.__dict__.get("_native_by_rows_" + name)
    if _unchanged(cache, tensors) and cache[3] is rows:
        return cache[2], rows
    index = None if rows is None else rows.long()
    value = tuple(t if index is None else t.index_select(1 if t.dim() >= 2 else 0, index).contiguous()
                  for t in tensors)
    group.__dict__["_native_by_rows_" + name] = (tensors, tuple(t._version for t in tensors), value, rows)
    return value, rows


def hooke_rows_graph(group):
    """The hooke tensor form's node graph by rows, as the ``hooke_node_*`` ops take it: (neighbor
    ``[N_n, V]``, node_k ``[N_n, V, d, d]``, incidences ``[V]``, row_node ``[V]`` or None), from
    :func:`hooke_node_graph` and :func:`node_graph_rows`; cached on the group like them."""
    neighbor, node_k = hooke_node_graph(group)
    incidences = _plan_indices(group.plan)[2]
    by_rows, rows = _by_rows(group, "hooke", incidences, (neighbor, node_k, incidences))
    return (*by_rows, rows)


def hooke_node_graph(group):
    """The node graph of a hooke tensor-form group in slot-major ("ELL") arrays, for
    ``hooke_node_system``: (neighbor ``[N_n, V]``, node_k ``[N_n, V, d, d]``).

    Slot s of node i is the slot the group's plan gives it (``force_index``): for edge e = (i, j)
    (i = ``edges[e, 0]``), ``neighbor[fi[e, 0], i] = j`` with ``node_k = K_e`` and
    ``neighbor[fi[e, 1], j] = i`` with ``node_k = K_e^T``. Unused slots hold zeros (never read).
    neighbor has the plan's native index dtype (that of :func:`_plan_indices`), node_k edge_k's
    dtype and device. Cached on the group while edge_k and the plan's indices are the same
    unmodified tensors."""
    index, force_index, _ = _plan_indices(group.plan)
    edge_k = group.edge_k
    tensors = (edge_k, index, force_index)
    cache = group.__dict__.get("_native_node_graph")
    if _unchanged(cache, tensors):
        return cache[2]
    plan = group.plan
    num_slots, num_nodes, dim = plan.num_slots, plan.num_nodes, edge_k.shape[-1]
    first, second = index[:, 0].long(), index[:, 1].long()
    slot_first, slot_second = force_index[:, 0].long(), force_index[:, 1].long()
    neighbor = _edge_neighbors(index, force_index, num_slots, num_nodes)
    node_k = edge_k.new_zeros((num_slots, num_nodes, dim, dim))
    with torch.no_grad():
        node_k[slot_first, first] = edge_k
        node_k[slot_second, second] = edge_k.transpose(1, 2)
    value = (neighbor, node_k)
    group.__dict__["_native_node_graph"] = (tensors, tuple(t._version for t in tensors), value)
    return value


#: Whether the CG products of stress-form stvk and corotational groups run over the node graph
#: with the differential at the linearisation as its slot tensors (:func:`tangent_node_k`, once
#: per linearisation: 9 values an edge and direction a CG iteration instead of an element pass
#: that recomputes each element's differential). Benchmarks switch it off to compare
#: (``TENSORMASS_NODE_TANGENT=0`` in the environment, or this flag).
NODE_TANGENT = os.environ.get("TENSORMASS_NODE_TANGENT", "1") != "0"


def tangent_graph(group):
    """The node graph of a stress-form group's tangent: (EdgeGraph with native index tensors, and
    by the rows of :func:`node_graph_rows`: neighbor ``[N_n, V]``, incidences ``[V]``, row_node
    ``[V]`` or None, slot_edge ``[N_n, V]``), the graph's index dtype that of :func:`_plan_indices`
    of the group's plan. Cached on the group while its elements are the same unmodified tensor
    (the first call synchronises with the device: build it before a capture)."""
    graph, neighbor, incidences = _tangent_edge_graph(group)
    (neighbor, row_incidences, slot_edge), rows = _by_rows(group, "tangent", incidences,
                                                          (neighbor, incidences, graph.slot_edge))
    return graph, neighbor, row_incidences, rows, slot_edge


def _tangent_edge_graph(group):
    """tangent_graph's (EdgeGraph, neighbor, incidences) in node order, cached on the group."""
    from ..mesh.topology import EdgeGraph

    elements = group.elements
    cache = group.__dict__.get("_native_tangent_graph")
    if _unchanged(cache, (elements,)):
        return cache[2]
    dtype = _plan_indices(group.plan)[0].dtype  # the elements' (every index tensor of the op has one dtype)
    graph = EdgeGraph.build(elements.long(), group.num_nodes)
    plan = graph.plan

    def native(t):
        return t.to(dtype).contiguous()

    graph = type(graph)(native(graph.edges), native(graph.element_edges), native(graph.edge_slots),
                        graph.num_edge_slots, native(graph.edge_counts),
                        type(plan)(native(plan.index), native(plan.force_index), plan.num_slots, plan.num_nodes,
                                   native(plan.incidences)), native(graph.slot_edge))
    plan = graph.plan
    value = (graph, _edge_neighbors(plan.index, plan.force_index, plan.num_slots, plan.num_nodes),
             plan.incidences)
    group.__dict__["_native_tangent_graph"] = ((elements,), (elements._version,), value)
    return value


def tangent_serves(group, u: torch.Tensor, inputs=()) -> bool:
    """Whether :func:`tangent_node_k` serves ``group`` at ``u``: :data:`NODE_TANGENT` on, a
    stress-form stvk or corotational group the ops support, the op compiled, and no gradient wanted
    through ``u``, ``inputs`` or the group's data (the node graph's products are not differentiable)."""
    return (NODE_TANGENT and group.form == "stress" and group.model != "hooke"
            and hasattr(torch.ops.tensormass, "stress_tangent_node_k") and supports(group, u)
            and not _wants_grad((u, *inputs, group.shape_vectors, group.measure, group.young, group.poisson)))


def tangent_node_k(group, u: torch.Tensor, rotations: Optional[torch.Tensor] = None,
                   out: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The force differential of a stress-form group at displacements ``u [V, d]`` as the slot
    tensors of its node graph (:func:`tangent_graph`): node_k ``[N_n, V, d, d]`` by the graph's
    rows, with -H_ij in the slot of (i -> j), H_ij = d f_i / d u_j summed over the elements of the
    edge, so that ``hooke_node_system`` over (neighbor, node_k, incidences, row_node) is
    :func:`system_matvec`'s product
    at u. ``rotations``: the corotational rotations of the linearisation (computed at u when None).
    Into ``out`` when it has the shape, dtype and device (the step's buffer: CUDA graphs replay
    into it), else a new tensor. Requires :func:`tangent_serves`."""
    graph, _, incidences, _, slot_edge = tangent_graph(group)
    plan = graph.plan
    d = u.shape[1]
    shape = (plan.num_slots, u.shape[0], d, d)
    if out is None or tuple(out.shape) != shape or out.dtype != u.dtype or out.device != u.device:
        out = u.new_zeros(shape)
    work_shape = (graph.num_edge_slots, graph.edges.shape[0], 12 if d == 3 else 4)  # blocks padded to 16 bytes
    work = group.__dict__.get("_native_tangent_work")
    if work is None or tuple(work.shape) != work_shape or work.dtype != u.dtype or work.device != u.device:
        work = group.__dict__["_native_tangent_work"] = u.new_empty(work_shape)
    index, _, _ = _plan_indices(group.plan)
    m, vol, lam, mu, proj, model, _, rotations = _stress_args(group, u, rotations)
    torch.ops.tensormass.stress_tangent_node_k(
        u.contiguous(), index, m, vol, lam, mu, proj, model, rotations, graph.element_edges, graph.edge_slots,
        graph.num_edge_slots, graph.edge_counts, slot_edge, incidences, out, work)
    return out


def _ref_stress_tangent_node_k(u, elements, m, vol, lam, mu, proj, model, rotations, element_edges, edge_slots,
                               num_edge_slots, edge_counts, slot_edge, incidences):
    """stress_tangent_node_k's reference: the element blocks H_ab from the reference element
    dforces along unit displacements (n d of them), summed onto edges in slot order, written to
    the node graph's slots ``[N_n, V, d, d]`` (-H_g where slot_edge = g, -H_g^T where ~g; zeros in
    unused slots)."""
    n, d = elements.shape[1], u.shape[1]
    u_e = u[elements]
    name = _model_name(model)
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
    return torch.where(used[..., None, None], -blocks, torch.zeros_like(blocks))  # [N_n, V, d, d]


#: The layouts of the hooke tensor form's CG matvec in :func:`system_matvec`: "node" (one kernel
#: over the node graph, ``hooke_node_system``) or "padded" (kernel 1 into PartialForce, then
#: ``gather_system``). Both give bitwise the same result.
HOOKE_MATVEC_LAYOUTS = ("node", "padded")
#: The layout :func:`system_matvec` uses when its ``layout`` argument is None (benchmarks switch it).
HOOKE_MATVEC_LAYOUT = "node"


def system_fusable(group) -> bool:
    """Whether :func:`system_matvec` has a fused path for ``group``: kernel 1 through a padded
    partial-dforce op (stress form, both tensor forms)."""
    return hasattr(torch.ops.tensormass, "gather_system") and group.form in ("stress", "tensor")


def _contiguous(*tensors):
    return tuple(None if t is None else t.contiguous() for t in tensors)


def _wants_grad(tensors) -> bool:
    return torch.is_grad_enabled() and any(t is not None and t.requires_grad for t in tensors)


def _node_layout(group, layout: str, inputs, op: str) -> bool:
    """Whether the hooke tensor form's product runs over the node graph (op ``op``): layout
    "node", the op compiled, no gradient wanted through ``inputs`` or the edge tensors."""
    return (group.form == "tensor" and group.model == "hooke" and layout == "node"
            and hasattr(torch.ops.tensormass, op) and not _wants_grad((*inputs, group.edge_k)))


def _node_graph(group, layout: str, inputs, op: str, node_k: Optional[torch.Tensor] = None):
    """(neighbor ``[N_n, V]``, node_k ``[N_n, V, d, d]``, incidences ``[V]``, row_node ``[V]`` or
    None: by rows, :func:`node_graph_rows`) of the group's CG
    product over the node graph (op ``op``) where it runs there: a stress-form group's tangent
    graph with ``node_k`` given (:func:`tangent_node_k` at the linearisation), or the hooke tensor
    form's own graph (``layout`` "node"); no gradient wanted through ``inputs``. None otherwise."""
    if node_k is not None:
        if not hasattr(torch.ops.tensormass, op) or _wants_grad((*inputs, node_k)):
            return None
        _, neighbor, incidences, rows, _ = tangent_graph(group)
        return neighbor, node_k, incidences, rows
    if not _node_layout(group, layout, inputs, op):
        return None
    return hooke_rows_graph(group)


def _partial_dforces(group, u: torch.Tensor, p: torch.Tensor, rotations: Optional[torch.Tensor]):
    """Kernel 1 of the CG product: the padded partial force differentials along ``p``
    (PartialForce ``[N_n, V, d]``) and the plan's incidences ``[V]``."""
    plan = group.plan
    index, force_index, incidences = _plan_indices(plan)
    if group.form == "stress":
        partial = torch.ops.tensormass.stress_partial_dforces(u, p, index, force_index, plan.num_slots,
                                                              *_stress_args(group, u, rotations))
    elif group.model == "hooke":  # linear: the partial forces of p are its partial dforces
        partial = torch.ops.tensormass.tensor_hooke_partial_forces(p, index, force_index, plan.num_slots,
                                                                   group.edge_k.contiguous())
    else:
        partial = torch.ops.tensormass.tensor_stvk_partial_dforces(u, p, index, force_index, plan.num_slots,
                                                                   *_stvk_tensors(group))
    return partial, incidences


def system_matvec(group, u: torch.Tensor, p: torch.Tensor, mass: torch.Tensor, free: Optional[torch.Tensor],
                  c_mass: float, c_stiff: float, rotations: Optional[torch.Tensor] = None,
                  node_stiffness: Optional[torch.Tensor] = None, layout: Optional[str] = None,
                  node_k: Optional[torch.Tensor] = None):
    """The CG matvec of implicit Euler for one group: kernel 1 (padded partial dforces along ``p``)
    and kernel 2 with the system epilogue (``gather_system``); for the hooke tensor form with
    ``layout`` "node" (the default, :data:`HOOKE_MATVEC_LAYOUT`) and no gradient wanted, one kernel
    over the node graph instead (``hooke_node_system``, bitwise the same result). ``mass`` and
    ``free`` are ``[V]`` (``free`` float 0/1 or None); ``rotations``: the corotational rotations of
    the linearisation at ``u`` ``[N, d, d]``, kept across CG iterations (computed here when None);
    ``node_stiffness`` ``[V, d, d]`` (contact penalties) or None; ``layout``: "node", "padded" or
    None (the module default); ``node_k``: the tangent of a stress-form group at u on its node
    graph (:func:`tangent_node_k`), then the product runs over that graph (``hooke_node_system``).
    Returns (Ap ``[V, d]``, p . Ap per node ``[V]``)."""
    layout = HOOKE_MATVEC_LAYOUT if layout is None else layout
    if layout not in HOOKE_MATVEC_LAYOUTS:
        raise ValueError(f"unknown matvec layout {layout!r}; known: {', '.join(HOOKE_MATVEC_LAYOUTS)}")
    u, p, mass, free, node_stiffness = _contiguous(u, p, mass, free, node_stiffness)
    graph = _node_graph(group, layout, (p, mass, free, node_stiffness), "hooke_node_system", node_k)
    if graph is not None:
        return torch.ops.tensormass.hooke_node_system(p, *graph, mass, free, float(c_mass), float(c_stiff),
                                                      node_stiffness)
    partial, incidences = _partial_dforces(group, u, p, rotations)
    if torch.is_grad_enabled() and any(t is not None and t.requires_grad
                                       for t in (partial, p, mass, free, node_stiffness)):
        # gather_system has no gradient: the same arithmetic in differentiable ops
        kp = torch.ops.tensormass.gather_partial(partial, incidences, None)
        return _system_epilogue(kp, p, mass, free, c_mass, c_stiff, node_stiffness)
    return torch.ops.tensormass.gather_system(partial, incidences, p, mass, free, float(c_mass), float(c_stiff),
                                              node_stiffness)


def system_matvec_alpha(group, u: torch.Tensor, p: torch.Tensor, mass: torch.Tensor, free: Optional[torch.Tensor],
                        c_mass: float, c_stiff: float, rotations: Optional[torch.Tensor],
                        node_stiffness: Optional[torch.Tensor], ap: torch.Tensor, plan_tensors, cg_state,
                        node_k: Optional[torch.Tensor] = None) -> bool:
    """:func:`system_matvec` fused with the CG step length (``gather_system_alpha`` /
    ``hooke_node_system_alpha``): Ap into ``ap [V, d]`` in place and ``cg_state.alpha`` /
    ``.status`` as ``cg_alpha`` would set them, one launch fewer per CG iteration. ``plan_tensors``:
    (chunk_start, chunk_object, object_chunk) of the CG's chunk plan; ``cg_state``: its
    ``CGState``; ``node_k``: as in :func:`system_matvec`. Returns False (nothing done) where the
    ops are missing or a gradient is wanted."""
    ops_ns = torch.ops.tensormass
    if not hasattr(ops_ns, "gather_system_alpha") or _wants_grad((p, mass, free, node_stiffness)):
        return False
    u, p, mass, free, node_stiffness = _contiguous(u, p, mass, free, node_stiffness)
    s = cg_state
    cg_args = (*plan_tensors, s.rr, s.status, s.alpha, s.scratch, s.counter)
    if node_k is not None or (group.form == "tensor" and group.model == "hooke" and HOOKE_MATVEC_LAYOUT == "node"):
        graph = _node_graph(group, "node", (), "hooke_node_system_alpha", node_k)
        if graph is None:
            return False
        ops_ns.hooke_node_system_alpha(p, *graph, mass, free, float(c_mass), float(c_stiff), node_stiffness, ap,
                                       *cg_args)
        return True
    partial, incidences = _partial_dforces(group, u, p, rotations)
    if _wants_grad((partial,)):
        return False
    ops_ns.gather_system_alpha(partial, incidences, p, mass, free, float(c_mass), float(c_stiff), node_stiffness, ap,
                               *cg_args)
    return True


#: Blocks of the persistent CG kernel resident on each multiprocessor (``kPersistentBlocksPerSM``
#: of csrc/cuda/cg_persistent.cuh: its launch bounds guarantee them).
PERSISTENT_BLOCKS_PER_SM = 2


def persistent_cg_fits(device: torch.device, num_chunks: int) -> bool:
    """Whether a CG over ``num_chunks`` chunks runs as one op on ``device``: always on the CPU; on a
    GPU when every chunk has its own resident block of the persistent kernel (one wave). Beyond
    that the blocks loop over chunks with 16 warps per SM, too few to stream: on an H100 a CG
    iteration over 5-10M elements took 1.53-1.58x its memory floor so, against 1.37-1.45x with
    the per-iteration kernels on a full grid (whose launches cost nothing at that size)."""
    if device.type != "cuda":
        return True
    sms = torch.cuda.get_device_properties(device).multi_processor_count
    return num_chunks <= PERSISTENT_BLOCKS_PER_SM * sms


def system_cg_serves(group, inputs=(), num_chunks: int = 0, node_k: Optional[torch.Tensor] = None) -> bool:
    """Whether :func:`system_cg` solves ``group``'s systems in one op: over a node graph (the hooke
    tensor form's with :data:`HOOKE_MATVEC_LAYOUT` "node", or a stress-form group's tangent graph
    with ``node_k`` given), ``hooke_node_cg`` compiled, no gradient wanted through ``inputs``, and
    a plan of ``num_chunks`` chunks that fits (:func:`persistent_cg_fits`) on the device of
    ``inputs[0]``."""
    inputs = tuple(inputs)
    return ((node_k is not None or HOOKE_MATVEC_LAYOUT == "node")
            and _node_graph(group, "node", inputs, "hooke_node_cg", node_k) is not None
            and (not inputs or persistent_cg_fits(inputs[0].device, num_chunks)))


def system_cg(group, mass: torch.Tensor, free: Optional[torch.Tensor], c_mass: float,
              c_stiff: float, node_stiffness: Optional[torch.Tensor], ap: torch.Tensor, rhs: Optional[torch.Tensor],
              tol: float, plan_tensors, cg_state, max_iter: int, count: int,
              node_k: Optional[torch.Tensor] = None) -> bool:
    """A whole CG solve of the system of :func:`system_matvec` in one op (``hooke_node_cg``: one
    persistent kernel on the GPU) on ``cg_state`` (``CGState``; its direction ``p`` is the
    product's input): with ``rhs [V, d]`` the start from x0 = 0 (rhs projected on
    ``free``, relative tolerance ``tol``), then up to ``count`` iterations, stopping once no
    object is active;
    ``ap [V, d]``: the product's buffer. Bitwise the op-by-op solve. Only for the hooke tensor form
    over the node graph (:data:`HOOKE_MATVEC_LAYOUT` "node"); returns False, having done nothing,
    for any other group, where the op is missing or a gradient is wanted."""
    ops_ns = torch.ops.tensormass
    s = cg_state
    if not system_cg_serves(group, (s.p, mass, free, node_stiffness, rhs), s.scratch.numel(), node_k):
        return False
    mass, free, node_stiffness, rhs = _contiguous(mass, free, node_stiffness, rhs)
    graph = _node_graph(group, "node", (), "hooke_node_cg", node_k)
    ops_ns.hooke_node_cg(s.p, *graph, mass, free, float(c_mass), float(c_stiff), node_stiffness,
                         ap, s.x, s.r, rhs, float(tol) ** 2, *plan_tensors, s.threshold, s.rhs_sq, int(max_iter),
                         int(count), s.rr, s.status, s.alpha, s.beta, s.iterations, s.rr_swap, s.work, s.sums)
    return True


#: Whether whole CG solves on the GPU run as ``hooke_node_solve`` (the pipelined CG, one grid
#: barrier an iteration) where it fits, before ``hooke_node_cg``. Benchmarks and the bitwise tests
#: of hooke_node_cg switch it off.
PIPELINED_SOLVE = True
#: Nodes per chunk of the pipelined solve's plan in each layout (csrc/cuda/cg_pipelined.cuh
#: kSolveChunkNodes: two threads a node; kStreamChunkNodes: one).
SOLVE_CHUNK_NODES = 128
STREAM_CHUNK_NODES = 256
_LAYOUT_CHUNK_NODES = {"shared": SOLVE_CHUNK_NODES, "streamed": STREAM_CHUNK_NODES}


def _layouts_from_env(default: tuple) -> tuple:
    text = os.environ.get("TENSORMASS_PIPELINED_LAYOUTS")
    if text is None:
        return default
    names = tuple(name.strip() for name in text.split(",") if name.strip())
    unknown = [name for name in names if name not in _LAYOUT_CHUNK_NODES]
    if unknown:
        raise ValueError(f"TENSORMASS_PIPELINED_LAYOUTS: unknown layout(s) {unknown}; "
                         f"known: {sorted(_LAYOUT_CHUNK_NODES)}")
    return names


#: The layouts of the pipelined solve's node graph, tried in this order (the first that fits one
#: wave of the GPU runs; csrc/cuda/cg_pipelined.cuh): "shared", chunks of
#: :data:`SOLVE_CHUNK_NODES` nodes whose slots sit in shared memory for the whole solve (small
#: systems: latency is all); "streamed", chunks of :data:`STREAM_CHUNK_NODES` nodes, each node's
#: first slots in shared memory for the whole solve and the rest read from the graph every
#: iteration (graphs beyond shared memory, up to ~67k nodes on an H100).
#: Tests and benchmarks narrow it (``TENSORMASS_PIPELINED_LAYOUTS=shared`` in the environment, a
#: comma-separated list, or this tuple).
PIPELINED_LAYOUTS = _layouts_from_env(("shared", "streamed"))


def solve_plan(plan, layout: str = "shared"):
    """The chunk plan of :func:`system_solve` in ``layout`` (see :data:`PIPELINED_LAYOUTS`) for the
    objects of ``plan`` (a ``ChunkPlan``): chunks of at most :data:`SOLVE_CHUNK_NODES` ("shared")
    or :data:`STREAM_CHUNK_NODES` ("streamed") nodes, one GPU block each. Cached on ``plan``."""
    if layout not in _LAYOUT_CHUNK_NODES:
        raise ValueError(f"layout must be one of {sorted(_LAYOUT_CHUNK_NODES)}, got {layout!r}")
    plans = plan.__dict__.setdefault("_solve_plans", {})
    if layout not in plans:
        plans[layout] = type(plan).from_segments(plan.segments, _LAYOUT_CHUNK_NODES[layout])
    return plans[layout]


def chunk_slots(group, plan, incidences: Optional[torch.Tensor] = None) -> int:
    """The most slots of any chunk of ``plan`` (the sum of the node graph's incidences over its
    nodes): the shared memory a block of the pipelined solve needs. ``incidences``: the node
    graph's ``[V]`` (that of the group's plan when None: the hooke tensor form). A host
    synchronisation the first time; cached on the group while the plan and its incidences are the
    same."""
    if incidences is None:
        _, _, incidences = _plan_indices(group.plan)
    cache = group.__dict__.get("_solve_chunk_slots")
    if cache is not None and cache[0] is plan and _unchanged(cache[1], (incidences,)):
        return cache[2]
    prefix = torch.zeros(incidences.numel() + 1, dtype=torch.int64, device=incidences.device)
    torch.cumsum(incidences.long(), 0, out=prefix[1:])
    starts = plan.chunk_start.to(incidences.device)
    value = int((prefix[starts[1:]] - prefix[starts[:-1]]).max()) if plan.num_chunks else 0
    group.__dict__["_solve_chunk_slots"] = (plan, ((incidences,), (incidences._version,), None), value)
    return value


#: Whether a whole solve by the pipelined CG also ends the implicit Euler step when asked
#: (``StepEnd``: ``hooke_node_solve_step``, one launch a step fewer); off, the step's end is its
#: own op (``euler_update``). Tests compare the two.
FUSED_STEP_END = True


@dataclasses.dataclass
class StepEnd:
    """The end of an implicit Euler step for the solve that computes its ``dv`` to do in its own
    kernel (:func:`system_solve`: ``hooke_node_solve_step``), as ``euler_update`` does it:
    ``v_new = v + dv (+ dv_imposed)``, ``x_new = x + h v_new`` (all ``[V, d]``; ``carry``: also
    into ``x, v``), each object's ``|v_new|^2`` into ``norms [B]``, the step's summary into
    ``summary [5, B]`` float64 and, with a ``ring [R, 5, B]``, its row ``ring_pos [1]`` (then
    advanced). ``done``: set by the solve that did it (else the caller runs ``euler_update``)."""

    x: torch.Tensor
    v: torch.Tensor
    dv_imposed: Optional[torch.Tensor]
    h: float
    x_new: torch.Tensor
    v_new: torch.Tensor
    norms: torch.Tensor
    summary: torch.Tensor
    ring: Optional[torch.Tensor] = None
    ring_pos: Optional[torch.Tensor] = None
    carry: bool = False
    done: bool = False
    #: the step's right-hand side for the solve to compute first (``StepRhs``; the solve's rhs is
    #: then its output), ``steps`` steps back to back (needs ``carry`` beyond one): one kernel
    #: for all of them (``hooke_node_steps``) where it serves, else nothing is done
    rhs: Optional["StepRhs"] = None
    steps: int = 1


@dataclasses.dataclass
class StepRhs:
    """What the solve needs to compute implicit Euler's right-hand side itself, at the state
    ``StepEnd.x, StepEnd.v`` (``hooke_node_steps``), as :func:`step_rhs` does:
    ``rhs = h (f((x - rest) + w_coef v) + external + contact(x) - Kc(x) (w_coef v) - r_M mass v)``,
    ``u = x - rest`` into ``u [V, d]`` (``rest, external [V, d]``) and, with ``planes`` (a
    ``contact.Planes``), Kc into the solve's ``node_stiffness [V, 3, 3]``, which its products
    then read."""

    rest: torch.Tensor
    external: torch.Tensor
    w_coef: float
    rayleigh_mass: float
    u: torch.Tensor
    planes: Optional[object] = None


class _SolveWork:
    """The pipelined solve's work on one CG state, for one plan, graph (its ``incidences``), and
    ``key`` (the right-hand side's shape and dtype, the layouts to try): the
    exchange rows ``[2, V, 4d]``, the counters, the chunk sums of each layout tried, and what the
    tries found (``layout``: the one that ran; ``misfits``: those that did not fit, not tried
    again: each try is a launch attempt, on every step)."""

    def __init__(self, plan, incidences: torch.Tensor, key, rhs: torch.Tensor):
        self.plan, self.incidences, self.key = plan, incidences, key
        self.exchange = torch.zeros((2, rhs.shape[0], 4 * rhs.shape[1]), dtype=rhs.dtype, device=rhs.device)
        self.counters = torch.zeros(3, dtype=torch.int32, device=rhs.device)
        self.sums = {}
        self.end_work = {}
        self.layout = None
        self.misfits = set()

    def sums_of(self, layout: str, plan) -> torch.Tensor:
        if layout not in self.sums:
            self.sums[layout] = torch.zeros(4 * plan.num_chunks, dtype=torch.float64, device=self.exchange.device)
        return self.sums[layout]

    def end_work_of(self, layout: str, plan):
        """The step end's chunk sums ``[K]`` float64 and object counters ``[B + 1]`` int32 (zero
        between calls) in ``layout``."""
        if layout not in self.end_work:
            device = self.exchange.device
            self.end_work[layout] = (torch.zeros(plan.num_chunks, dtype=torch.float64, device=device),
                                     torch.zeros(plan.object_chunk.numel(), dtype=torch.int32, device=device))
        return self.end_work[layout]


def system_solve(group, mass: torch.Tensor, free: Optional[torch.Tensor], c_mass: float, c_stiff: float,
                 node_stiffness: Optional[torch.Tensor], rhs: torch.Tensor, tol: float, plan, cg_state,
                 max_iter: int, node_k: Optional[torch.Tensor] = None, step_end: Optional[StepEnd] = None) -> bool:
    """A whole CG solve from x0 = 0 of :func:`system_matvec`'s system (rhs ``[V, d]`` projected on
    ``free``; relative tolerance ``tol``; at most ``max_iter`` iterations) by the pipelined CG
    (``hooke_node_solve``: Chronopoulos-Gear, one reduction and one grid barrier an iteration, one
    persistent kernel) into ``cg_state`` (a ``CGState`` over ``plan``: x, r, p, the per-object
    scalars and statuses), in the first of :data:`PIPELINED_LAYOUTS` that fits. CG's iterates in
    exact arithmetic, rounded differently from :func:`system_cg`'s. Returns False, having done
    nothing, where it does not serve: not a CUDA tensor, :data:`PIPELINED_SOLVE` off, no node graph
    (``node_k``: as in :func:`system_matvec`), a gradient wanted, or a system too large for one
    wave of the kernel in every layout. ``step_end``: the implicit Euler step's end, done in the
    same kernel (``hooke_node_solve_step``; its ``done`` set) where :data:`FUSED_STEP_END`; with
    its ``rhs`` (a :class:`StepRhs`), ``rhs`` is this solve's output: its ``steps`` steps, each
    its right-hand side, solve and end, in one kernel (``hooke_node_steps``) where
    :func:`steps_serve`, else nothing is done."""
    s = cg_state
    if not (PIPELINED_SOLVE and rhs.is_cuda and (node_k is not None or HOOKE_MATVEC_LAYOUT == "node")):
        return False
    if step_end is not None and step_end.rhs is not None and not steps_serve(group, node_stiffness, node_k, step_end):
        return False
    graph = _node_graph(group, "node", (s.p, mass, free, node_stiffness, rhs), "hooke_node_solve", node_k)
    if graph is None:
        return False
    key = (tuple(rhs.shape), rhs.dtype, PIPELINED_LAYOUTS)
    work = s.__dict__.get("_solve_work")
    if work is None or work.plan is not plan or work.incidences is not graph[2] or work.key != key:
        work = s.__dict__["_solve_work"] = _SolveWork(plan, graph[2], key, rhs)
    mass, free, node_stiffness, rhs = _contiguous(mass, free, node_stiffness, rhs)
    for layout in ((work.layout,) if work.layout is not None else PIPELINED_LAYOUTS):
        if layout in work.misfits:
            continue
        layout_plan = solve_plan(plan, layout)
        slots = chunk_slots(group, layout_plan, graph[2]) if layout == "shared" else 0
        system = (*graph, mass, free, float(c_mass), float(c_stiff))
        solve = (float(tol) ** 2, *layout_plan.tensors(), _LAYOUT_CHUNK_NODES[layout], slots, int(max_iter), s.x, s.r,
                 s.p, s.threshold, s.rhs_sq, s.rr, s.status, s.alpha, s.beta, s.iterations, work.exchange,
                 work.sums_of(layout, layout_plan), work.counters)
        args = (*system, node_stiffness, rhs, *solve)
        if step_end is not None and step_end.rhs is not None:
            e, in_solve = step_end, step_end.rhs
            planes = (None,) * 3 if in_solve.planes is None else _contiguous(
                in_solve.planes.normals, in_solve.planes.offsets, in_solve.planes.stiffness)
            ran = bool(torch.ops.tensormass.hooke_node_steps(
                *system, in_solve.rest, in_solve.external, float(in_solve.w_coef), float(in_solve.rayleigh_mass),
                *planes, in_solve.u, rhs, node_stiffness, *solve, e.x, e.v, float(e.h), e.x_new, e.v_new, e.norms,
                e.summary, *work.end_work_of(layout, layout_plan), e.ring, e.ring_pos, bool(e.carry), int(e.steps)))
            e.done = ran
        elif step_end is not None and FUSED_STEP_END:
            e = step_end
            ran = bool(torch.ops.tensormass.hooke_node_solve_step(
                *args, e.x, e.v, e.dv_imposed, float(e.h), e.x_new, e.v_new, e.norms, e.summary,
                *work.end_work_of(layout, layout_plan), e.ring, e.ring_pos, bool(e.carry)))
            e.done = ran
        else:
            ran = bool(torch.ops.tensormass.hooke_node_solve(*args))
        if ran:
            work.layout = layout
            return True
        work.layout = None
        work.misfits.add(layout)
    return False


#: Whether a solve that ends an implicit Euler step also computes its right-hand side where it
#: can (``StepEnd.rhs``: ``hooke_node_steps``, chained steps in one kernel); off, the right-hand
#: side is its own op (``hooke_node_step_rhs``) before each solve. Tests compare the two;
#: benchmarks switch it (``TENSORMASS_SOLVE_STEP_RHS=0`` in the environment, or this flag).
SOLVE_STEP_RHS = os.environ.get("TENSORMASS_SOLVE_STEP_RHS", "1") != "0"


def steps_serve(group, node_stiffness: Optional[torch.Tensor], node_k: Optional[torch.Tensor],
                step_end: StepEnd) -> bool:
    """Whether ``hooke_node_steps`` serves these steps: :data:`SOLVE_STEP_RHS` and
    :data:`FUSED_STEP_END` (its solve ends each step), the hooke tensor
    form's own node graph (``node_k`` None; :func:`step_rhs_serves`), a contact stiffness buffer
    exactly where there are planes (3-D, of the state's dtype and device), no imposed velocity,
    and ``carry`` where the steps are more than one. (The solve may still not fit the device:
    :func:`system_solve` says.)"""
    e = step_end
    if (e.rhs.planes is None) != (node_stiffness is None) or not planes_serve(e.rhs.planes, e.x, node_stiffness):
        return False
    return (SOLVE_STEP_RHS and FUSED_STEP_END and hasattr(torch.ops.tensormass, "hooke_node_steps") and node_k is None
            and e.dv_imposed is None and (e.carry or e.steps == 1) and e.steps >= 1
            and step_rhs_serves(group, (e.x, e.v, e.rhs.rest, e.rhs.external)))


def planes_serve(planes, x: torch.Tensor, node_stiffness: Optional[torch.Tensor]) -> bool:
    """Whether the right-hand side's kernels take these contact ``planes`` (a ``contact.Planes``
    or None) for positions ``x [V, d]``: none, or 3-D positions, a contact stiffness buffer and
    planes of x's dtype and device."""
    return planes is None or (x.shape[1] == 3 and node_stiffness is not None and planes.normals.dtype == x.dtype
                              and planes.normals.device == x.device)


def step_rhs_serves(group, inputs=()) -> bool:
    """Whether :func:`step_rhs` computes ``group``'s step right-hand side in one op: the hooke
    tensor form over the node graph (:data:`HOOKE_MATVEC_LAYOUT` "node"), ``hooke_node_step_rhs``
    compiled, no gradient wanted through ``inputs``."""
    return HOOKE_MATVEC_LAYOUT == "node" and _node_layout(group, "node", tuple(inputs), "hooke_node_step_rhs")


def step_rhs(group, x: torch.Tensor, v: torch.Tensor, rest: torch.Tensor, mass: torch.Tensor,
             external: torch.Tensor, planes, h: float, w_coef: float, rayleigh_mass: float, u: torch.Tensor,
             rhs: torch.Tensor, node_stiffness: Optional[torch.Tensor]) -> bool:
    """Implicit Euler's right-hand side for the hooke tensor form in one pass over the nodes
    (``hooke_node_step_rhs``): into ``rhs [V, d]``, ``h (f((x - rest) + w_coef v) + external +
    contact(x) - Kc(x) (w_coef v) - r_M mass v)``, with ``u = x - rest`` into ``u [V, d]`` and,
    with ``planes`` (``contact.Planes``, 3-D), the contact stiffness into ``node_stiffness
    [V, 3, 3]``. ``mass`` ``[V]``. Returns False, having done nothing, where the op does not serve
    the group (see :func:`step_rhs_serves`)."""
    if not step_rhs_serves(group, (x, v, rest, mass, external)):
        return False
    x, v, rest, mass, external = _contiguous(x, v, rest, mass, external)
    graph = hooke_rows_graph(group)
    normals = offsets = stiffness = None
    if planes is not None:
        normals, offsets, stiffness = _contiguous(planes.normals, planes.offsets, planes.stiffness)
    torch.ops.tensormass.hooke_node_step_rhs(x, v, rest, *graph, mass, external, normals,
                                             offsets, stiffness, float(h), float(w_coef), float(rayleigh_mass), u,
                                             rhs, node_stiffness)
    return True
