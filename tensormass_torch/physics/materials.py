"""Materials: Young's modulus, Poisson ratio, density and the constitutive model.

Parameters are scalars or per-element tensors ``[N]`` (heterogeneous objects). Triangles are
plane-stress membranes of the given ``thickness``: their rest measure is area x thickness.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Union

import torch

from ..errors import MaterialError
from ..ops.reference.stress_form import lame  # noqa: F401 (the materials' Lame constants, public here)

#: Constitutive models this build implements (``Material(model=...)``).
MODELS = ("hooke", "stvk", "corotational")
#: Rotation extraction of the corotational model: polar decomposition, or SOFA's QR frame.
ROTATIONS = ("polar", "qr")
TANGENTS = ("auto", "exact", "definite")

Scalar = Union[float, int, torch.Tensor]


def _check_range(name: str, value: Scalar, low: float, high: float, low_open=True, high_open=True):
    """Raise MaterialError unless every entry of ``value`` lies in (low, high) and is finite."""
    t = torch.as_tensor(value, dtype=torch.float64).detach()
    if t.numel() == 0:
        raise MaterialError(f"{name} is empty")
    if not torch.isfinite(t).all():
        raise MaterialError(f"{name} must be finite, got {value!r}")
    below = (t <= low) if low_open else (t < low)
    above = (t >= high) if high_open else (t > high)
    bad = below | above
    if bad.any():
        lo = "(" if low_open else "["
        hi = ")" if high_open else "]"
        worst = t[bad].flatten()[0].item()
        raise MaterialError(f"{name} must lie in {lo}{low}, {high}{hi}, got {worst!r}")


@dataclass(frozen=True)
class Material:
    """An elastic material.

    Args:
        young: Young's modulus E in Pa, > 0; a float or a per-element tensor ``[N]``.
        poisson: Poisson ratio nu in (-1, 0.5); float or ``[N]``.
        density: mass density rho in kg/m^3 (kg/m^2 per unit thickness for membranes), > 0.
        model: ``"hooke"`` (linear), ``"stvk"`` (St Venant-Kirchhoff) or ``"corotational"``
            (linear in a per-element rotated frame; native kernels for both rotations).
        thickness: membrane thickness in m (triangles only), > 0.
        rotation: corotational rotations by ``"polar"`` decomposition or SOFA's ``"qr"`` frame.
        tangent: the force differential the solvers use (forces and energy never change):
            ``"exact"``; ``"definite"`` (``stvk`` only): the positive part of the second
            Piola-Kirchhoff stress in the geometric term, so the linear system stays positive
            definite under compression, where the exact ``stvk`` tangent is indefinite and CG
            breaks down (the step is then a quasi-Newton step); ``"auto"`` (default):
            ``"definite"`` for ``stvk`` in the stress form, ``"exact"`` otherwise (the hooke and
            corotational tangents are positive semi-definite already). See :meth:`tangent_for`.
    """

    young: Scalar
    poisson: Scalar
    density: Scalar = 1000.0
    model: str = "hooke"
    thickness: Scalar = 1.0
    rotation: str = "polar"
    tangent: str = "auto"

    def __post_init__(self):
        if not isinstance(self.model, str) or self.model not in MODELS:
            raise MaterialError(f"unknown material model {self.model!r}; known models: {', '.join(MODELS)}")
        if self.rotation not in ROTATIONS:
            raise MaterialError(f"unknown rotation {self.rotation!r}; known: {', '.join(ROTATIONS)}")
        if self.tangent not in TANGENTS:
            raise MaterialError(f"unknown tangent {self.tangent!r}; known: {', '.join(TANGENTS)}")
        if self.tangent == "definite" and self.model != "stvk":
            raise MaterialError(f"tangent='definite' applies to the stvk model only (the {self.model} tangent is "
                                "positive semi-definite already)")
        _check_range("young", self.young, 0.0, math.inf)
        _check_range("poisson", self.poisson, -1.0, 0.5)
        _check_range("density", self.density, 0.0, math.inf)
        _check_range("thickness", self.thickness, 0.0, math.inf)

    def tangent_for(self, form: str) -> str:
        """The tangent the solvers use for this material evaluated in ``form`` (``"stress"`` or
        ``"tensor"``): ``tangent`` itself unless it is ``"auto"``, which is ``"definite"`` for
        ``stvk`` in the stress form (a compressed stvk body keeps a solvable implicit system) and
        ``"exact"`` everywhere else (the tensor form has no definite tangent)."""
        if self.tangent != "auto":
            return self.tangent
        return "definite" if self.model == "stvk" and form == "stress" else "exact"

    def per_element(self, name: str, num_elements: int, like: torch.Tensor) -> torch.Tensor:
        """Parameter ``name`` as a tensor ``[N]`` of ``like``'s dtype and device.

        A tensor parameter keeps its autograd graph (gradients flow to material parameters).
        """
        value = getattr(self, name)
        t = torch.as_tensor(value, dtype=like.dtype, device=like.device)
        if t.dim() == 0:
            return t.expand(num_elements)
        if t.shape != (num_elements,):
            raise MaterialError(f"{name} has shape {tuple(t.shape)}; expected a scalar or [{num_elements}]")
        return t
