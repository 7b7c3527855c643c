"""A TensorMass's forces, force differential and lumped masses as differentiable functions of
its material: what the adjoint of the implicit step (``solver.adjoint``) differentiates.

The model's groups hold what their kernels need precomputed from the material (the tensor
form's edge tensors, the cached Lame constants), so no gradient reaches a material parameter
through them. This view evaluates every group through the stress-form ops instead (the same
forces and differential, up to rounding: the tensor form is the stress form's sums regrouped),
with the Lame constants formed from the per-element values it is given at each call, so
autograd reaches them: per-element Young's modulus, Poisson ratio and density ``[N]`` in the
model's element numbering (the parts in the order they were packed).
"""
from __future__ import annotations

from typing import List, Optional

import torch

from .. import ops
from ..errors import SceneError
from ..ops import stress
from .groups import ElementGroup


class DifferentiableModel:
    """The elastic terms of ``model`` (a :class:`TensorMass` as built: no element removed or cut)
    as functions of per-element material values.

    Attributes:
        group_ids: per group, the model's element ids of its rows ``[N_g]`` (int64).
        young, poisson, density: the model's own per-element values ``[N]`` (detached).
    """

    def __init__(self, model):
        self.check(model)
        self.model = model
        like = model.rest
        self.group_ids: List[torch.Tensor] = []
        self._stress_groups: List[ElementGroup] = []
        young = like.new_empty(model.num_elements)
        poisson = like.new_empty(model.num_elements)
        density = like.new_empty(model.num_elements)
        for group in model.groups:
            ids, *values = model.group_sources(group)
            for full, value in zip((young, poisson, density), values):
                full[ids] = value
            self.group_ids.append(ids)
            self._stress_groups.append(_stress_group(model.rest, group, values[0], values[1]))
        self.young, self.poisson, self.density = young, poisson, density

    @staticmethod
    def check(model) -> None:
        """Raise SceneError where ``model`` has changed from what this view can be made of (a view
        made before the change holds the elements as they were)."""
        if "removed" in model._buffers:
            raise SceneError("gradients through a model whose elements were removed or cut are not available "
                             "yet: build a simulator of the remaining mesh")

    def per_element(self, name: str, value: Optional[torch.Tensor]) -> torch.Tensor:
        """``value`` (a 0-dim or ``[N]`` tensor; None: the model's own) as ``[N]`` over the model's
        elements, its autograd graph kept."""
        own = getattr(self, name)
        if value is None:
            return own
        if value.dim() == 0:
            return value.expand(own.shape[0])
        return value

    def lumped_mass(self, density: torch.Tensor) -> torch.Tensor:
        """Lumped masses ``[V]`` for per-element densities ``[N]``: the model's own sum (each element
        gives rho V / n to each of its n nodes), differentiable in the densities."""
        return self.model._lumped_mass([(group.elements, density[ids] * group.measure)
                                        for group, ids in zip(self._stress_groups, self.group_ids)])

    def step_forces(self, u: torch.Tensor, w: torch.Tensor, force_coef: float, stiffness_coef: float,
                    young: torch.Tensor, poisson: torch.Tensor) -> torch.Tensor:
        """``force_coef f(u) + stiffness_coef K(u) w`` ``[V, d]`` (implicit Euler's elastic terms) at
        displacements ``u [V, d]`` along ``w [V, d]`` for the per-element ``young, poisson [N]``:
        the corotational rotations at u (their derivative included), the stvk tangent the model's
        solver uses (exact or definite). A hooke group is linear, f(u) = K u: one product,
        K (force_coef u + stiffness_coef w), whose backward is one product and one pass over the
        elements for the moduli; a corotational group likewise one product at u + (stiffness_coef
        / force_coef) w with the rotations of u. ``force_coef`` must not be 0 (it is the step's h)."""
        total = None
        for group, ids in zip(self._stress_groups, self.group_ids):
            group.young, group.poisson = young[ids], poisson[ids]  # read by ops.stress.lame at each call
            if group.model == "hooke":
                term = ops.dforces(group, u, force_coef * u + stiffness_coef * w)
            elif group.model == "corotational":
                # with R = R(u) held in the op, f(u; R) is affine in u and K_R w = f(u + w; R) - f(u; R):
                # a f(u) + b K_R w = a f(u + (b / a) w; R), one op whose backward forms R's cotangent
                # and the (lam, mu) gradients once
                rotations = _Rotations.apply(u, group)
                term = force_coef * ops.forces(group, u + (stiffness_coef / force_coef) * w, rotations)
            else:
                state = ops.linearize(group, u)
                term = force_coef * ops.forces(group, u, state) + stiffness_coef * ops.dforces(group, u, w, state)
            total = term if total is None else total + term
        return total


class _Rotations(torch.autograd.Function):
    """A corotational group's rotations at ``u [V, d]`` (``ops.linearize``) ``[N, d, d]``, whose
    backward sums the elements' cotangents on the nodes through the group's plan (one
    deterministic gather) rather than autograd's scatter of ``u[elements]`` (a sort per call)."""

    @staticmethod
    def forward(ctx, u, group):
        rotations = ops.linearize(group, u)
        ctx.save_for_backward(u, rotations)
        ctx.group = group
        return rotations

    @staticmethod
    def backward(ctx, grad):
        u, rotations = ctx.saved_tensors
        per_element = stress.corotational_rotations_vjp(ctx.group, u, rotations, grad)
        return ops.node_gather(per_element, ctx.group.plan), None


def _stress_group(rest: torch.Tensor, group: ElementGroup, young: torch.Tensor, poisson: torch.Tensor) -> ElementGroup:
    """A stress-form group of ``group``'s elements (its own when it has the stress form: a new one
    all the same, whose material this view sets at each call), with ``group``'s measure (a
    membrane's thickness in it)."""
    tangent = group.tangent if group.form == "stress" else "exact"  # the tensor form's stvk is exact
    twin = ElementGroup(rest, group.elements, young, poisson, group.model, "stress", None,
                        group.rotation or "polar", tangent)
    twin.measure = group.measure.detach().clone()
    return twin


def check_per_element(name: str, value, count: int, like: torch.Tensor, low: float,
                      high: float) -> Optional[torch.Tensor]:
    """``value`` (None, a number, a 0-dim or ``[count]`` tensor) as a tensor of ``like``'s dtype and
    device (its autograd graph kept), after checking its shape and that it is finite and in
    (low, high); None stays None."""
    if value is None:
        return None
    t = value if isinstance(value, torch.Tensor) else torch.as_tensor(value)
    if t.dim() not in (0, 1) or (t.dim() == 1 and t.shape[0] != count):
        raise SceneError(f"{name} has shape {tuple(t.shape)}; expected a scalar or [{count}] (one per element)")
    if not t.is_floating_point():
        raise SceneError(f"{name} must be a floating-point tensor, got {t.dtype}")
    t = t.to(dtype=like.dtype, device=like.device)
    with torch.no_grad():
        bad = ~torch.isfinite(t) | (t <= low) | (t >= high)
        if bool(bad.any()):
            worst = t[bad].reshape(-1)[0].item()
            raise SceneError(f"{name} must be finite and in ({low:g}, {high:g}); got {worst!r}")
    return t

