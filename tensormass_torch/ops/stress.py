"""The stress-form op family (``csrc/stress/``): kernel 1 of the stress form (hooke, stvk,
corotational) at element level, into PartialForce, and fused with kernel 2, and the corotational
rotations. Each op's pure-torch reference, fake kernel and autograd, and the group-level wrappers
that feed the ops a group's tensors.

    stress_element_forces / _dforces     [N, n, d]
    stress_partial_forces / _dforces     PartialForce [N_n, V, d] (slots >= incidences[i] unset)
    stress_forces / stress_dforces       [V, d]
    corotational_rotations               [N, d, d] (method 0 = SOFA's QR frame, 1 = polar)

Autograd: forces: d(g . f(u))/du = dforces(u, g) (the stiffness is symmetric: f = -grad W),
except for the corotational model with R recomputed inside the op (f is not an energy gradient
through R(u): reference vjp); with ``rotations`` given, R is an input: the u-gradient is
dforces(u, g, R) and R gets the reference vjp. dforces: d(g . K(u) du)/d du = dforces(u, g).
lam, mu: the forces are linear in (lam, mu), so the gradient per element is the dot of the
element's cotangent with its forces at (lam, mu) = (1, 0) and (0, 1) (not the definite stvk
tangent, whose positive part of S is not linear in them: the reference's vjp). Every other gradient
(geometry, u in the element-level and padded ops, u in stvk dforces) is the reference's vjp, so
every input that requires grad gets a correct one; double backward works where the reference
path does.
"""
from __future__ import annotations

import functools
from typing import Optional

import torch

from . import library
from .library import (
    MODEL_IDS,
    ROTATION_IDS,
    OpDef,
    fake_element,
    fake_element_d,
    fake_nodes,
    fake_partial,
    fake_partial_d,
    gather,
    model_name,
    op,
    plan_indices,
    scatter,
    unchanged,
)
from .reference import corotational, stress_form
from .reference.stress_form import small_matmul

__all__ = ["corotational_rotations", "corotational_rotations_vjp", "stress_args", "lame"]

# ---------------------------------------------------------------------------------------------
# References
# ---------------------------------------------------------------------------------------------


def _qr_rotations(u_e, rest):
    if rest is None:
        raise ValueError("the corotational model (model 2) needs rest_elements [N, n, 3]")
    return corotational.qr_rotations(rest + u_e, rest)


def _ref_corotational_rotations(u, elements, m, proj, rest, method, known=None):
    """Element rotations ``[N, d, d]`` at u: method 0 = SOFA's QR frame, 1 = polar (membranes map
    their rest normal onto the current one first, as ``ops.linearize``). ``known``: the polar
    factors as the kernel computed them (only their derivative is then taken here)."""
    return _element_rotations_at(u[elements], m, proj, rest, method, known)


def _element_rotations_at(u_e, m, proj, rest, method, known=None):
    """:func:`_ref_corotational_rotations` from the elements' nodal displacements ``u_e [N, n, d]``."""
    if int(method) == ROTATION_IDS["qr"]:
        return _qr_rotations(u_e, rest)
    if int(method) != ROTATION_IDS["polar"]:
        raise ValueError(f"unknown rotation method {method!r} (0 = qr, 1 = polar)")
    F = corotational.deformation_gradient(u_e, m, proj)
    if proj is None:
        return corotational.polar_rotations(F, rotations=known)
    x_e = rest + u_e

    def unit_normal(p):
        n = torch.linalg.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        return n / torch.linalg.vector_norm(n, dim=1, keepdim=True)

    return corotational.polar_rotations(F, unit_normal(rest), unit_normal(x_e), rotations=known)


def _element_rotations(u_e, rest, rotations):
    """The rotations the corotational stress ops use: those given, else SOFA's QR frame at u."""
    return rotations if rotations is not None else _qr_rotations(u_e, rest)


def _ref_stress_element_forces(u, elements, m, vol, lam, mu, proj, model, rest=None, rotations=None):
    name = model_name(model)
    if name == "corotational":
        u_e = u[elements]
        return corotational.forces(u_e, m, vol, lam, mu, _element_rotations(u_e, rest, rotations), proj)
    return stress_form.FORCES[name](u[elements], m, vol, lam, mu, proj)


def _ref_stress_element_dforces(u, du, elements, m, vol, lam, mu, proj, model, rest=None, rotations=None):
    name = model_name(model)
    if name == "corotational":
        return corotational.dforces(du[elements], m, vol, lam, mu,
                                    _element_rotations(u[elements], rest, rotations), proj)
    return stress_form.DFORCES[name](u[elements], du[elements], m, vol, lam, mu, proj)


def _ref_stress_partial_forces(u, elements, force_index, num_slots, m, vol, lam, mu, proj, model, rest=None,
                               rotations=None):
    f = _ref_stress_element_forces(u, elements, m, vol, lam, mu, proj, model, rest, rotations)
    return scatter(f, elements, force_index, num_slots, u.shape[0])


def _ref_stress_partial_dforces(u, du, elements, force_index, num_slots, m, vol, lam, mu, proj, model,
                                rest=None, rotations=None):
    f = _ref_stress_element_dforces(u, du, elements, m, vol, lam, mu, proj, model, rest, rotations)
    return scatter(f, elements, force_index, num_slots, u.shape[0])


def _ref_stress_forces(u, elements, force_index, num_slots, incidences, m, vol, lam, mu, proj, model, rest=None,
                       rotations=None):
    f = _ref_stress_element_forces(u, elements, m, vol, lam, mu, proj, model, rest, rotations)
    return gather(f, elements, force_index, num_slots, incidences)


def _ref_stress_dforces(u, du, elements, force_index, num_slots, incidences, m, vol, lam, mu, proj, model,
                       rest=None, rotations=None):
    f = _ref_stress_element_dforces(u, du, elements, m, vol, lam, mu, proj, model, rest, rotations)
    return gather(f, elements, force_index, num_slots, incidences)

# ---------------------------------------------------------------------------------------------
# Fake kernels and autograd
# ---------------------------------------------------------------------------------------------


def _fake_rotations(u, elements, *_):
    return u.new_empty((elements.shape[0], u.shape[1], u.shape[1]))


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
            f = op("stress_element_dforces")(u, du, elements, m, vol, a, b, proj, model, rest, rotations)
        else:
            u, elements = inputs[0], inputs[1]
            f = op("stress_element_forces")(u, elements, m, vol, a, b, proj, model, rest, rotations)
        return (g_e * f).sum((1, 2))

    return (at(ones, zeros) if need_lam else None), (at(zeros, ones) if need_mu else None)


def _rotation_cotangent(name, inputs, grad):
    """d(grad . out)/dR ``[N, d, d]`` for the corotational stress ops with the rotations given.

    The op's element output is f_j = -vol R sigma m_j with sigma = C(P sym(R^T A - P0) P): for the
    forces A = F = P + grad U (P0 = P), for the differential A = grad dU (P0 = 0); C the isotropic
    stiffness (lam, mu) on the plane of P (I for full-dimensional elements). With G = sum_j g_j m_j
    (x) (g the element's cotangent), grad . out = -vol <R sigma, G>, and C being self-adjoint,

        dL/dR = -vol (G sigma + A sigma_g),   sigma_g = C(P sym(R^T G) P),

    sigma_g being the stress of the differential along g: a few products of 3x3 matrices per
    element, where differentiating the reference retraces its whole graph."""
    m, vol, lam, mu, proj, _, _, rotations = inputs[-8:]
    dforce = "dforces" in name
    elements = inputs[2] if dforce else inputs[1]
    source = inputs[1] if dforce else inputs[0]  # du, or u
    g_e = _element_cotangent(name, inputs, grad)
    A = stress_form.displacement_gradient(source[elements], m)
    rotations_t = rotations.transpose(-1, -2)
    strain = small_matmul(rotations_t, A)
    if not dforce:
        plane = corotational._plane(m, proj)
        A = A + plane
        strain = strain + small_matmul(rotations_t, plane) - plane  # R^T F - P
    G = stress_form.displacement_gradient(g_e, m)
    sigma = stress_form._isotropic(stress_form._project(stress_form._sym(strain), proj), lam, mu, proj)
    sigma_g = stress_form._isotropic(stress_form._project(stress_form._sym(small_matmul(rotations_t, G)), proj),
                                     lam, mu, proj)
    return -vol[:, None, None] * (small_matmul(G, sigma) + small_matmul(A, sigma_g))


def _rotations_gradients(inputs, g, needs):
    """The rotations op's u-gradient: polar factors computed again by the kernel (a product per
    element, not the reference's Newton passes and their graph), only their derivative through
    the reference; SOFA's QR frame (closed form, cheap) through the reference."""
    u, elements, m, proj, rest, method = inputs
    if not needs[0] or int(method) != ROTATION_IDS["polar"]:
        return {}
    with torch.no_grad():
        known = op("corotational_rotations")(*inputs)
    return library.reference_vjp(functools.partial(_ref_corotational_rotations, known=known), inputs, [0], g)


def _fast_gradients(name):
    """The gradients the stress ops compute themselves (see the module's docstring)."""
    fused = name in ("stress_forces", "stress_dforces")
    dforce = name.endswith("dforces")

    def fast_gradients(inputs, g, needs):
        fast = {}
        # The stress ops end with (..., proj, model, rest_elements, rotations).
        corot = int(inputs[-3]) == MODEL_IDS["corotational"]
        # R recomputed inside the op from u (no rotations given) makes the forces depend on u through R
        r_of_u = corot and inputs[-1] is None
        if fused:
            u_pos, du_pos = 0, 1
            target = du_pos if dforce else u_pos  # d/du of f(u) and d/d(du) of K(u) du: both K(u) g
            # corotational with R recomputed from u: f(u) = -R(u) K (R(u)^T x - X) is not the
            # gradient of an energy through R, so df/du != dforces (R fixed): its u-gradient goes
            # through the reference (qr_rotations differentiated). With R given, df/du is
            # dforces(u, ., R), and R's own gradient is the reference vjp. dforces is linear in du
            # with R fixed and K symmetric: d/d(du) is fast.
            if needs[target] and not (r_of_u and not dforce):
                args = list(inputs)
                if not dforce:
                    args.insert(1, g)
                    if int(inputs[-3]) == MODEL_IDS["stvk_definite"]:
                        args[-3] = MODEL_IDS["stvk"]  # the forces' Jacobian is the exact tangent
                else:
                    args[1] = g
                fast[target] = op("stress_dforces")(*args)
            if dforce and needs[u_pos] and (int(inputs[-3]) == MODEL_IDS["hooke"] or (corot and not r_of_u)):
                fast[u_pos] = None  # K does not depend on u: hooke, corotational with R given
        rotations_pos = len(inputs) - 1
        if corot and not r_of_u and needs[rotations_pos]:
            fast[rotations_pos] = _rotation_cotangent(name, inputs, g)
        lam_pos, mu_pos = len(inputs) - 6, len(inputs) - 5
        # the definite tangent's S+ is not linear in (lam, mu): its gradient is the reference's vjp
        definite = dforce and int(inputs[-3]) == MODEL_IDS["stvk_definite"]
        if (needs[lam_pos] or needs[mu_pos]) and not definite:
            fast[lam_pos], fast[mu_pos] = _lame_gradients(name, inputs, g, needs[lam_pos], needs[mu_pos])
        return fast

    return fast_gradients



def _example(name):
    def example(device, dtype):
        ex = library.Example(device, dtype, uniform="_partial_" in name)
        model = "corotational" if name == "corotational_rotations" else "stvk"
        geometry = ex.stress(model)
        plan = (ex.force_index, ex.num_slots)
        args = {
            "stress_element_forces": (ex.u, ex.elements, *geometry),
            "stress_element_dforces": (ex.u, ex.du, ex.elements, *geometry),
            "stress_partial_forces": (ex.u, ex.elements, *plan, *geometry),
            "stress_partial_dforces": (ex.u, ex.du, ex.elements, *plan, *geometry),
            "stress_forces": (ex.u, ex.elements, *plan, ex.incidences, *geometry),
            "stress_dforces": (ex.u, ex.du, ex.elements, *plan, ex.incidences, *geometry),
            "corotational_rotations": (ex.u, ex.elements, ex.m, None, geometry[6], ROTATION_IDS["qr"]),
        }[name]
        return args, {}

    return example


_FAKES = {"stress_element_forces": fake_element, "stress_element_dforces": fake_element_d,
          "stress_partial_forces": fake_partial, "stress_partial_dforces": fake_partial_d,
          "stress_forces": fake_nodes, "stress_dforces": fake_nodes}
_REFERENCES = {"stress_element_forces": _ref_stress_element_forces,
               "stress_element_dforces": _ref_stress_element_dforces,
               "stress_partial_forces": _ref_stress_partial_forces,
               "stress_partial_dforces": _ref_stress_partial_dforces,
               "stress_forces": _ref_stress_forces, "stress_dforces": _ref_stress_dforces}

_DEFINED = {"stress_partial_forces": library.partial_defined(1), "stress_partial_dforces": library.partial_defined(2)}
OPS = tuple(OpDef(name, _REFERENCES[name], _FAKES[name], _fast_gradients(name), example=_example(name),
                  defined=_DEFINED.get(name)) for name in _REFERENCES) + (
    OpDef("corotational_rotations", _ref_corotational_rotations, _fake_rotations, _rotations_gradients,
          example=_example("corotational_rotations")),)
library.define(OPS, lambda: library.register(OPS))

# ---------------------------------------------------------------------------------------------
# Group-level wrappers: a stress-form group's tensors as the ops take them
# ---------------------------------------------------------------------------------------------


def lame(group):
    """(lam, mu) of a stress-form group; cached on the group while young/poisson are the same
    unmodified tensors and need no gradient (then recomputed at every call, for autograd)."""
    tensors = (group.young, group.poisson)
    if any(t.requires_grad for t in tensors):
        return group.lame()
    cache = group.__dict__.get("_native_lame")
    if unchanged(cache, tensors):
        return cache[2]
    lam, mu = group.lame()
    value = (lam.contiguous(), mu.contiguous())
    group.__dict__["_native_lame"] = (tensors, tuple(t._version for t in tensors), value)
    return value


def stress_args(group, u: Optional[torch.Tensor] = None, rotations: Optional[torch.Tensor] = None):
    """The trailing arguments of the stress ops for ``group``. Corotational: the ``rotations``
    ``[N, d, d]`` of the linearisation (computed at ``u`` when None), so no kernel recomputes R;
    with neither, the rest nodes (the kernels then recompute SOFA's QR frame from u per call)."""
    lam, mu = lame(group)
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


def corotational_rotations_vjp(group, u: torch.Tensor, rotations: torch.Tensor, grad: torch.Tensor) -> torch.Tensor:
    """d(grad . R(u))/du per element node ``[N, n, d]`` (not yet summed on the nodes: the caller
    gathers it with the group's plan, deterministically) for a corotational group's rotations
    ``rotations [N, d, d]`` at ``u [V, d]`` and their cotangent ``grad [N, d, d]``: the polar map's
    derivative at the factors given, SOFA's QR frame's through its closed form."""
    index, _, _ = plan_indices(group.plan)
    u_e = u.detach()[index].requires_grad_(True)
    with torch.enable_grad():
        value = _element_rotations_at(u_e, group.shape_vectors, group.projector, getattr(group, "rest_elements", None),
                                      ROTATION_IDS[group.rotation], rotations.detach())
        (cotangent,) = torch.autograd.grad(value, u_e, grad)
    return cotangent


def corotational_rotations(group, u: torch.Tensor) -> torch.Tensor:
    """The element rotations ``[N, d, d]`` of a corotational group at displacements ``u [V, d]``
    (``group.rotation``: "qr" or "polar"), computed once per linearisation."""
    index, _, _ = plan_indices(group.plan)
    rest = getattr(group, "rest_elements", None)
    proj = group.projector
    return torch.ops.tensormass.corotational_rotations(
        u.contiguous(), index, group.shape_vectors.contiguous(), None if proj is None else proj.contiguous(),
        None if rest is None else rest.contiguous(), ROTATION_IDS[group.rotation])
