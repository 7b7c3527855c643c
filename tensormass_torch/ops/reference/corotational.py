"""Corotational linear elasticity (Nesme & Payan 2005; SOFA's TetrahedronFEMForceField "large").

Per element a rotation R is extracted from the deformation gradient F = P + grad U (P the
identity, or the tangent projector of a membrane), and linear elasticity acts on the unrotated
displacement: grad U' = R^T F - P, eps' = P sym(grad U') P, sigma' = lam tr(eps') P + 2 mu eps',
f_j = -vol R sigma' m_j, i.e. f = -R K (R^T x - X). With R held fixed this is the gradient of
W = vol psi(eps'); the differential is R K R^T dx. Shapes as in stress_form: u [N, n, d],
m [N, n, d], vol/lam/mu [N], proj [N, d, d] or None, rotations [N, d, d].
"""
from __future__ import annotations

import torch

from .stress_form import _energy_density, _isotropic, _nodal, _project, _sym, displacement_gradient


def _plane(m, proj):
    d = m.shape[-1]
    return torch.eye(d, dtype=m.dtype, device=m.device).expand(m.shape[0], d, d) if proj is None else proj


def deformation_gradient(u, m, proj=None):
    """F = P + grad U ``[N, d, d]`` (P = I for full-dimensional elements)."""
    return _plane(m, proj) + displacement_gradient(u, m)


def polar_rotations(F: torch.Tensor, rest_normals=None, normals=None) -> torch.Tensor:
    """Rotation factor of the polar decomposition F = R S, a proper rotation (det R = +1) ``[N, d, d]``.

    Inverted elements (det F < 0) get the closest proper rotation: the singular vector of the
    smallest singular value is flipped. For membranes, F maps the rest plane only, so the rest
    normal is mapped onto the current normal first (``rest_normals``, ``normals`` ``[N, 3]``).
    """
    if rest_normals is not None:
        F = F + normals[:, :, None] * rest_normals[:, None, :]
    return _PolarRotation.apply(F)[0]


class _PolarRotation(torch.autograd.Function):
    """F -> R of F = R S, with the polar factor's own derivative rather than the SVD's.

    With F = U diag(s) V^T (s signed: the last one negated where R flips it) and R = U V^T, a
    change dF turns R by dR = R W, W skew with W S + S W = R^T dF - dF^T R (the skew part of
    R^T dF = W S + dS), so in V's basis W_ij = (V^T (R^T dF - dF^T R) V)_ij / (s_i + s_j). Its
    vector-Jacobian product is dL/dF = 2 R skew(V (M o (V^T R^T G V)) V^T) with M_ij = 1 / (s_i
    + s_j). Unlike the SVD's backward (1 / (s_i^2 - s_j^2)), it is finite at repeated singular
    values (at rest F = I: all equal); only a collapsed element (s_i + s_j = 0) has none."""

    generate_vmap_rule = True

    @staticmethod
    def forward(F):
        U, s, Vh = torch.linalg.svd(F)
        det = torch.linalg.det(U @ Vh)
        flip = torch.ones_like(s)
        flip[..., -1] = torch.where(det < 0, -1.0, 1.0)
        return (U * flip[..., None, :]) @ Vh, s * flip, Vh.transpose(-1, -2)

    @staticmethod
    def setup_context(ctx, inputs, output):
        rotations, signed, V = output
        ctx.mark_non_differentiable(signed, V)
        ctx.save_for_backward(rotations, signed, V)

    @staticmethod
    def backward(ctx, grad, _signed, _V):
        R, s, V = ctx.saved_tensors
        inner = V.transpose(-1, -2) @ (R.transpose(-1, -2) @ grad) @ V
        total = s[..., :, None] + s[..., None, :]
        tiny = torch.finfo(s.dtype).tiny
        total = torch.where(total.abs() > tiny, total, torch.full_like(total, tiny))
        C = V @ (inner / total) @ V.transpose(-1, -2)
        return R @ (C - C.transpose(-1, -2))


def qr_rotations(x_elem: torch.Tensor, rest_elem: torch.Tensor) -> torch.Tensor:
    """SOFA's "large" frame: axes from the first edge and the normal of the first face.

    x_elem, rest_elem ``[N, n, 3]`` -> R ``[N, 3, 3]`` with R = frame(x)^T frame(X).
    """
    def frame(p):
        ex = p[:, 1] - p[:, 0]
        ez = torch.linalg.cross(ex, p[:, 2] - p[:, 0])
        ey = torch.linalg.cross(ez, ex)
        axes = torch.stack([ex, ey, ez], dim=1)
        return axes / torch.linalg.vector_norm(axes, dim=2, keepdim=True)

    return frame(x_elem).transpose(1, 2) @ frame(rest_elem)


def _rotated_strain(u, m, rotations, proj):
    F = deformation_gradient(u, m, proj)
    return _project(_sym(rotations.transpose(1, 2) @ F - _plane(m, proj)), proj)


def forces(u, m, vol, lam, mu, rotations, proj=None):
    """Element forces ``[N, n, d]`` for the given rotations."""
    stress = _isotropic(_rotated_strain(u, m, rotations, proj), lam, mu, proj)
    return _nodal(rotations @ stress, m, vol)


def energy(u, m, vol, lam, mu, rotations, proj=None):
    """Element energies ``[N]`` with the rotations held fixed."""
    return vol * _energy_density(_rotated_strain(u, m, rotations, proj), lam, mu)


def dforces(du, m, vol, lam, mu, rotations, proj=None):
    """(dF/du) du with R fixed: -vol R sigma(P sym(R^T grad dU) P) m_j ``[N, n, d]``."""
    d_strain = _project(_sym(rotations.transpose(1, 2) @ displacement_gradient(du, m)), proj)
    return _nodal(rotations @ _isotropic(d_strain, lam, mu, proj), m, vol)
