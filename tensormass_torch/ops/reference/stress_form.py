"""Stress form: element forces through grad U, the strain, the stress and P m_j.

Shapes: N elements, n nodes per element, d dimensions.
    u   nodal displacements per element  [N, n, d]
    m   shape vectors                    [N, n, d]
    vol rest measure                     [N]
    lam, mu  Lamé constants              [N]
    proj  tangent projector of membranes [N, d, d], or None (identity: tets, 2-D triangles)

With grad U = sum_j u_j (x) m_j, the force of an element on its node j is
f_j = -vol * P m_j, where P is the first Piola-Kirchhoff stress (sigma for ``hooke``).
Membranes use strains projected on their rest plane, E_2D = P E P, which leaves this formula
unchanged because the stress then lies in the plane too.
"""
from __future__ import annotations

import torch


def lame(young: torch.Tensor, poisson: torch.Tensor, plane_stress: bool = False):
    """Lamé constants (lam, mu) from E and nu; ``plane_stress`` gives lam = E nu / (1 - nu^2).

    Shapes follow the inputs (``[N]``).
    """
    mu = young / (2.0 * (1.0 + poisson))
    if plane_stress:
        lam = young * poisson / (1.0 - poisson * poisson)
    else:
        lam = young * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson))
    return lam, mu


def displacement_gradient(u: torch.Tensor, m: torch.Tensor) -> torch.Tensor:
    """grad U = sum_j u_j (x) m_j: ``[N, d, d]``."""
    return small_matmul(u.transpose(-1, -2), m)


def small_matmul(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """``a @ b`` for batches of small matrices ``[..., p, q] x [..., q, r]``. On a GPU as q
    broadcast products summed (a few elementwise kernels: ``@`` on a large batch of 3x3 matrices
    launches batched GEMMs that take far longer than the arithmetic, and one broadcast product
    summed over its middle dimension a strided reduction); on a CPU ``@``, which is faster there."""
    if a.device.type == "cpu":
        return a @ b
    out = a[..., :, :1] * b[..., :1, :]
    for k in range(1, a.shape[-1]):
        out = out + a[..., :, k:k + 1] * b[..., k:k + 1, :]
    return out


def _sym(a: torch.Tensor) -> torch.Tensor:
    return 0.5 * (a + a.transpose(-1, -2))


def _project(a: torch.Tensor, proj) -> torch.Tensor:
    return a if proj is None else proj @ a @ proj


def _trace(a: torch.Tensor) -> torch.Tensor:
    return a.diagonal(dim1=-2, dim2=-1).sum(-1)


def _isotropic(strain: torch.Tensor, lam: torch.Tensor, mu: torch.Tensor, proj) -> torch.Tensor:
    """lam tr(strain) I_plane + 2 mu strain: ``[N, d, d]``."""
    identity = torch.eye(strain.shape[-1], dtype=strain.dtype, device=strain.device) if proj is None else proj
    return (lam * _trace(strain))[:, None, None] * identity + (2.0 * mu)[:, None, None] * strain


def _nodal(stress: torch.Tensor, m: torch.Tensor, vol: torch.Tensor) -> torch.Tensor:
    """f_j = -vol * stress m_j: ``[N, n, d]``."""
    return -vol[:, None, None] * torch.einsum("nab,njb->nja", stress, m)


def _energy_density(strain, lam, mu):
    tr = _trace(strain)
    return 0.5 * lam * tr * tr + mu * (strain * strain).sum((-1, -2))


def hooke_strain(u, m, proj):
    """Linear strain eps = sym(grad U), projected for membranes: ``[N, d, d]``."""
    return _project(_sym(displacement_gradient(u, m)), proj)


def green_strain(grad_u, proj):
    """Green strain E = sym(grad U) + 1/2 grad U^T grad U (no I cancellation), projected."""
    return _project(_sym(grad_u) + 0.5 * grad_u.transpose(-1, -2) @ grad_u, proj)


def hooke_forces(u, m, vol, lam, mu, proj=None):
    """Element forces of linear elasticity: ``[N, n, d]``."""
    return _nodal(_isotropic(hooke_strain(u, m, proj), lam, mu, proj), m, vol)


def hooke_energy(u, m, vol, lam, mu, proj=None):
    """Element energies ``[N]``."""
    return vol * _energy_density(hooke_strain(u, m, proj), lam, mu)


def hooke_dforces(u, du, m, vol, lam, mu, proj=None):
    """(dF/du) du per element: linear, so the forces of du. ``[N, n, d]``."""
    return hooke_forces(du, m, vol, lam, mu, proj)


def stvk_forces(u, m, vol, lam, mu, proj=None):
    """Element forces of St Venant-Kirchhoff: f_j = -vol F S m_j. ``[N, n, d]``."""
    grad_u = displacement_gradient(u, m)
    second_pk = _isotropic(green_strain(grad_u, proj), lam, mu, proj)
    first_pk = second_pk + grad_u @ second_pk  # F S with F = I + grad U
    return _nodal(first_pk, m, vol)


def stvk_energy(u, m, vol, lam, mu, proj=None):
    """Element energies ``[N]``."""
    return vol * _energy_density(green_strain(displacement_gradient(u, m), proj), lam, mu)


def stvk_dforces(u, du, m, vol, lam, mu, proj=None):
    """(dF/du) du per element: dP = dF S + F dS, dS = C : sym(F^T dF). ``[N, n, d]``."""
    grad_u = displacement_gradient(u, m)
    grad_du = displacement_gradient(du, m)
    second_pk = _isotropic(green_strain(grad_u, proj), lam, mu, proj)
    d_strain = _project(_sym(grad_du + grad_u.transpose(-1, -2) @ grad_du), proj)
    d_second_pk = _isotropic(d_strain, lam, mu, proj)
    d_first_pk = grad_du @ second_pk + d_second_pk + grad_u @ d_second_pk
    return _nodal(d_first_pk, m, vol)


def positive_part(sym: torch.Tensor) -> torch.Tensor:
    """The positive part of symmetric matrices ``[..., d, d]``: negative eigenvalues set to 0.
    Differentiable everywhere, repeated eigenvalues included (:class:`_PositivePart`)."""
    return _PositivePart.apply(sym)[0]


class _PositivePart(torch.autograd.Function):
    """S -> S+ with the derivative of a matrix function (Daleckii-Krein): for S = Q diag(l) Q^T,
    d(S+) = Q (G o (Q^T dS Q)) Q^T with G_ij = (l_i+ - l_j+) / (l_i - l_j), and where l_i and l_j
    (nearly) coincide the derivative there, 1 above 0 and 0 below (1/2 at 0 exactly). eigh's own
    backward divides by l_i - l_j and gives NaN at repeated eigenvalues: at rest S = 0, all equal.
    The backward is written in differentiable ops, so a second derivative exists as well."""

    generate_vmap_rule = True  # (the ops' reference vjps run under torch.func)

    @staticmethod
    def forward(sym):
        values, vectors = torch.linalg.eigh(sym)
        return (vectors * torch.clamp(values, min=0.0).unsqueeze(-2)) @ vectors.transpose(-1, -2), values, vectors

    @staticmethod
    def setup_context(ctx, inputs, output):
        _, values, vectors = output
        ctx.mark_non_differentiable(values, vectors)
        ctx.save_for_backward(values, vectors)

    @staticmethod
    def backward(ctx, grad, _values, _vectors):
        values, vectors = ctx.saved_tensors
        return _positive_part_vjp(values, vectors, grad)


def _positive_part_vjp(values, vectors, grad):
    positive = torch.clamp(values, min=0.0)
    slope = (values > 0).to(values.dtype) + 0.5 * (values == 0).to(values.dtype)
    gap = values.unsqueeze(-1) - values.unsqueeze(-2)
    scale = values.abs().amax(-1, keepdim=True).unsqueeze(-1)
    close = gap.abs() <= 1e-12 * scale
    secant = (positive.unsqueeze(-1) - positive.unsqueeze(-2)) / torch.where(close, torch.ones_like(gap), gap)
    tangent = 0.5 * (slope.unsqueeze(-1) + slope.unsqueeze(-2))
    weights = torch.where(close, tangent, secant)
    inner = vectors.transpose(-1, -2) @ (0.5 * (grad + grad.transpose(-1, -2))) @ vectors
    return vectors @ (weights * inner) @ vectors.transpose(-1, -2)


def stvk_definite_dforces(u, du, m, vol, lam, mu, proj=None):
    """stvk's force differential with S+ (the positive part of S) in its geometric term dF S: a
    positive semi-definite tangent whatever the compression (``Material(tangent="definite")``).
    ``[N, n, d]``."""
    grad_u = displacement_gradient(u, m)
    grad_du = displacement_gradient(du, m)
    second_pk = _isotropic(green_strain(grad_u, proj), lam, mu, proj)
    d_strain = _project(_sym(grad_du + grad_u.transpose(-1, -2) @ grad_du), proj)
    d_second_pk = _isotropic(d_strain, lam, mu, proj)
    d_first_pk = grad_du @ positive_part(second_pk) + d_second_pk + grad_u @ d_second_pk
    return _nodal(d_first_pk, m, vol)


# Keyed by the kernel model (``kernel_model``): "stvk_definite" = stvk with the definite tangent.
FORCES = {"hooke": hooke_forces, "stvk": stvk_forces, "stvk_definite": stvk_forces}
DFORCES = {"hooke": hooke_dforces, "stvk": stvk_dforces, "stvk_definite": stvk_definite_dforces}
ENERGIES = {"hooke": hooke_energy, "stvk": stvk_energy, "stvk_definite": stvk_energy}


def kernel_model(group) -> str:
    """The model whose kernels evaluate ``group``: its model, or "stvk_definite" for stvk with
    ``tangent="definite"``."""
    return "stvk_definite" if group.model == "stvk" and getattr(group, "tangent", "exact") == "definite" \
        else group.model
